// The robot conformance check (docs/robot-protocol.md, section 11): every rule passes against
// the simulated robot, a robot that breaks a rule fails exactly the rules it breaks, and
// `fettle robot conformance` reports it with its exit code.
#include <gtest/gtest.h>

#include <chrono>
#include <regex>
#include <set>
#include <string>
#include <thread>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>

#include "../support/child.hpp"
#include "fettle/drivers/robot_conformance.hpp"
#include "fettle/sim/robot.hpp"

namespace robot = fettle::drivers::robot;
using Outcome = robot::ConformanceRule::Outcome;

namespace {

/// The simulated robot on its own io_context thread, as a separate controller would run.
class SimRobot {
 public:
  explicit SimRobot(fettle::sim::RobotSimOptions o) : robot_(io_, std::move(o)) {
    robot_.start();
    thread_ = std::thread([this] { io_.run(); });
  }
  ~SimRobot() {
    boost::asio::post(io_, [this] { robot_.close(); });
    guard_.reset();
    thread_.join();
  }
  [[nodiscard]] int port() const { return robot_.port(); }

 private:
  boost::asio::io_context io_;
  boost::asio::executor_work_guard<boost::asio::io_context::executor_type> guard_{io_.get_executor()};
  fettle::sim::RobotSim robot_;
  std::thread thread_;
};

fettle::sim::RobotSimOptions instant() {
  fettle::sim::RobotSimOptions o;
  o.speedup = 0.0;
  return o;
}

robot::ConformanceOptions against(int port) {
  robot::ConformanceOptions o;
  o.port = port;
  o.motion = true;
  o.reply_timeout_ms = 1500;
  return o;
}

std::set<std::string> failed(const std::vector<robot::ConformanceRule>& results) {
  std::set<std::string> out;
  for (const auto& r : results)
    if (r.outcome == Outcome::fail) out.insert(r.id);
  return out;
}

std::string dump(const std::vector<robot::ConformanceRule>& results) {
  std::string s;
  for (const auto& r : results) s += std::string(robot::name(r.outcome)) + " " + r.id + ": " + r.detail + "\n";
  return s;
}

}  // namespace

TEST(RobotConformance, TheSimulatedRobotPassesEveryRule) {
  SimRobot sim(instant());
  int reported = 0;
  const auto results = robot::run_conformance(against(sim.port()), [&](const auto&) { ++reported; });
  EXPECT_GE(results.size(), 25U);
  EXPECT_EQ(reported, static_cast<int>(results.size())) << "one progress report per rule";
  for (const auto& r : results) EXPECT_EQ(r.outcome, Outcome::pass) << r.id << ": " << r.detail;
}

TEST(RobotConformance, MotionRulesAreSkippedUnlessAskedFor) {
  SimRobot sim(instant());
  auto o = against(sim.port());
  o.motion = false;
  const auto results = robot::run_conformance(o);
  int skipped = 0;
  for (const auto& r : results) {
    if (r.outcome == Outcome::skipped) {
      ++skipped;
      EXPECT_TRUE(r.id.starts_with("run.")) << r.id;
      EXPECT_NE(r.detail.find("--motion"), std::string::npos) << r.detail;
    } else {
      EXPECT_EQ(r.outcome, Outcome::pass) << r.id << ": " << r.detail;
    }
  }
  EXPECT_EQ(skipped, 2);
}

// A robot that never answers PING fails the rules that need a PONG, and only those.
TEST(RobotConformance, ARobotThatIgnoresPingsFailsThePingRules) {
  auto o = instant();
  o.faults.ignore_pings = true;
  SimRobot sim(o);
  auto c = against(sim.port());
  c.reply_timeout_ms = 300;
  const auto results = robot::run_conformance(c);
  EXPECT_EQ(failed(results), (std::set<std::string>{"hello.twice", "ping", "upload.without_traj", "line.empty", "busy"}))
      << dump(results);
  for (const auto& r : results)
    if (r.id == "ping") {
      EXPECT_NE(r.detail.find("expected PONG"), std::string::npos) << r.detail;
    }
}

// A robot that refuses the cell id fails every rule that says HELLO, with the robot's words.
TEST(RobotConformance, ARobotExpectingAnotherCellFailsWithItsNak) {
  auto o = instant();
  o.expected_cell_id = "cell-02";
  SimRobot sim(o);
  const auto results = robot::run_conformance(against(sim.port()));
  ASSERT_FALSE(results.empty());
  EXPECT_EQ(results.front().id, "hello");
  EXPECT_EQ(results.front().outcome, Outcome::fail);
  EXPECT_NE(results.front().detail.find("NAK 1 CELL"), std::string::npos) << results.front().detail;
}

TEST(RobotConformance, NoRobotAtTheAddressFailsEveryRuleWithTheConnectError) {
  int port = 0;
  {
    SimRobot sim(instant());  // a port that was free, now closed again
    port = sim.port();
  }
  auto o = against(port);
  o.motion = false;
  for (const auto& r : robot::run_conformance(o)) {
    if (r.outcome == Outcome::skipped) continue;
    EXPECT_EQ(r.outcome, Outcome::fail) << r.id;
    EXPECT_NE(r.detail.find("cannot connect"), std::string::npos) << r.detail;
  }
}

// The command a robot integrator runs, against `fettle-sim robot` in its own process.
TEST(RobotConformance, FettleRobotConformancePassesAgainstFettleSimRobot) {
  const std::string bin = FETTLE_BIN_DIR;
  fettle::test::Child sim({bin + "/fettle-sim", "--log-level", "warn", "robot", "--listen", "127.0.0.1:0", "--speedup", "0"});
  ASSERT_TRUE(sim.started());
  const auto m = sim.wait_line(std::regex(R"(listening on 127\.0\.0\.1:(\d+))"), std::chrono::seconds(5));
  ASSERT_TRUE(m) << sim.output();
  const std::string port = (*m)[1].str();

  int rc = 0;
  const auto out = fettle::test::run_capture(
      bin + "/fettle robot conformance --address 127.0.0.1:" + port + " --motion --timeout-ms 1500", rc);
  EXPECT_EQ(rc, 0) << out;
  EXPECT_TRUE(std::regex_search(out, std::regex(R"(\n(\d+) of \1 rules pass \(docs/robot-protocol\.md\))"))) << out;
  EXPECT_NE(out.find("PASS  seq.skip (section 2.1)"), std::string::npos) << out;
  EXPECT_EQ(out.find("FAIL"), std::string::npos) << out;

  // Nothing listening any more: exit code 3 (a device could not be reached).
  sim.kill();
  (void)fettle::test::run_capture(bin + "/fettle robot conformance --address 127.0.0.1:1 --timeout-ms 200", rc);
  EXPECT_EQ(rc, 3);
}
