// `fettle-sim robot --listen 127.0.0.1:0` as a user runs it: it prints the bound port,
// a RobotLink connects, uploads and runs; SIGTERM ends it with exit code 0.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <regex>
#include <string>

#include <boost/asio/io_context.hpp>

#include "fettle/drivers/robot_link.hpp"

using namespace std::chrono_literals;
using fettle::drivers::RobotState;

namespace {

struct Child {
  pid_t pid = -1;
  FILE* out = nullptr;
};

Child spawn(const std::vector<std::string>& args) {
  int fds[2];
  if (::pipe(fds) != 0) return {};
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::dup2(fds[1], 1);
    ::close(fds[0]);
    ::close(fds[1]);
    std::vector<char*> argv;
    for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    ::execv(argv[0], argv.data());
    ::_exit(127);
  }
  ::close(fds[1]);
  return {pid, ::fdopen(fds[0], "r")};
}

}  // namespace

TEST(RobotSimCli, PrintsThePortAndServesARobotLink) {
  const std::string exe = std::string(FETTLE_BIN_DIR) + "/fettle-sim";
  Child c = spawn({exe, "--log-level", "warn", "robot", "--listen", "127.0.0.1:0", "--speedup", "0"});
  ASSERT_GT(c.pid, 0);
  ASSERT_NE(c.out, nullptr);
  char line[256] = {};
  ASSERT_NE(std::fgets(line, sizeof line, c.out), nullptr) << "fettle-sim robot printed nothing";
  std::smatch m;
  const std::string first(line);
  ASSERT_TRUE(std::regex_search(first, m, std::regex(R"(listening on 127\.0\.0\.1:(\d+))"))) << first;
  const int port = std::stoi(m[1]);
  EXPECT_GT(port, 0);

  boost::asio::io_context io;
  fettle::drivers::RobotLinkOptions o;
  o.port = port;
  o.cell_id = "cli-test";
  o.reply_timeout_ms = 2000;
  fettle::drivers::RobotLink link(io, o);
  link.start();
  auto run_until = [&](auto pred) {
    const auto end = std::chrono::steady_clock::now() + 5s;
    while (!pred() && std::chrono::steady_clock::now() < end) {
      io.run_for(10ms);
      if (io.stopped()) io.restart();
    }
    return pred();
  };
  ASSERT_TRUE(run_until([&] { return link.state() == RobotState::ready; })) << link.last_error().message;

  fettle::Trajectory t;
  for (int i = 0; i < 5; ++i) {
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = fettle::Vec3(300.0 + i, 0.0, 200.0);
    p.speed_mm_s = 50.0;
    p.segment = i / 2;
    t.points.push_back(p);
  }
  std::optional<fettle::Status> up, run;
  link.upload(t, [&](fettle::Status s) { up = s; });
  ASSERT_TRUE(run_until([&] { return up.has_value(); }));
  ASSERT_TRUE(up->ok()) << up->error().message;
  link.run([&](fettle::Status s) { run = s; });
  ASSERT_TRUE(run_until([&] { return run.has_value(); }));
  EXPECT_TRUE(run->ok()) << run->error().message;
  link.shutdown();

  ::kill(c.pid, SIGTERM);
  int status = 0;
  ::waitpid(c.pid, &status, 0);
  std::string rest;
  while (std::fgets(line, sizeof line, c.out) != nullptr) rest += line;
  ::fclose(c.out);
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
  EXPECT_NE(rest.find("1 trajectories received, 1 executed"), std::string::npos) << rest;
}

TEST(RobotSimCli, BadListenAddressIsAUsageOrUserError) {
  const std::string cmd = std::string(FETTLE_BIN_DIR) + "/fettle-sim robot --listen 127.0.0.1:99999 2>&1";
  FILE* p = ::popen(cmd.c_str(), "r");
  ASSERT_NE(p, nullptr);
  std::string out;
  char buf[256];
  while (std::fgets(buf, sizeof buf, p) != nullptr) out += buf;
  const int status = ::pclose(p);
  EXPECT_EQ(WEXITSTATUS(status), 1) << out;
  EXPECT_NE(out.find("99999"), std::string::npos) << out;
}
