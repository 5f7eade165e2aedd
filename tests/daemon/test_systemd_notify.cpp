// sd_notify helpers, the event-loop watchdog, signal hooks and root refusal, against a
// real notification socket (a Unix datagram socket standing in for systemd's).
#include <poll.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <chrono>
#include <csignal>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>
#include <gtest/gtest.h>

#include "fettle/daemon/service.hpp"
#include "test_control_support.hpp"
#include "test_systemd_support.hpp"

namespace {

namespace service = fettle::daemon::service;
using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;

/// Receives what the service sends to NOTIFY_SOCKET; sets and clears the environment.
class NotifySocket {
 public:
  NotifySocket() {
    path_ = (dir_.path() / "notify").string();
    fd_ = ::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::strncpy(addr.sun_path, path_.c_str(), sizeof(addr.sun_path) - 1);
    if (::bind(fd_, reinterpret_cast<const sockaddr*>(&addr), sizeof addr) != 0) ADD_FAILURE() << "bind " << path_;
    ::setenv("NOTIFY_SOCKET", path_.c_str(), 1);
  }
  ~NotifySocket() {
    ::unsetenv("NOTIFY_SOCKET");
    ::unsetenv("WATCHDOG_USEC");
    ::unsetenv("WATCHDOG_PID");
    ::close(fd_);
  }
  NotifySocket(const NotifySocket&) = delete;
  NotifySocket& operator=(const NotifySocket&) = delete;

  /// The next datagram, or "" after the timeout.
  std::string receive(std::chrono::milliseconds timeout = 2000ms) {
    pollfd p{fd_, POLLIN, 0};
    if (::poll(&p, 1, static_cast<int>(timeout.count())) <= 0) return {};
    char buf[4096];
    const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
    return n > 0 ? std::string(buf, static_cast<std::size_t>(n)) : std::string{};
  }

  /// Every datagram until `within` has passed, with its arrival time.
  std::vector<std::pair<Clock::time_point, std::string>> collect(std::chrono::milliseconds within) {
    std::vector<std::pair<Clock::time_point, std::string>> got;
    const auto end = Clock::now() + within;
    while (Clock::now() < end) {
      const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(end - Clock::now());
      auto m = receive(std::max(left, 1ms));
      if (!m.empty()) got.emplace_back(Clock::now(), std::move(m));
    }
    return got;
  }

