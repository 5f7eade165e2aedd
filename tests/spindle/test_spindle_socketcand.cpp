// The master and the simulated drive over socketcand's rawmode protocol on loopback TCP:
// in one process (SocketcandServer on an in-process bus) and across processes
// (`fettle-sim spindle --listen 127.0.0.1:0`).
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <string>
#include <thread>

#include <gtest/gtest.h>

#include <boost/asio/connect.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/read_until.hpp>
#include <boost/asio/streambuf.hpp>
#include <boost/asio/write.hpp>

#include "fettle/drivers/spindle.hpp"
#include "fettle/sim/spindle.hpp"
#include "spindle_test_util.hpp"
#include "../support/raw_tcp_peer.hpp"

using namespace fettle::canopen;
using fettle::Status;
using fettle::drivers::SpindleDrive;
using fettle::drivers::SpindleEvent;
using fettle::drivers::SpindleOptions;
using fettle::test::await;
using fettle::test::run_until;
using namespace std::chrono_literals;

namespace {

/// A child process with pipes on stdin and stdout.
class Child {
 public:
  explicit Child(std::vector<std::string> argv) {
    int in[2];
    int out[2];
    if (::pipe(in) != 0 || ::pipe(out) != 0) throw std::runtime_error("pipe failed");
    pid_ = ::fork();
    if (pid_ == 0) {
      ::dup2(in[0], STDIN_FILENO);
      ::dup2(out[1], STDOUT_FILENO);
      ::close(in[1]);
      ::close(out[0]);
      std::vector<char*> args;
      for (auto& a : argv) args.push_back(a.data());
      args.push_back(nullptr);
      ::execv(args[0], args.data());
      ::_exit(127);
    }
    ::close(in[0]);
    ::close(out[1]);
    stdin_ = in[1];
    stdout_ = out[0];
  }
  ~Child() {
    if (pid_ > 0) {
      ::kill(pid_, SIGTERM);
      int status = 0;
      ::waitpid(pid_, &status, 0);
    }
    ::close(stdin_);
    ::close(stdout_);
  }
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;

  /// The next stdout line, or "" after `timeout`.
  std::string read_line(std::chrono::milliseconds timeout) {
    const auto end = std::chrono::steady_clock::now() + timeout;
    while (true) {
      if (auto nl = buffer_.find('\n'); nl != std::string::npos) {
        auto line = buffer_.substr(0, nl);
        buffer_.erase(0, nl + 1);
        return line;
      }
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(end - std::chrono::steady_clock::now());
      if (left.count() <= 0) return "";
      pollfd p{stdout_, POLLIN, 0};
      if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) return "";
      char chunk[256];
      const auto n = ::read(stdout_, chunk, sizeof chunk);
      if (n <= 0) return "";
      buffer_.append(chunk, static_cast<std::size_t>(n));
    }
  }
  void write_line(const std::string& line) {
    const std::string s = line + "\n";
    ASSERT_EQ(::write(stdin_, s.data(), s.size()), static_cast<ssize_t>(s.size()));
  }

 private:
  pid_t pid_ = -1;
  int stdin_ = -1;
  int stdout_ = -1;
  std::string buffer_;
};

class SpindleSocketcandTest : public ::testing::Test {
 protected:
  boost::asio::io_context io;
  std::vector<SpindleEvent> events;
  bool saw(SpindleEvent::Kind k) const {
    return std::any_of(events.begin(), events.end(), [k](const auto& e) { return e.kind == k; });
  }
};

}  // namespace

TEST_F(SpindleSocketcandTest, ServerSpeaksTheHandshakeAndRejectsAnUnknownBus) {
  auto bus = InProcessBus::create();
  fettle::sim::SocketcandServer server(io, bus, "127.0.0.1", 0, "can0");
  ASSERT_GT(server.port(), 0);
  std::atomic<bool> finished{false};
  std::thread client([port = server.port(), &finished] {
    boost::asio::io_context cio;
    boost::asio::ip::tcp::socket s(cio);
    s.connect({boost::asio::ip::make_address("127.0.0.1"), static_cast<unsigned short>(port)});
    boost::asio::streambuf buf;
    auto next = [&] {
      boost::asio::read_until(s, buf, '>');
      std::istream is(&buf);
      std::string el;
      std::getline(is, el, '>');
      return el + ">";
    };
    EXPECT_EQ(next(), "< hi >");
    boost::asio::write(s, boost::asio::buffer(std::string("< open can9 >")));
    EXPECT_NE(next().find("< error"), std::string::npos);
    boost::asio::write(s, boost::asio::buffer(std::string("< open can0 >")));
    EXPECT_EQ(next(), "< ok >");
    boost::asio::write(s, boost::asio::buffer(std::string("< rawmode >")));
    EXPECT_EQ(next(), "< ok >");
    finished = true;
  });
  // Serve the handshake while the client thread runs, then see the session end when it leaves.
  const bool served = run_until(io, [&] { return finished.load(); });
  client.join();
  ASSERT_TRUE(served);
  EXPECT_TRUE(run_until(io, [&] { return server.clients() == 0; }));
}

