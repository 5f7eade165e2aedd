// `fettle-sim robot --listen 127.0.0.1:0` as a user runs it: it prints the bound port,
// a RobotLink connects, uploads and runs; SIGTERM ends it with exit code 0.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <chrono>
#include <filesystem>
#include <optional>
#include <regex>
#include <string>

#include <boost/asio/io_context.hpp>

#include "../support/child.hpp"
#include "../support/sim_cell_file.hpp"
#include "fettle/drivers/robot_link.hpp"

using namespace std::chrono_literals;
using fettle::drivers::RobotState;
using fettle::test::Child;

namespace {

const std::string kSim = std::string(FETTLE_BIN_DIR) + "/fettle-sim";

/// A RobotLink to the simulated robot on `port`, driven on the test's thread.
struct LinkToRobot {
  LinkToRobot(int port, const std::string& cell_id) : link(io, options(port, cell_id)) { link.start(); }
  ~LinkToRobot() { link.shutdown(); }

  static fettle::drivers::RobotLinkOptions options(int port, const std::string& cell_id) {
    fettle::drivers::RobotLinkOptions o;
    o.port = port;
    o.cell_id = cell_id;
    o.reply_timeout_ms = 2000;
    return o;
  }
  /// Runs the link until `pred` holds, at most 5 s.
  template <class Pred>
  bool run_until(Pred pred) {
    const auto end = std::chrono::steady_clock::now() + 5s;
    while (!pred() && std::chrono::steady_clock::now() < end) {
      io.run_for(10ms);
      if (io.stopped()) io.restart();
    }
    return pred();
  }
  /// Uploads `t` and waits for the robot's answer.
  std::optional<fettle::Status> upload(const fettle::Trajectory& t) {
    std::optional<fettle::Status> up;
    link.upload(t, [&](fettle::Status st) { up = st; });
    run_until([&] { return up.has_value(); });
    return up;
  }

  boost::asio::io_context io;
  fettle::drivers::RobotLink link;
};

}  // namespace

TEST(RobotSimCli, PrintsThePortAndServesARobotLink) {
  Child c({kSim, "--log-level", "warn", "robot", "--listen", "127.0.0.1:0", "--speedup", "0"});
  ASSERT_TRUE(c.started());
  const auto m = c.wait_line(std::regex(R"(listening on 127\.0\.0\.1:(\d+))"), 5s);
  ASSERT_TRUE(m) << "fettle-sim robot did not print its port: " << c.output();
  const int port = std::stoi((*m)[1].str());
  EXPECT_GT(port, 0);

  LinkToRobot r(port, "cli-test");
  ASSERT_TRUE(r.run_until([&] { return r.link.state() == RobotState::ready; })) << r.link.last_error().message;

  fettle::Trajectory t;
  for (int i = 0; i < 5; ++i) {
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = fettle::Vec3(300.0 + i, 0.0, 200.0);
    p.speed_mm_s = 50.0;
    p.segment = i / 2;
    t.points.push_back(p);
  }
  const auto up = r.upload(t);
  ASSERT_TRUE(up.has_value());
  ASSERT_TRUE(up->ok()) << up->error().message;
  std::optional<fettle::Status> run;
  r.link.run([&](fettle::Status st) { run = st; });
  ASSERT_TRUE(r.run_until([&] { return run.has_value(); }));
  EXPECT_TRUE(run->ok()) << run->error().message;
  r.link.shutdown();

  const int status = c.stop();
  const std::string rest = c.rest();
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
  Child c({kSim, "--log-level", "warn", "robot", "--cell", cell.string(), "--speedup", "0"});
  ASSERT_TRUE(c.started());
  std::string line;
  ASSERT_TRUE(c.wait_line(std::regex("listening on"), 5s, &line)) << "fettle-sim robot printed nothing";
  EXPECT_EQ(line, "fettle-sim robot listening on 127.0.0.1:" + std::to_string(port));

  LinkToRobot r(port, "sim-cell");  // the cell file's [robot] cell_id
  ASSERT_TRUE(r.run_until([&] { return r.link.state() == RobotState::ready; })) << r.link.last_error().message;
  // 700 mm is outside the cell's workspace (+-600 mm in x), inside the simulator's default one.
  fettle::Trajectory t;
  for (const double x : {300.0, 700.0}) {
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = fettle::Vec3(x, 0.0, 200.0);
    p.speed_mm_s = 50.0;
    t.points.push_back(p);
  }
  const auto up = r.upload(t);
  ASSERT_TRUE(up.has_value());
  EXPECT_FALSE(up->ok()) << "a point outside the cell's [safety] workspace was accepted";
  std::filesystem::remove_all(dir);
}

TEST(RobotSimCli, BadListenAddressIsAUsageOrUserError) {
  int rc = 0;
  const auto out = fettle::test::run_capture(kSim + " robot --listen 127.0.0.1:99999", rc);
  EXPECT_EQ(rc, 1) << out;
  EXPECT_NE(out.find("99999"), std::string::npos) << out;
}
