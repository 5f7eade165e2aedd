// `fettle-sim robot --listen 127.0.0.1:0` as a user runs it: it prints the bound port,
// a RobotLink connects, uploads and runs; SIGTERM ends it with exit code 0.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <regex>
#include <string>

#include <boost/asio/io_context.hpp>

#include "../support/sim_cell_file.hpp"
#include "../support/spawn.hpp"
#include "fettle/drivers/robot_link.hpp"

using namespace std::chrono_literals;
using fettle::drivers::RobotState;

using Child = fettle::test::Spawned;
using fettle::test::spawn;

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

// A cell assembled from the separate simulators: `--cell` makes the robot listen where the cell
// file says, accept its cell id and keep its [safety] workspace.
TEST(RobotSimCli, WithACellFileItListensWhereTheCellSaysAndKeepsItsWorkspace) {
  char tmpl[] = "/tmp/fettle-robot-cell-XXXXXX";
  ASSERT_NE(::mkdtemp(tmpl), nullptr);
  const std::filesystem::path dir(tmpl);
  const int port = fettle::test::free_tcp_port();
  const auto cell = fettle::test::write_sim_cell(dir, {fettle::test::free_tcp_port(), port, 1});
  const std::string exe = std::string(FETTLE_BIN_DIR) + "/fettle-sim";
  Child c = spawn({exe, "--log-level", "warn", "robot", "--cell", cell.string(), "--speedup", "0"});
  ASSERT_GT(c.pid, 0);
  char line[256] = {};
  ASSERT_NE(std::fgets(line, sizeof line, c.out), nullptr) << "fettle-sim robot printed nothing";
  EXPECT_EQ(std::string(line), "fettle-sim robot listening on 127.0.0.1:" + std::to_string(port) + "\n");

  boost::asio::io_context io;
  fettle::drivers::RobotLinkOptions o;
  o.port = port;
  o.cell_id = "sim-cell";  // the cell file's [robot] cell_id
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
  // 700 mm is outside the cell's workspace (+-600 mm in x), inside the simulator's default one.
  fettle::Trajectory t;
  for (const double x : {300.0, 700.0}) {
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = fettle::Vec3(x, 0.0, 200.0);
    p.speed_mm_s = 50.0;
    t.points.push_back(p);
  }
  std::optional<fettle::Status> up;
  link.upload(t, [&](fettle::Status s) { up = s; });
  ASSERT_TRUE(run_until([&] { return up.has_value(); }));
  EXPECT_FALSE(up->ok()) << "a point outside the cell's [safety] workspace was accepted";
  link.shutdown();
  ::kill(c.pid, SIGTERM);
  ::waitpid(c.pid, nullptr, 0);
  ::fclose(c.out);
  std::filesystem::remove_all(dir);
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