TEST_F(SpindleSocketcandTest, MasterSpinsUpTheDriveThroughAnInProcessSocketcandServer) {
  auto bus = InProcessBus::create();
  fettle::sim::SocketcandServer server(io, bus, "127.0.0.1", 0, "can0");
  fettle::sim::SimulatedSpindleDrive drive(io, bus->attach(io, "drive"));
  drive.power_on();
  SpindleDrive master(io, open_socketcand(io, "127.0.0.1", server.port(), "can0"), SpindleOptions{});
  EXPECT_TRUE(master.configure().ok());
  master.on_event([this](const SpindleEvent& e) { events.push_back(e); });
  Status s = await(io, [&](auto h) { master.activate_async(h); });
  ASSERT_TRUE(s.ok()) << s.error().message;
  s = await(io, [&](auto h) { master.spin_up(4000, h); });
  ASSERT_TRUE(s.ok()) << s.error().message;
  EXPECT_NEAR(drive.velocity_rpm(), 4000.0, 100.0);

  // The server goes away: the link loss is a latched fault, reported as an event.
  server.disconnect_all();
  ASSERT_TRUE(run_until(io, [&] { return master.status().fault.has_value(); }));
  EXPECT_EQ(master.status().fault->code, "spindle.link_lost");
  EXPECT_TRUE(saw(SpindleEvent::Kind::link_error));
}

TEST_F(SpindleSocketcandTest, ConnectionRefusedIsALinkErrorThatFailsStart) {
  // Find a free port, then close it so nothing listens there.
  int port = 0;
  {
    boost::asio::ip::tcp::acceptor a(io, {boost::asio::ip::make_address("127.0.0.1"), 0});
    port = a.local_endpoint().port();
  }
  SpindleDrive master(io, open_socketcand(io, "127.0.0.1", port, "can0"), SpindleOptions{});
  EXPECT_TRUE(master.configure().ok());
  const Status s = await(io, [&](auto h) { master.activate_async(h); });
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code, "spindle.link_lost");
  EXPECT_NE(s.error().message.find("connect"), std::string::npos) << s.error().message;
}

TEST_F(SpindleSocketcandTest, MasterDrivesFettleSimSpindleInAnotherProcess) {
  const std::string sim = std::string(FETTLE_BIN_DIR) + "/fettle-sim";
  if (::access(sim.c_str(), X_OK) != 0) GTEST_SKIP() << sim << " is not built";
  Child child({sim, "spindle", "--listen", "127.0.0.1:0"});
  const std::string line = child.read_line(5000ms);
  ASSERT_EQ(line.rfind("listening 127.0.0.1:", 0), 0U) << "first line: '" << line << "'";
  const int port = std::stoi(line.substr(line.rfind(':') + 1));
  ASSERT_GT(port, 0);

  SpindleDrive master(io, open_socketcand(io, "127.0.0.1", port, "can0"), SpindleOptions{});
  EXPECT_TRUE(master.configure().ok());
  master.on_event([this](const SpindleEvent& e) { events.push_back(e); });
  Status s = await(io, [&](auto h) { master.activate_async(h); });
  ASSERT_TRUE(s.ok()) << s.error().message;
  s = await(io, [&](auto h) { master.spin_up(5000, h); });
  ASSERT_TRUE(s.ok()) << s.error().message;
  EXPECT_NEAR(master.status().velocity_rpm, 5000.0, 100.0);

  child.write_line("removal 60");
  ASSERT_TRUE(run_until(io, [&] { return master.status().current_a > 3.0; })) << master.status().current_a;

  child.write_line("fault overtemperature");
  ASSERT_TRUE(run_until(io, [&] { return master.status().fault.has_value(); }));
  EXPECT_NE(master.status().fault->message.find("0x4310"), std::string::npos) << master.status().fault->message;
  s = await(io, [&](auto h) { master.fault_reset(h); });
  EXPECT_TRUE(s.ok()) << s.error().message;
  s = await(io, [&](auto h) { master.spin_down(h); });
  EXPECT_TRUE(s.ok()) << s.error().message;
}

