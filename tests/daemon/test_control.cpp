// The control socket server and client over real Unix sockets in a temp dir.
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <future>
#include <string>
#include <thread>
#include <vector>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <gtest/gtest.h>

#include "test_control_support.hpp"
#include "fettle/daemon/control.hpp"

namespace {

namespace control = fettle::daemon::control;
namespace fs = std::filesystem;
using control::json;
using namespace std::chrono_literals;
using fettle::test::ControlFixture;
using fettle::test::TempDir;

/// A raw connected Unix socket (for clients that misbehave).
int raw_connect(const fs::path& path) {
  const int fd = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  std::strncpy(addr.sun_path, path.c_str(), sizeof(addr.sun_path) - 1);
  if (::connect(fd, reinterpret_cast<const sockaddr*>(&addr), sizeof addr) != 0) {
    ::close(fd);
    return -1;
  }
  return fd;
}

/// A listening Unix socket on `path` that never accepts (the caller closes the fd).
int listen_unix(const fs::path& path, int backlog) {
  const int fd = ::socket(AF_UNIX, SOCK_STREAM, 0);
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  std::strncpy(addr.sun_path, path.c_str(), sizeof(addr.sun_path) - 1);
  EXPECT_EQ(::bind(fd, reinterpret_cast<const sockaddr*>(&addr), sizeof addr), 0) << path;
  EXPECT_EQ(::listen(fd, backlog), 0) << path;
  return fd;
}

/// Leaves a socket file nobody listens on (a daemon that crashed).
void make_stale_socket(const fs::path& path) {
  ::close(listen_unix(path, 1));  // the file stays, nobody listens
}

json ask(const fs::path& socket, const json& request) {
  auto r = control::call(socket, request, 5s);
  if (!r) ADD_FAILURE() << r.error().code << ": " << r.error().message;
  return r ? r.value() : json{};
}

TEST_F(ControlFixture, StatusRoundTripMergesHandlerFieldsAndEchoesId) {
  ASSERT_TRUE(start());
  const json r = ask(socket(), json{{"cmd", "status"}, {"id", 7}});
  EXPECT_EQ(r.value("ok", false), true) << r.dump();
  EXPECT_EQ(r.value("state", ""), "Idle");
  EXPECT_EQ(r.value("state_code", -1), 4);
  EXPECT_EQ(r.value("maintenance", true), false);
  EXPECT_EQ(r.value("id", 0), 7);
  EXPECT_EQ(handler.status_calls.load(), 1);
}

TEST_F(ControlFixture, LastCycleAndCyclesWrapTheHandlersValues) {
  ASSERT_TRUE(start());
  json r = ask(socket(), json{{"cmd", "last_cycle"}});
  ASSERT_TRUE(r.value("ok", false)) << r.dump();
  EXPECT_EQ(r["cycle"]["id"], "c-0005");

  r = ask(socket(), json{{"cmd", "cycles"}, {"limit", 3}});
  ASSERT_TRUE(r.value("ok", false)) << r.dump();
  ASSERT_TRUE(r["cycles"].is_array());
  EXPECT_EQ(r["cycles"].size(), 3U);
  EXPECT_EQ(r["cycles"][0]["id"], "c-0005");

  r = ask(socket(), json{{"cmd", "cycles"}});  // default limit covers all five
  EXPECT_EQ(r["cycles"].size(), 5U);

  for (const json& bad : {json{{"cmd", "cycles"}, {"limit", 0}}, json{{"cmd", "cycles"}, {"limit", "ten"}},
                          json{{"cmd", "cycles"}, {"limit", 2.5}}}) {
    r = ask(socket(), bad);
    EXPECT_FALSE(r.value("ok", true)) << bad.dump();
    EXPECT_EQ(r.value("code", ""), control::code::bad_argument) << bad.dump();
  }
}

TEST_F(ControlFixture, HandlerErrorsAreRepliedWithTheirCode) {
  handler.no_cycles = true;
  ASSERT_TRUE(start());
  const json r = ask(socket(), json{{"cmd", "last_cycle"}});
  EXPECT_FALSE(r.value("ok", true));
  EXPECT_EQ(r.value("code", ""), "records.unreadable");
  EXPECT_NE(r.value("error", "").find("journal"), std::string::npos);
}

TEST_F(ControlFixture, ResetHoldUnholdDryCycleAreRefusedOutsideMaintenance) {
  ASSERT_TRUE(start());
  for (const char* cmd : {"reset", "hold", "unhold", "dry_cycle"}) {
    const json r = ask(socket(), json{{"cmd", cmd}});
    EXPECT_FALSE(r.value("ok", true)) << cmd;
    EXPECT_EQ(r.value("code", ""), control::code::maintenance_required) << cmd;
    EXPECT_NE(r.value("error", "").find("maintenance mode"), std::string::npos) << r.dump();
  }
  EXPECT_EQ(handler.commands.load(), 0) << "the handler must not see gated commands";

  json r = ask(socket(), json{{"cmd", "maintenance"}, {"on", true}});
  ASSERT_TRUE(r.value("ok", false)) << r.dump();
  EXPECT_TRUE(r.value("maintenance", false));
  EXPECT_EQ(ask(socket(), json{{"cmd", "status"}}).value("maintenance", false), true);

  r = ask(socket(), json{{"cmd", "reset"}});
  EXPECT_TRUE(r.value("ok", false)) << r.dump();
  EXPECT_EQ(r.value("state", ""), "Resetting");
  r = ask(socket(), json{{"cmd", "hold"}});
  EXPECT_EQ(r.value("state", ""), "Holding");
  r = ask(socket(), json{{"cmd", "unhold"}});
  EXPECT_EQ(r.value("state", ""), "Unholding");
  r = ask(socket(), json{{"cmd", "dry_cycle"}});
  EXPECT_TRUE(r.value("ok", false));
  EXPECT_EQ(r.value("cycle_id", ""), "dry-1");
  EXPECT_EQ(handler.commands.load(), 4);

  r = ask(socket(), json{{"cmd", "maintenance"}, {"on", false}});
  EXPECT_FALSE(r.value("maintenance", true));
  EXPECT_EQ(ask(socket(), json{{"cmd", "reset"}}).value("code", ""), control::code::maintenance_required);
  EXPECT_EQ(handler.commands.load(), 4);
}

// A new wheel after a tool.worn fault: maintenance mode only, the tool named, an unknown one
// refused with the handler's reason.
TEST_F(ControlFixture, ToolChangedNeedsMaintenanceAndATool) {
  ASSERT_TRUE(start());
  json r = ask(socket(), json{{"cmd", "tool_changed"}, {"tool", "flat-16"}});
  EXPECT_EQ(r.value("code", ""), control::code::maintenance_required) << r.dump();
  EXPECT_EQ(handler.commands.load(), 0);
  ASSERT_TRUE(ask(socket(), json{{"cmd", "maintenance"}, {"on", true}}).value("ok", false));
  r = ask(socket(), json{{"cmd", "tool_changed"}});
  EXPECT_EQ(r.value("code", ""), control::code::bad_argument) << r.dump();
  EXPECT_NE(r.value("error", "").find("\"tool\""), std::string::npos) << r.dump();
  r = ask(socket(), json{{"cmd", "tool_changed"}, {"tool", "flat-61"}});
  EXPECT_EQ(r.value("code", ""), "fettled.unknown_tool") << r.dump();
  EXPECT_NE(r.value("error", "").find("flat-61"), std::string::npos) << r.dump();
  r = ask(socket(), json{{"cmd", "tool_changed"}, {"tool", "flat-16"}});
  EXPECT_TRUE(r.value("ok", false)) << r.dump();
  EXPECT_EQ(r.value("tool", ""), "flat-16");
  EXPECT_EQ(handler.tool_changed_name, "flat-16");
}

TEST_F(ControlFixture, HandlerCanRefuseMaintenanceMode) {
  handler.refuse_maintenance = true;
  ASSERT_TRUE(start());
  const json r = ask(socket(), json{{"cmd", "maintenance"}, {"on", true}});
  EXPECT_FALSE(r.value("ok", true));
  EXPECT_EQ(r.value("code", ""), "packml.busy");
  EXPECT_FALSE(ask(socket(), json{{"cmd", "maintenance"}}).value("maintenance", true));
  EXPECT_EQ(ask(socket(), json{{"cmd", "maintenance"}, {"on", "yes"}}).value("code", ""),
            control::code::bad_argument);
}

TEST_F(ControlFixture, MalformedRequestsGetAnErrorAndTheConnectionGoesOn) {
  ASSERT_TRUE(start());
  auto client = control::Client::connect(socket());
  ASSERT_TRUE(client) << client.error().message;
  const std::vector<std::pair<std::string, std::string>> cases{
      {"{not json\n", control::code::bad_json},
      {"[1,2,3]\n", control::code::bad_json},
      {"\"status\"\n", control::code::bad_json},
      {"{\"command\":\"status\"}\n", control::code::bad_argument},
      {"{\"cmd\":42}\n", control::code::bad_argument},
      {"{\"cmd\":\"launch\"}\n", control::code::unknown_command},
      {std::string("{\"cmd\":\"st\xff\xfe\"}\n"), control::code::bad_json},  // invalid UTF-8
      {std::string("\0\0\0\n", 4), control::code::bad_json},
  };
  for (const auto& [line, code] : cases) {
    auto r = client->request_raw(line, 5s);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_FALSE(r->value("ok", true)) << line;
    EXPECT_EQ(r->value("code", ""), code) << line << " -> " << r->dump();
  }
  // Blank lines are ignored, CRLF accepted, and two requests in one write get two replies in order.
  auto r = client->request_raw("\n\r\n{\"cmd\":\"status\",\"id\":1}\r\n{\"cmd\":\"maintenance\",\"id\":2}\n", 5s);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_EQ(r->value("id", 0), 1);
  r = client->request_raw("", 5s);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_EQ(r->value("id", 0), 2);
}

TEST_F(ControlFixture, OversizeLinesAreRefusedAndTheRestOfTheLineSkipped) {
  ASSERT_TRUE(start());
  auto client = control::Client::connect(socket());
  ASSERT_TRUE(client) << client.error().message;
  // 100 KiB of one line, then a valid request on the same connection.
  const std::string big = "{\"cmd\":\"status\",\"pad\":\"" + std::string(100 * 1024, 'x') + "\"}\n";
  auto r = client->request_raw(big + "{\"cmd\":\"status\",\"id\":9}\n", 5s);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_EQ(r->value("code", ""), control::code::line_too_long);
  EXPECT_NE(r->value("error", "").find("65536"), std::string::npos) << r->dump();
  r = client->request_raw("", 5s);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_TRUE(r->value("ok", false)) << r->dump();
  EXPECT_EQ(r->value("id", 0), 9);

  // A line exactly at the limit is still accepted.
  const std::string prefix = "{\"cmd\":\"status\",\"id\":3,\"pad\":\"";
  const std::string at_limit = prefix + std::string(64 * 1024 - prefix.size() - 2, 'y') + "\"}";
  ASSERT_EQ(at_limit.size(), 64U * 1024U);
  r = client->request_raw(at_limit + "\n", 5s);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_EQ(r->value("id", 0), 3) << r->dump().substr(0, 200);

  // Endless bytes without a newline: one error reply, memory bounded, the server lives.
  auto flood = control::Client::connect(socket());
  ASSERT_TRUE(flood);
  r = flood->request_raw(std::string(1024 * 1024, 'z'), 5s);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_EQ(r->value("code", ""), control::code::line_too_long);
  EXPECT_TRUE(ask(socket(), json{{"cmd", "status"}}).value("ok", false));
}

TEST_F(ControlFixture, AThrowingHandlerGivesHandlerFailedAndTheServerGoesOn) {
  handler.throw_on_status = true;
  ASSERT_TRUE(start());
  const json r = ask(socket(), json{{"cmd", "status"}});
  EXPECT_FALSE(r.value("ok", true));
  EXPECT_EQ(r.value("code", ""), control::code::handler_failed);
  handler.throw_on_status = false;
  EXPECT_TRUE(ask(socket(), json{{"cmd", "status"}}).value("ok", false));
}

TEST_F(ControlFixture, SocketHasMode0660) {
  ASSERT_TRUE(start());
  struct stat st {};
  ASSERT_EQ(::lstat(socket().c_str(), &st), 0);
  EXPECT_TRUE(S_ISSOCK(st.st_mode));
  EXPECT_EQ(st.st_mode & 07777U, 0660U);
}

TEST_F(ControlFixture, SocketModeFollowsTheOptionEvenUnderAPermissiveUmask) {
  options.mode = 0600;
  const ::mode_t old = ::umask(0);
  const bool started = start();
  ::umask(old);
  ASSERT_TRUE(started);
  struct stat st {};
  ASSERT_EQ(::lstat(socket().c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 07777U, 0600U);
}

TEST_F(ControlFixture, RefusesAWorldWritableDirectory) {
  ASSERT_EQ(::chmod(dir.path().c_str(), 01777), 0);
  const auto st = server().start();
  ASSERT_FALSE(st);
  EXPECT_EQ(st.error().code, "control.socket_dir");
  EXPECT_NE(st.error().message.find("world-writable"), std::string::npos) << st.error().message;
  EXPECT_NE(st.error().message.find(dir.path().string()), std::string::npos) << st.error().message;
  EXPECT_FALSE(fs::exists(socket()));
}

TEST_F(ControlFixture, RefusesAMissingDirectoryAndANonSocketPath) {
  options.socket_path = dir.path() / "missing" / "fettled.sock";
  auto st = server().start();
  ASSERT_FALSE(st);
  EXPECT_EQ(st.error().code, "control.socket_dir");

  reset_server();
  options.socket_path = dir.path() / "plain-file";
  std::ofstream{options.socket_path} << "not a socket";
  st = server().start();
  ASSERT_FALSE(st);
  EXPECT_EQ(st.error().code, "control.socket_exists");
  EXPECT_TRUE(fs::exists(options.socket_path)) << "a file that is not ours must not be removed";
}

TEST_F(ControlFixture, RemovesAStaleSocketAndServes) {
  make_stale_socket(socket());
  ASSERT_TRUE(fs::exists(socket()));
  {
    auto c = control::Client::connect(socket(), 1s);
    ASSERT_FALSE(c);
    EXPECT_EQ(c.error().code, control::code::not_running);
  }
  ASSERT_TRUE(start());
  EXPECT_TRUE(ask(socket(), json{{"cmd", "status"}}).value("ok", false));
}

TEST_F(ControlFixture, RefusesALiveSocketAndLeavesItsOwnerAlone) {
  ASSERT_TRUE(start());
  boost::asio::io_context io2;
  fettle::test::FakeHandler handler2;
  control::Server second{io2, handler2, options};
  const auto st = second.start();
  ASSERT_FALSE(st);
  EXPECT_EQ(st.error().code, "control.socket_in_use");
  EXPECT_TRUE(ask(socket(), json{{"cmd", "status"}}).value("ok", false)) << "the first server must still answer";
}

TEST_F(ControlFixture, StopRemovesTheSocketFile) {
  ASSERT_TRUE(start());
  ASSERT_TRUE(fs::exists(socket()));
  stop_loop();
  reset_server();
  EXPECT_FALSE(fs::exists(socket()));
  auto c = control::Client::connect(socket(), 1s);
  ASSERT_FALSE(c);
  EXPECT_EQ(c.error().code, control::code::not_running);
}

TEST_F(ControlFixture, ManyConcurrentClientsAllGetTheirReplies) {
  ASSERT_TRUE(start());
  constexpr int clients = 16;
  constexpr int requests = 50;
  std::atomic<int> good{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < clients; ++t)
    threads.emplace_back([&, t] {
      auto c = control::Client::connect(socket(), 5s);
      if (!c) return;
      for (int i = 0; i < requests; ++i) {
        auto r = c->request(json{{"cmd", "status"}, {"id", t * 1000 + i}}, 5s);
        if (r && r->value("ok", false) && r->value("id", -1) == t * 1000 + i) ++good;
      }
    });
  for (auto& th : threads) th.join();
  EXPECT_EQ(good.load(), clients * requests);
  EXPECT_EQ(handler.status_calls.load(), clients * requests);
}

TEST_F(ControlFixture, AStalledClientDoesNotBlockOthersAndIsDroppedWhenItStopsReading) {
  options.write_timeout = 300ms;
  ASSERT_TRUE(start());
  // 1: sends half a request and waits forever.
  const int half = raw_connect(socket());
  ASSERT_GE(half, 0);
  ASSERT_GT(::send(half, "{\"cmd\":\"sta", 11, MSG_NOSIGNAL), 0);
  // 2: floods requests and never reads a reply (fills both socket buffers).
  const int deaf = raw_connect(socket());
  ASSERT_GE(deaf, 0);
  int flags = 0;
  (void)flags;
  std::string burst;
  for (int i = 0; i < 2000; ++i) burst += "{\"cmd\":\"status\"}\n";
  std::thread flooder([&] {
    for (int i = 0; i < 50; ++i)
      if (::send(deaf, burst.data(), burst.size(), MSG_NOSIGNAL | MSG_DONTWAIT) < 0 && errno != EAGAIN) break;
  });
  // Meanwhile others are served promptly.
  for (int i = 0; i < 20; ++i) {
    const auto t0 = std::chrono::steady_clock::now();
    auto r = control::call(socket(), json{{"cmd", "status"}}, 2s);
    ASSERT_TRUE(r) << r.error().message;
    EXPECT_TRUE(r->value("ok", false));
    EXPECT_LT(std::chrono::steady_clock::now() - t0, 1s);
  }
  flooder.join();
  // The deaf client is dropped after the write timeout; the half-line one stays (idle timeout off).
  const auto deadline = std::chrono::steady_clock::now() + 5s;
  std::size_t n = 99;
  while (std::chrono::steady_clock::now() < deadline) {
    n = client_count();
    if (n == 1) break;
    std::this_thread::sleep_for(20ms);
  }
  EXPECT_EQ(n, 1U) << "only the half-line client should remain";
  ::close(half);
  ::close(deaf);
}

TEST_F(ControlFixture, IdleClientsAreClosed) {
  options.idle_timeout = 200ms;
  ASSERT_TRUE(start());
  const int fd = raw_connect(socket());
  ASSERT_GE(fd, 0);
  timeval tv{3, 0};
  ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
  char c = 0;
  const auto t0 = std::chrono::steady_clock::now();
  EXPECT_EQ(::recv(fd, &c, 1, 0), 0) << "expected the server to close the idle connection";
  EXPECT_LT(std::chrono::steady_clock::now() - t0, 2s);
  ::close(fd);
}

TEST_F(ControlFixture, OneClientTooManyIsToldWhyAndASlotFreesWhenOneLeaves) {
  options.max_clients = 2;
  options.privileged_slot = false;  // the tests run as root: the third would get a's slot once idle
  ASSERT_TRUE(start());
  auto b = control::Client::connect(socket());
  ASSERT_TRUE(b);
  ASSERT_TRUE(b->request(json{{"cmd", "status"}}));
  {
    auto a = control::Client::connect(socket());
    ASSERT_TRUE(a);
    ASSERT_TRUE(a->request(json{{"cmd", "status"}}));  // both accepted before the third comes
    auto c = control::Client::connect(socket());
    ASSERT_TRUE(c);
    auto r = c->request(json{{"cmd", "status"}}, 2s);
    if (r) {
      EXPECT_EQ(r->value("code", ""), control::code::too_many_clients) << r->dump();
    } else {
      EXPECT_EQ(r.error().code, control::code::io) << r.error().message;  // closed before our write landed
    }
  }  // a leaves
  const auto deadline = std::chrono::steady_clock::now() + 3s;
  while (client_count() > 1 && std::chrono::steady_clock::now() < deadline) std::this_thread::sleep_for(10ms);
  auto d = control::Client::connect(socket());
  ASSERT_TRUE(d);
  auto r = d->request(json{{"cmd", "status"}}, 2s);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_TRUE(r->value("ok", false)) << r->dump();
}

// A client that drips one byte now and then, never finishing its line, held its slot until
// the 10-minute idle timeout: 32 of them locked every `fettle status` out (issue 40, item 5).
TEST_F(ControlFixture, ADrippingClientIsDroppedAtTheRequestDeadline) {
  options.request_timeout = 300ms;
  ASSERT_TRUE(start());
  const int fd = raw_connect(socket());
  ASSERT_GE(fd, 0);
  const auto t0 = std::chrono::steady_clock::now();
  bool closed = false;
  for (int i = 0; i < 30 && !closed; ++i) {  // a byte every 100 ms: never idle, never complete
    if (::send(fd, "{", 1, MSG_NOSIGNAL) != 1) closed = true;
    char c = 0;
    if (::recv(fd, &c, 1, MSG_DONTWAIT) == 0) closed = true;
    std::this_thread::sleep_for(100ms);
  }
  EXPECT_TRUE(closed) << "a line never completed kept its slot for 3 s";
  EXPECT_LT(std::chrono::steady_clock::now() - t0, 2s);
  ::close(fd);
  // one that sends nothing at all is dropped at the same deadline
  const int quiet = raw_connect(socket());
  ASSERT_GE(quiet, 0);
  timeval tv{3, 0};
  ::setsockopt(quiet, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
  char c = 0;
  EXPECT_EQ(::recv(quiet, &c, 1, 0), 0);
  ::close(quiet);
}

// All slots held by clients that made one request and then sit idle: a client of root or of the
// daemon's own user (the tests run as either) still gets its answer, for which the client idle
// longest is dropped. Clients that are busy are never dropped for it (the test above:
// OneClientTooManyIsToldWhyAndASlotFreesWhenOneLeaves).
TEST_F(ControlFixture, AFullServerStillAnswersRootByDroppingItsLongestIdleClient) {
  options.max_clients = 4;
  options.request_timeout = 200ms;
  ASSERT_TRUE(start());
  std::vector<int> idle;
  for (int i = 0; i < 4; ++i) {
    const int fd = raw_connect(socket());
    ASSERT_GE(fd, 0);
    ASSERT_EQ(::send(fd, "{\"cmd\":\"status\"}\n", 17, MSG_NOSIGNAL), 17);
    char buf[4096];
    ASSERT_GT(::recv(fd, buf, sizeof buf, 0), 0);
    idle.push_back(fd);
    std::this_thread::sleep_for(20ms);  // the first is the one idle longest
  }
  std::this_thread::sleep_for(300ms);
  ASSERT_EQ(client_count(), 4U);
  const auto r = ask(socket(), json{{"cmd", "status"}});
  EXPECT_TRUE(r.value("ok", false)) << r.dump();
  char c = 0;
  EXPECT_EQ(::recv(idle.front(), &c, 1, MSG_DONTWAIT), 0) << "the client idle longest made room";
  for (int fd : idle) ::close(fd);
}

// 300 connects at once: the listen backlog of 16 refused most of them at connect (EAGAIN); now
// they wait to be accepted and are told too_many_clients, and status still answers.
TEST_F(ControlFixture, ABurstOfConnectsIsNotRefusedByTheBacklog) {
  options.max_clients = 8;
  ASSERT_TRUE(start());
  std::vector<int> fds;
  int refused = 0;
  for (int i = 0; i < 300; ++i) {  // non-blocking, as a probe would: a full backlog is EAGAIN
    const int fd = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::strncpy(addr.sun_path, socket().c_str(), sizeof(addr.sun_path) - 1);
    if (::connect(fd, reinterpret_cast<const sockaddr*>(&addr), sizeof addr) != 0) ++refused;
    fds.push_back(fd);
  }
  EXPECT_EQ(refused, 0);
  for (int fd : fds) ::close(fd);
  const auto r = ask(socket(), json{{"cmd", "status"}});
  EXPECT_TRUE(r.value("ok", false)) << r.dump();
}

TEST(ControlClient, NoServerSaysIsFettledRunning) {
  TempDir dir;
  const fs::path path = dir.path() / "fettled.sock";
  auto c = control::Client::connect(path, 1s);
  ASSERT_FALSE(c);
  EXPECT_EQ(c.error().code, control::code::not_running);
  EXPECT_NE(c.error().message.find("is fettled running? socket " + path.string()), std::string::npos)
      << c.error().message;

  make_stale_socket(path);
  c = control::Client::connect(path, 1s);
  ASSERT_FALSE(c);
  EXPECT_EQ(c.error().message, "is fettled running? socket " + path.string() + ": connection refused");
}

TEST(ControlClient, AServerThatNeverRepliesTimesOut) {
  TempDir dir;
  const fs::path path = dir.path() / "mute.sock";
  const int fd = listen_unix(path, 4);
  const auto t0 = std::chrono::steady_clock::now();
  auto r = control::call(path, json{{"cmd", "status"}}, 300ms);
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, control::code::timeout);
  EXPECT_LT(std::chrono::steady_clock::now() - t0, 2s);
  ::close(fd);
}

TEST(ControlServer, HandleWorksWithoutASocket) {
  boost::asio::io_context io;
  fettle::test::FakeHandler handler;
  control::Server server{io, handler, {}};
  EXPECT_EQ(server.handle(json{{"cmd", "status"}}).value("state", ""), "Idle");
  EXPECT_EQ(server.handle(json{{"cmd", "hold"}}).value("code", ""), control::code::maintenance_required);
  server.set_maintenance(true);
  EXPECT_TRUE(server.handle(json{{"cmd", "hold"}}).value("ok", false));
  EXPECT_EQ(server.handle(json::array()).value("code", ""), control::code::bad_json);
}

}  // namespace