 private:
  fettle::test::TempDir dir_;
  std::string path_;
  int fd_ = -1;
};

TEST(ServiceNotify, OutsideSystemdEverythingIsANoOp) {
  ::unsetenv("NOTIFY_SOCKET");
  ::unsetenv("WATCHDOG_USEC");
  EXPECT_FALSE(service::under_systemd());
  EXPECT_FALSE(service::notify_ready("Idle"));
  EXPECT_FALSE(service::notify_status("Idle"));
  EXPECT_FALSE(service::notify_watchdog());
  EXPECT_FALSE(service::notify_stopping());
  EXPECT_FALSE(service::watchdog_interval().has_value());
  boost::asio::io_context io;
  service::Watchdog wd{io};
  EXPECT_FALSE(wd.enabled());
  EXPECT_FALSE(wd.start());
  EXPECT_EQ(io.poll(), 0U) << "no timer may be armed without a watchdog";
}

TEST(ServiceNotify, ReadyStatusStoppingReachTheNotifySocket) {
  NotifySocket sd;
  ASSERT_TRUE(service::under_systemd());
  EXPECT_TRUE(service::notify_ready("Idle"));
  EXPECT_EQ(sd.receive(), "READY=1\nSTATUS=Idle");
  EXPECT_TRUE(service::notify_status("Execute: cycle 42"));
  EXPECT_EQ(sd.receive(), "STATUS=Execute: cycle 42");
  EXPECT_TRUE(service::notify_ready());
  EXPECT_EQ(sd.receive(), "READY=1");
  EXPECT_TRUE(service::notify_stopping("stopping: SIGTERM"));
  EXPECT_EQ(sd.receive(), "STOPPING=1\nSTATUS=stopping: SIGTERM");
}

TEST(ServiceNotify, WatchdogIntervalComesFromTheEnvironmentForThisProcessOnly) {
  NotifySocket sd;
  ::setenv("WATCHDOG_USEC", "4000000", 1);
  ::setenv("WATCHDOG_PID", std::to_string(::getpid()).c_str(), 1);
  ASSERT_TRUE(service::watchdog_interval().has_value());
  EXPECT_EQ(*service::watchdog_interval(), 4s);
  ::setenv("WATCHDOG_PID", std::to_string(::getpid() + 1).c_str(), 1);  // meant for another process
  EXPECT_FALSE(service::watchdog_interval().has_value());
}

TEST(ServiceNotify, WatchdogPingsAtHalfTheIntervalFromTheLoop) {
  NotifySocket sd;
  ::setenv("WATCHDOG_USEC", "200000", 1);  // 200 ms -> a ping every 100 ms
  ::setenv("WATCHDOG_PID", std::to_string(::getpid()).c_str(), 1);
  boost::asio::io_context io;
  service::Watchdog wd{io};
  ASSERT_TRUE(wd.enabled());
  EXPECT_EQ(wd.ping_period(), 100ms);
  ASSERT_TRUE(wd.start());
  std::thread loop([&] { io.run_for(650ms); });
  const auto got = sd.collect(600ms);
  loop.join();
  ASSERT_GE(got.size(), 4U);
  EXPECT_LE(got.size(), 8U);
  for (const auto& [t, m] : got) EXPECT_EQ(m, "WATCHDOG=1");
  for (std::size_t i = 1; i < got.size(); ++i) {
    const auto gap = got[i].first - got[i - 1].first;
    EXPECT_LT(gap, 200ms) << "ping " << i << " came too late for a 200 ms watchdog";
  }
  const auto mean = (got.back().first - got.front().first) / static_cast<int>(got.size() - 1);
  EXPECT_GT(mean, 80ms) << "pings more often than half the interval";
  EXPECT_LT(mean, 150ms) << "pings less often than half the interval";
  std::size_t late = 0;  // sent after collect() stopped listening, before the loop stopped
  while (!sd.receive(50ms).empty()) ++late;
  EXPECT_EQ(wd.pings(), got.size() + late);
}

TEST(ServiceNotify, AStuckLoopStopsThePings) {
  NotifySocket sd;
  boost::asio::io_context io;
  service::Watchdog wd{io, std::chrono::microseconds{100000}};  // ping every 50 ms
  ASSERT_TRUE(wd.start());  // first ping at once
  EXPECT_EQ(sd.receive(), "WATCHDOG=1");
  boost::asio::steady_timer stuck{io};
  stuck.expires_after(100ms);
  stuck.async_wait([](const boost::system::error_code&) { std::this_thread::sleep_for(400ms); });  // a blocked loop
  std::thread loop([&] { io.run_for(700ms); });
  const auto got = sd.collect(650ms);
  loop.join();
  ASSERT_GE(got.size(), 3U);
  std::chrono::nanoseconds longest{0};
  for (std::size_t i = 1; i < got.size(); ++i) longest = std::max(longest, got[i].first - got[i - 1].first);
  EXPECT_GE(longest, 300ms) << "pings went on while the loop was blocked";
  wd.stop();
}

TEST(ServiceSignals, SigtermAndSigintArriveOnTheLoop) {
  boost::asio::io_context io;
  std::vector<int> seen;
  std::thread::id handler_thread;
  service::Signals signals{io, [&](int sig) {
                             seen.push_back(sig);
                             handler_thread = std::this_thread::get_id();
                             if (seen.size() == 2) io.stop();
                           }};
  std::thread loop([&] { io.run_for(3s); });
  std::this_thread::sleep_for(50ms);
  ASSERT_EQ(::kill(::getpid(), SIGTERM), 0);
  std::this_thread::sleep_for(50ms);
  ASSERT_EQ(::kill(::getpid(), SIGINT), 0);
  const auto loop_id = loop.get_id();
  loop.join();
  ASSERT_EQ(seen.size(), 2U);
  EXPECT_EQ(seen[0], SIGTERM);
  EXPECT_EQ(seen[1], SIGINT);
  EXPECT_EQ(handler_thread, loop_id);
}

TEST(ServiceUser, RootIsRefusedUnlessAllowed) {
  const auto st = service::check_user(false, 0U);
  ASSERT_FALSE(st);
  EXPECT_EQ(st.error().code, "service.root");
  EXPECT_NE(st.error().message.find("--allow-root"), std::string::npos) << st.error().message;
  EXPECT_NE(st.error().message.find("refuses to run as root"), std::string::npos) << st.error().message;
  EXPECT_TRUE(service::check_user(true, 0U));
  EXPECT_TRUE(service::check_user(false, 1000U));
  EXPECT_EQ(static_cast<bool>(service::check_user(false)), ::geteuid() != 0);
}

// The built fettled, as root without --allow-root: it stops before reading its config or
// opening anything. The config path does not exist, so a refusal that came after the config
// load would report the config instead.
TEST(ServiceUser, FettledAsRootWithoutTheFlagExitsBeforeReadingItsConfig) {
  if (::geteuid() != 0) GTEST_SKIP() << "not running as root: the refusal is reachable only as root (check_user itself is tested above)";
  const std::string fettled = std::string(FETTLE_BIN_DIR) + "/fettled";
  const std::string config = "/nonexistent-fettle-test/cell.toml";
  const auto r = fettle::test::run(fettle::test::quote(fettled) + " --config " + config);
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("refuses to run as root"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("--allow-root"), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find(config), std::string::npos) << "the config was read before the user check:\n" << r.output;
  // and with the flag the same command gets as far as the config, and names it
  const auto allowed = fettle::test::run(fettle::test::quote(fettled) + " --allow-root --config " + config);
  EXPECT_NE(allowed.exit_code, 0) << allowed.output;
  EXPECT_NE(allowed.output.find(config), std::string::npos) << allowed.output;
}

}  // namespace