// Bad peers on the socketcand link (issue 11): a server that says nothing, one that is not
// socketcand at all, one whose element never ends, one that sends a malformed frame. Each makes
// start() fail with an error that says what came, in bounded time; none crashes or hangs.
namespace {

using fettle::test::RawTcpPeer;

SpindleOptions quick_options() {
  SpindleOptions o;
  o.step_timeout_ms = 300;
  o.sdo_timeout_ms = 200;
  return o;
}

/// Reads on `fd` until the text received contains `what` (false after 2 s or on close).
bool read_until_text(RawTcpPeer& peer, int fd, const std::string& what) {
  std::string got;
  const auto end = std::chrono::steady_clock::now() + 2s;
  while (std::chrono::steady_clock::now() < end && !peer.stop_requested()) {
    got += peer.read_some(fd, 50ms);
    if (got.find(what) != std::string::npos) return true;
  }
  return false;
}

class SpindleSocketcandBadPeer : public SpindleSocketcandTest {
 protected:
  /// start() against `peer`, with short timeouts.
  Status start_against(const RawTcpPeer& peer) {
    SpindleDrive master(io, open_socketcand(io, "127.0.0.1", peer.port(), "can0"), quick_options());
    EXPECT_TRUE(master.configure().ok());
    master.on_event([this](const SpindleEvent& e) { events.push_back(e); });
    return await(io, [&](auto h) { master.activate_async(h); }, 5000ms);
  }
};

}  // namespace

TEST_F(SpindleSocketcandBadPeer, SilentServerFailsStartWithItsTimeoutNotAHang) {
  RawTcpPeer peer([](RawTcpPeer& p, int fd) { p.hold(fd, 4s); });
  const auto t0 = std::chrono::steady_clock::now();
  const Status s = start_against(peer);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.error().code, "test.no_completion") << s.error().message;
  EXPECT_EQ(s.error().code.rfind("spindle.", 0), 0U) << s.error().code << ": " << s.error().message;
  EXPECT_LT(std::chrono::steady_clock::now() - t0, 3s);
  EXPECT_EQ(peer.connections(), 1);
}

TEST_F(SpindleSocketcandBadPeer, AServerThatIsNotSocketcandIsALinkErrorNamingWhatItSaid) {
  RawTcpPeer peer([](RawTcpPeer& p, int fd) {
    (void)RawTcpPeer::send(fd, "HTTP/1.1 400 Bad Request\r\nContent-Type: text/html\r\n\r\n<html><body>no</body></html>");
    p.hold(fd, 4s);
  });
  const Status s = start_against(peer);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code, "spindle.link_lost") << s.error().message;
  EXPECT_NE(s.error().message.find("expected '< hi >'"), std::string::npos) << s.error().message;
  EXPECT_NE(s.error().message.find("html"), std::string::npos) << s.error().message;
  EXPECT_TRUE(saw(SpindleEvent::Kind::link_error));
}

TEST_F(SpindleSocketcandBadPeer, AnElementThatNeverEndsIsCutAfter256Characters) {
  RawTcpPeer peer([](RawTcpPeer& p, int fd) {
    (void)RawTcpPeer::send(fd, "< hi " + std::string(100000, 'x'));
    p.hold(fd, 4s);
  });
  const Status s = start_against(peer);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code, "spindle.link_lost") << s.error().message;
  EXPECT_NE(s.error().message.find("256 characters"), std::string::npos) << s.error().message;
}

TEST_F(SpindleSocketcandBadPeer, AMalformedFrameAfterTheHandshakeIsALinkErrorNamingIt) {
  std::atomic<bool> handshake{false};
  RawTcpPeer peer([&handshake](RawTcpPeer& p, int fd) {
    (void)RawTcpPeer::send(fd, "< hi >");
    if (!read_until_text(p, fd, "< open can0 >")) return;
    (void)RawTcpPeer::send(fd, "< ok >");
    if (!read_until_text(p, fd, "< rawmode >")) return;
    (void)RawTcpPeer::send(fd, "< ok >");
    handshake = true;
    (void)RawTcpPeer::send(fd, "< frame 7G1 1.000000 zz >");
    p.hold(fd, 4s);
  });
  const Status s = start_against(peer);
  EXPECT_TRUE(handshake.load());
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code, "spindle.link_lost") << s.error().message;
  EXPECT_NE(s.error().message.find("cannot parse"), std::string::npos) << s.error().message;
  EXPECT_NE(s.error().message.find("7G1"), std::string::npos) << s.error().message;
}
