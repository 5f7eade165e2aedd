// RobotLink against the simulated robot controller on loopback (ephemeral ports):
// one test per message and per fault; after each fault the client is in a defined
// state with a specific error and recovers when the peer comes back.
#include <gtest/gtest.h>

#include <chrono>
#include <deque>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/write.hpp>

#include "fettle/drivers/robot_link.hpp"
#include "fettle/drivers/robot_protocol.hpp"
#include "fettle/sim/robot.hpp"

namespace asio = boost::asio;
using fettle::drivers::RobotLink;
using fettle::drivers::RobotLinkOptions;
using fettle::drivers::RobotState;
using fettle::sim::RobotSim;
using fettle::sim::RobotSimOptions;
using namespace std::chrono_literals;

namespace {

fettle::Trajectory make_trajectory(int n, int per_segment = 4, double speed_mm_s = 100.0) {
  fettle::Trajectory t;
  t.part_id = "test";
  const fettle::Quat down(0.0, 1.0, 0.0, 0.0);
  for (int i = 0; i < n; ++i) {
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = fettle::Vec3(400.0 + 2.0 * i, -50.0 + 0.5 * i, 300.0 - 0.25 * i);
    p.T_base_tool.orientation = down;
    p.speed_mm_s = speed_mm_s;
    p.spindle_rpm = i == 0 ? 0 : 9000;
    p.segment = i / per_segment;
    p.kind = i == 0 ? fettle::MoveKind::approach : fettle::MoveKind::grind;
    t.points.push_back(p);
  }
  return t;
}

/// Records the outcome of an asynchronous call.
struct Outcome {
  std::optional<fettle::Status> status;
  RobotLink::Handler handler() {
    return [this](fettle::Status s) { status = std::move(s); };
  }
  [[nodiscard]] bool done() const { return status.has_value(); }
  [[nodiscard]] bool ok() const { return status && status->ok(); }
  [[nodiscard]] std::string code() const { return !status ? "<pending>" : status->ok() ? "ok" : status->error().code; }
};

/// A raw TCP client on the same io_context, for feeding the simulated robot by hand.
struct RawClient {
  explicit RawClient(asio::io_context& io) : socket(io) {}
  asio::ip::tcp::socket socket;
  std::array<char, 512> buf{};
  fettle::drivers::robot::LineSplitter splitter;
  std::vector<std::string> lines;
  bool connected = false;
  bool closed = false;

  void connect(int port) {
    socket.async_connect({asio::ip::make_address("127.0.0.1"), static_cast<unsigned short>(port)},
                         [this](const boost::system::error_code& ec) {
                           connected = !ec;
                           if (!ec) read();
                         });
  }
  void read() {
    socket.async_read_some(asio::buffer(buf), [this](const boost::system::error_code& ec, std::size_t n) {
      if (ec) {
        closed = true;
        return;
      }
      (void)splitter.feed(std::string_view(buf.data(), n), lines);
      read();
    });
  }
  void send(std::string bytes) {
    auto p = std::make_shared<std::string>(std::move(bytes));
    asio::async_write(socket, asio::buffer(*p), [p](const boost::system::error_code&, std::size_t) {});
  }
  [[nodiscard]] bool has_line_containing(const std::string& s) const {
    for (const auto& l : lines)
      if (l.find(s) != std::string::npos) return true;
    return false;
  }
};

class RobotLinkTest : public ::testing::Test {
 protected:
  void SetUp() override { start_sim(0); }

  void start_sim(int port) {
    RobotSimOptions o;
    o.port = port;
    o.speedup = 0.0;  // instant execution unless a test changes it
    o.envelope.min_mm = {-1000, -1000, 0};
    o.envelope.max_mm = {1000, 1000, 1000};
    o.envelope.max_speed_mm_s = 500;
    o.faults = faults_;
    o.speedup = speedup_;
    sim_ = std::make_unique<RobotSim>(io_, o);
    sim_->on_executed([this](const fettle::Trajectory& t) { executed_.push_back(t); });
    sim_->start();
    port_ = sim_->port();
  }

  RobotLinkOptions link_options() const {
    RobotLinkOptions o;
    o.port = port_;
    o.cell_id = "test-cell";
    o.connect_timeout_ms = 500;
    o.reply_timeout_ms = 300;
    o.ping_period_ms = 40;
    o.missed_pings = 3;
    o.chunk_points = 3;
    o.run_timeout_ms = 5000;
    o.reconnect_initial_ms = 20;
    o.reconnect_max_ms = 100;
    return o;
  }

  void start_link(std::optional<RobotLinkOptions> o = std::nullopt) {
    link_ = std::make_unique<RobotLink>(io_, o.value_or(link_options()));
    link_->on_state([this](RobotState s, const fettle::Error& e) {
      states_.push_back(s);
      if (!e.code.empty()) errors_.push_back(e.code);
    });
    link_->on_progress([this](const fettle::drivers::RobotProgress& p) { progress_.push_back(p); });
    link_->start();
  }

  /// Runs the io_context until `pred` holds or `timeout` passes.
  bool run_until(const std::function<bool()>& pred, std::chrono::milliseconds timeout = 3000ms) {
    const auto end = std::chrono::steady_clock::now() + timeout;
    while (!pred()) {
      if (std::chrono::steady_clock::now() > end) return false;
      io_.run_for(5ms);
      if (io_.stopped()) io_.restart();
    }
    return true;
  }

  void connect_ready() {
    start_link();
    ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::ready; })) << to_string(link_->state());
  }

  void upload(const fettle::Trajectory& t) {
    Outcome up;
    link_->upload(t, up.handler());
    ASSERT_TRUE(run_until([&] { return up.done(); }));
    ASSERT_TRUE(up.ok()) << up.status->error().message;
    ASSERT_EQ(link_->state(), RobotState::uploaded);
  }

  bool saw_error(const std::string& code) const {
    return std::find(errors_.begin(), errors_.end(), code) != errors_.end();
  }

  asio::io_context io_;
  fettle::sim::RobotFaults faults_;
  double speedup_ = 0.0;
  std::unique_ptr<RobotSim> sim_;
  std::unique_ptr<RobotLink> link_;
  int port_ = 0;
  std::vector<RobotState> states_;
  std::vector<std::string> errors_;
  std::vector<fettle::drivers::RobotProgress> progress_;
  std::vector<fettle::Trajectory> executed_;
};

// ---- messages ---------------------------------------------------------------------

TEST_F(RobotLinkTest, HelloMakesTheLinkReady) {
  connect_ready();
  EXPECT_EQ(link_->robot_id(), "fettle-sim-robot");
  EXPECT_EQ(link_->connections(), 1);
  ASSERT_GE(states_.size(), 2u);
  EXPECT_EQ(states_[0], RobotState::connecting);
  EXPECT_EQ(states_.back(), RobotState::ready);
}

// The link as the cycle sees it (drivers::RobotDevice): configure checks the options,
// activate connects, deactivate closes; the link's own state follows.
TEST_F(RobotLinkTest, TheLinkGoesThroughTheDeviceLifecycle) {
  RobotLink link(io_, link_options());
  fettle::drivers::RobotDevice& robot = link;
  EXPECT_EQ(robot.lifecycle(), fettle::drivers::Lifecycle::unconfigured);
  EXPECT_EQ(robot.activate().error().code, "robot.lifecycle");
  ASSERT_TRUE(robot.configure());
  EXPECT_EQ(robot.lifecycle(), fettle::drivers::Lifecycle::inactive);
  EXPECT_EQ(robot.state(), RobotState::disconnected);
  ASSERT_TRUE(robot.activate());
  EXPECT_EQ(robot.lifecycle(), fettle::drivers::Lifecycle::active);
  ASSERT_TRUE(run_until([&] { return robot.state() == RobotState::ready; })) << to_string(robot.state());
  robot.deactivate();
  EXPECT_EQ(robot.lifecycle(), fettle::drivers::Lifecycle::inactive);
  EXPECT_EQ(robot.state(), RobotState::disconnected);
}

TEST_F(RobotLinkTest, ConfigureRefusesOptionsThatCannotWorkNamingTheKey) {
  auto o = link_options();
  o.port = 0;
  RobotLink no_port(io_, o);
  const auto st = no_port.configure();
  ASSERT_FALSE(st);
  EXPECT_EQ(st.error().code, "robot.config");
  EXPECT_NE(st.error().message.find("[robot] port 0"), std::string::npos) << st.error().message;
  EXPECT_EQ(no_port.last_error().code, "robot.config");
  EXPECT_EQ(no_port.lifecycle(), fettle::drivers::Lifecycle::unconfigured);
  o = link_options();
  o.reply_timeout_ms = 0;
  RobotLink no_timeout(io_, o);
  EXPECT_EQ(no_timeout.configure().error().code, "robot.config");
}

TEST_F(RobotLinkTest, HelloWithWrongCellIsRefused) {
  sim_.reset();
  RobotSimOptions o;
  o.expected_cell_id = "cell-07";
  sim_ = std::make_unique<RobotSim>(io_, o);
  sim_->start();
  port_ = sim_->port();
  start_link();
  ASSERT_TRUE(run_until([&] { return saw_error("robot.nak.cell"); }));
  EXPECT_NE(link_->state(), RobotState::ready);
  EXPECT_EQ(link_->connections(), 0);
}

TEST_F(RobotLinkTest, UploadsInChunksAndRunsWithProgressBySegment) {
  connect_ready();
  const auto t = make_trajectory(10, 4);  // 4 chunks of 3, segments 0, 1, 2
  upload(t);
  EXPECT_EQ(sim_->stats().trajectories_received, 1);
  Outcome run;
  link_->run(run.handler());
  ASSERT_TRUE(run_until([&] { return run.done(); }));
  EXPECT_TRUE(run.ok()) << run.code();
  EXPECT_EQ(link_->state(), RobotState::uploaded);  // the robot keeps it: it may run again
  ASSERT_EQ(progress_.size(), 3u);
  for (int s = 0; s < 3; ++s) {
    EXPECT_EQ(progress_[static_cast<std::size_t>(s)].segment, s);
    EXPECT_EQ(progress_[static_cast<std::size_t>(s)].point_index, 4 * s);
    EXPECT_EQ(progress_[static_cast<std::size_t>(s)].trajectory_id, link_->trajectory_id());
  }
  // The executed path is what was sent, to the wire's resolution.
  ASSERT_EQ(executed_.size(), 1u);
  ASSERT_EQ(executed_[0].points.size(), t.points.size());
  for (std::size_t i = 0; i < t.points.size(); ++i) {
    EXPECT_LE((executed_[0].points[i].T_base_tool.position_mm - t.points[i].T_base_tool.position_mm).norm(), 1e-3);
    EXPECT_EQ(executed_[0].points[i].segment, t.points[i].segment);
  }
  EXPECT_EQ(sim_->stats().trajectories_executed, 1);
}

TEST_F(RobotLinkTest, RunsInAcceleratedRealTime) {
  sim_.reset();
  speedup_ = 10.0;
  start_sim(0);
  connect_ready();
  // 20 points 2.06 mm apart at 10 mm/s: about 3.9 s of motion, 0.39 s at 10x.
  upload(make_trajectory(20, 5, 10.0));
  Outcome run;
  const auto t0 = std::chrono::steady_clock::now();
  link_->run(run.handler());
  ASSERT_TRUE(run_until([&] { return run.done(); }, 5000ms));
  const auto elapsed = std::chrono::steady_clock::now() - t0;
  EXPECT_TRUE(run.ok()) << run.code();
  EXPECT_GE(elapsed, 300ms);
}

TEST_F(RobotLinkTest, PingPongKeepsAnIdleLinkUp) {
  connect_ready();
  run_until([] { return false; }, 400ms);  // ten ping periods
  EXPECT_EQ(link_->state(), RobotState::ready);
  EXPECT_EQ(link_->connections(), 1);
  EXPECT_TRUE(errors_.empty());
}

TEST_F(RobotLinkTest, StopDuringRunHaltsAndReportsStopped) {
  sim_.reset();
  speedup_ = 1.0;
  start_sim(0);
  connect_ready();
  upload(make_trajectory(40, 4, 20.0));  // about 4 s of motion
  Outcome run, stop;
  link_->run(run.handler());
  ASSERT_TRUE(run_until([&] { return progress_.size() >= 2; }));
  link_->stop(stop.handler());
  ASSERT_TRUE(run_until([&] { return stop.done() && run.done(); }));
  EXPECT_EQ(run.code(), "robot.stopped");
  EXPECT_TRUE(stop.ok()) << stop.code();
  EXPECT_EQ(link_->state(), RobotState::ready);
  ASSERT_TRUE(run_until([&] { return !executed_.empty(); }));
  EXPECT_GT(executed_[0].points.size(), 0u);
  EXPECT_LT(executed_[0].points.size(), 40u);
  // The robot discarded the trajectory: running it again is refused locally.
  Outcome again;
  link_->run(again.handler());
  ASSERT_TRUE(run_until([&] { return again.done(); }));
  EXPECT_EQ(again.code(), "robot.state");
}

TEST_F(RobotLinkTest, StopWhileIdleIsAcknowledged) {
  connect_ready();
  Outcome stop;
  link_->stop(stop.handler());
  ASSERT_TRUE(run_until([&] { return stop.done(); }));
  EXPECT_TRUE(stop.ok());
  EXPECT_EQ(link_->state(), RobotState::ready);
}

// An abort sends a quick STOP and then waits for the robot to stop: the second stop() joins
// the first and both get the ACK.
TEST_F(RobotLinkTest, ASecondStopWhileOneIsPendingGetsTheSameAck) {
  sim_.reset();
  speedup_ = 1.0;
  start_sim(0);
  connect_ready();
  upload(make_trajectory(40, 4, 20.0));
  Outcome run, first, second;
  link_->run(run.handler());
  ASSERT_TRUE(run_until([&] { return progress_.size() >= 2; }));
  link_->stop(first.handler());
  link_->stop(second.handler());
  ASSERT_TRUE(run_until([&] { return first.done() && second.done() && run.done(); }));
  EXPECT_TRUE(first.ok()) << first.code();
  EXPECT_TRUE(second.ok()) << second.code();
  EXPECT_EQ(run.code(), "robot.stopped");
  EXPECT_EQ(link_->state(), RobotState::ready);
  EXPECT_EQ(sim_->stats().trajectories_halted, 1);
}

TEST_F(RobotLinkTest, RequestsOutOfStateFailLocally) {
  connect_ready();
  Outcome run;
  link_->run(run.handler());
  ASSERT_TRUE(run_until([&] { return run.done(); }));
  EXPECT_EQ(run.code(), "robot.state");
  Outcome up;
  fettle::Trajectory empty;
  link_->upload(empty, up.handler());
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.invalid_point");
  EXPECT_EQ(link_->state(), RobotState::ready);
}

TEST_F(RobotLinkTest, StopDuringUploadAbortsIt) {
  connect_ready();
  auto f = sim_->faults();
  f.reply_delay_ms = 50;  // keep the upload in flight long enough to stop it
  sim_->set_faults(f);
  Outcome up, stop;
  link_->upload(make_trajectory(30), up.handler());
  ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::uploading; }));
  link_->stop(stop.handler());
  EXPECT_EQ(up.code(), "robot.stopped");
  ASSERT_TRUE(run_until([&] { return stop.done(); }));
  EXPECT_TRUE(stop.ok()) << stop.code();
  EXPECT_EQ(link_->state(), RobotState::ready);
  EXPECT_EQ(sim_->stats().trajectories_received, 0);
  f.reply_delay_ms = 0;
  sim_->set_faults(f);
  upload(make_trajectory(30));  // late ACKs of the aborted upload do not confuse the next one
}

TEST_F(RobotLinkTest, InjectedNakOnTrajFailsTheUpload) {
  connect_ready();
  auto f = sim_->faults();
  f.nak_verb = "TRAJ";
  f.nak_code = "FAULTED";
  sim_->set_faults(f);
  Outcome up;
  link_->upload(make_trajectory(5), up.handler());
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.nak.faulted");
  EXPECT_EQ(link_->state(), RobotState::ready);
}

// ---- robot-side validation → NAK ---------------------------------------------------

TEST_F(RobotLinkTest, PointOutsideTheEnvelopeIsNaked) {
  connect_ready();
  auto t = make_trajectory(7);
  t.points[5].T_base_tool.position_mm.z() = 1500.0;  // above the sim's 1000 mm
  Outcome up;
  link_->upload(t, up.handler());
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.nak.envelope");
  EXPECT_EQ(up.status->error().kind, fettle::ErrorKind::refused);  // fettled's fault 301 comes from the kind
  EXPECT_EQ(link_->state(), RobotState::ready);
  // The link stays usable: a good trajectory uploads next.
  upload(make_trajectory(7));
}

TEST_F(RobotLinkTest, SpeedAboveTheRobotLimitIsNaked) {
  connect_ready();
  auto t = make_trajectory(4);
  t.points[2].speed_mm_s = 800.0;
  Outcome up;
  link_->upload(t, up.handler());
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.nak.speed");
  EXPECT_EQ(link_->state(), RobotState::ready);
}

TEST_F(RobotLinkTest, InjectedNakOnEndFailsTheUpload) {
  connect_ready();
  auto f = sim_->faults();
  f.nak_verb = "END";
  f.nak_code = "CRC";
  sim_->set_faults(f);
  Outcome up;
  link_->upload(make_trajectory(5), up.handler());
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.nak.crc");
  EXPECT_EQ(link_->state(), RobotState::ready);
  EXPECT_EQ(link_->last_error().code, "robot.nak.crc");
  upload(make_trajectory(5));  // one-shot: the next upload goes through
}

TEST_F(RobotLinkTest, InjectedNakOnRunKeepsTheTrajectory) {
  connect_ready();
  upload(make_trajectory(5));
  auto f = sim_->faults();
  f.nak_verb = "RUN";
  f.nak_code = "BUSY";
  sim_->set_faults(f);
  Outcome run;
  link_->run(run.handler());
  ASSERT_TRUE(run_until([&] { return run.done(); }));
  EXPECT_EQ(run.code(), "robot.nak.busy");
  EXPECT_EQ(link_->state(), RobotState::uploaded);
  Outcome again;
  link_->run(again.handler());
  ASSERT_TRUE(run_until([&] { return again.done(); }));
  EXPECT_TRUE(again.ok()) << again.code();
}

// ---- faults ----------------------------------------------------------------------

TEST_F(RobotLinkTest, FaultMidRunLatchesUntilReset) {
  connect_ready();
  auto f = sim_->faults();
  f.fault_at_point = 6;
  f.fault_code = "COLLISION";
  sim_->set_faults(f);
  upload(make_trajectory(12));
  Outcome run;
  link_->run(run.handler());
  ASSERT_TRUE(run_until([&] { return run.done(); }));
  EXPECT_EQ(run.code(), "robot.fault.collision");
  EXPECT_EQ(link_->state(), RobotState::faulted);
  EXPECT_EQ(link_->last_error().code, "robot.fault.collision");
  EXPECT_EQ(link_->last_error().kind, fettle::ErrorKind::device_fault);
  ASSERT_EQ(executed_.size(), 1u);
  EXPECT_EQ(executed_[0].points.size(), 6u);  // the robot got as far as point 6
  // Faulted: an upload is refused until RESET.
  Outcome up;
  link_->upload(make_trajectory(3), up.handler());
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.state");
  Outcome reset;
  link_->reset(reset.handler());
  ASSERT_TRUE(run_until([&] { return reset.done(); }));
  EXPECT_TRUE(reset.ok());
  EXPECT_EQ(link_->state(), RobotState::ready);
  upload(make_trajectory(3));
}

TEST_F(RobotLinkTest, DisconnectMidUploadThenRecovers) {
  connect_ready();
  auto f = sim_->faults();
  f.disconnect_at_chunk = 2;
  sim_->set_faults(f);
  Outcome up;
  link_->upload(make_trajectory(9), up.handler());
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.connection_lost");
  EXPECT_EQ(link_->last_error().code, "robot.connection_lost");
  EXPECT_EQ(link_->last_error().kind, fettle::ErrorKind::link_lost);
  EXPECT_NE(link_->state(), RobotState::ready);
  ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::ready; }));
  EXPECT_EQ(link_->connections(), 2);
  upload(make_trajectory(9));
}

TEST_F(RobotLinkTest, MissedPongsTakeTheLinkDownAndItRecovers) {
  connect_ready();
  auto f = sim_->faults();
  f.ignore_pings = true;
  sim_->set_faults(f);
  ASSERT_TRUE(run_until([&] { return saw_error("robot.ping_timeout"); }, 2000ms));
  EXPECT_NE(std::find(states_.begin(), states_.end(), RobotState::disconnected), states_.end());
  f.ignore_pings = false;
  sim_->set_faults(f);
  ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::ready && link_->connections() >= 2; }));
}

TEST_F(RobotLinkTest, SlowRepliesWithinTheTimeoutWork) {
  connect_ready();
  auto f = sim_->faults();
  f.reply_delay_ms = 30;
  sim_->set_faults(f);
  upload(make_trajectory(6));
  EXPECT_EQ(link_->connections(), 1);
}

TEST_F(RobotLinkTest, RepliesSlowerThanTheTimeoutTakeTheLinkDown) {
  auto o = link_options();
  o.ping_period_ms = 1000;  // so that the late PONGs do not take the link down first
  start_link(o);
  ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::ready; }));
  auto f = sim_->faults();
  f.reply_delay_ms = 600;  // reply timeout is 300 ms
  sim_->set_faults(f);
  Outcome up;
  link_->upload(make_trajectory(6), up.handler());
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.reply_timeout");
  EXPECT_EQ(link_->last_error().code, "robot.reply_timeout");
  f.reply_delay_ms = 0;
  sim_->set_faults(f);
  ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::ready; }));
  upload(make_trajectory(6));
}

TEST_F(RobotLinkTest, GarbageReplyIsAProtocolErrorAndTheLinkRecovers) {
  connect_ready();
  auto f = sim_->faults();
  f.garbage_reply = true;
  sim_->set_faults(f);
  Outcome up;
  link_->upload(make_trajectory(4), up.handler());
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.protocol");
  ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::ready && link_->connections() == 2; }));
  upload(make_trajectory(4));
}

TEST_F(RobotLinkTest, OversizeReplyIsAProtocolErrorAndTheLinkRecovers) {
  connect_ready();
  auto f = sim_->faults();
  f.oversize_reply = true;
  sim_->set_faults(f);
  Outcome up;
  link_->upload(make_trajectory(4), up.handler());
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.protocol");
  EXPECT_NE(link_->last_error().message.find("longer than 80"), std::string::npos) << link_->last_error().message;
  ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::ready && link_->connections() == 2; }));
}

TEST_F(RobotLinkTest, RobotSwitchedOffAndBackOn) {
  connect_ready();
  upload(make_trajectory(4));
  sim_->close();
  ASSERT_TRUE(run_until([&] { return saw_error("robot.connection_lost"); }));
  // While it is off, reconnect attempts fail with a specific error.
  ASSERT_TRUE(run_until([&] { return saw_error("robot.connect_failed"); }));
  Outcome run;
  link_->run(run.handler());
  ASSERT_TRUE(run_until([&] { return run.done(); }));
  EXPECT_EQ(run.code(), "robot.state");
  sim_.reset();
  start_sim(port_);  // same port
  ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::ready; }));
  EXPECT_EQ(link_->connections(), 2);
  upload(make_trajectory(4));
}

TEST_F(RobotLinkTest, RunTimeoutSendsStop) {
  sim_.reset();
  speedup_ = 1.0;
  start_sim(0);
  auto o = link_options();
  o.run_timeout_ms = 150;
  start_link(o);
  ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::ready; }));
  upload(make_trajectory(40, 4, 20.0));  // about 4 s of motion
  Outcome run;
  link_->run(run.handler());
  ASSERT_TRUE(run_until([&] { return run.done(); }));
  EXPECT_EQ(run.code(), "robot.run_timeout");
  ASSERT_TRUE(run_until([&] { return link_->state() == RobotState::ready; }));
  ASSERT_TRUE(run_until([&] { return !executed_.empty(); }));
  EXPECT_LT(executed_[0].points.size(), 40u);
}

TEST_F(RobotLinkTest, ShutdownFailsPendingRequests) {
  connect_ready();
  auto f = sim_->faults();
  f.reply_delay_ms = 200;
  sim_->set_faults(f);
  Outcome up;
  link_->upload(make_trajectory(6), up.handler());
  link_->shutdown();
  ASSERT_TRUE(run_until([&] { return up.done(); }));
  EXPECT_EQ(up.code(), "robot.shutdown");
  EXPECT_EQ(link_->state(), RobotState::disconnected);
  run_until([] { return false; }, 100ms);
  EXPECT_EQ(link_->state(), RobotState::disconnected);  // no reconnect after shutdown
}

TEST_F(RobotLinkTest, SecondClientIsRefusedBusyFirstStaysUp) {
  connect_ready();
  RobotLink second(io_, link_options());
  std::vector<std::string> second_errors;
  second.on_state([&](RobotState, const fettle::Error& e) {
    if (!e.code.empty()) second_errors.push_back(e.code);
  });
  second.start();
  ASSERT_TRUE(run_until([&] {
    return std::find(second_errors.begin(), second_errors.end(), "robot.nak.busy") != second_errors.end();
  }));
  second.shutdown();
  EXPECT_EQ(link_->state(), RobotState::ready);
  upload(make_trajectory(3));
}

// ---- the simulated robot's own checks (a raw client, bytes by hand) ----------------

TEST_F(RobotLinkTest, SimClosesOnGarbageAndKeepsServing) {
  RawClient raw(io_);
  raw.connect(port_);
  ASSERT_TRUE(run_until([&] { return raw.connected; }));
  raw.send("1 HELLO 1 c 1000\n2 P\x01NG\n");
  ASSERT_TRUE(run_until([&] { return raw.closed; }));
  EXPECT_TRUE(raw.has_line_containing("NAK 0 SYNTAX"));
  EXPECT_EQ(sim_->stats().closed_for_garbage, 1);
  connect_ready();  // the server still serves
}

TEST_F(RobotLinkTest, SimClosesOnOversizeInput) {
  RawClient raw(io_);
  raw.connect(port_);
  ASSERT_TRUE(run_until([&] { return raw.connected; }));
  raw.send(std::string(500, 'A'));
  ASSERT_TRUE(run_until([&] { return raw.closed; }));
  EXPECT_EQ(sim_->stats().closed_for_garbage, 1);
  EXPECT_NE(sim_->stats().last_close_reason.find("oversize"), std::string::npos);
  connect_ready();
}

TEST_F(RobotLinkTest, SimNaksBadCrcAndNonUnitQuaternion) {
  RawClient raw(io_);
  raw.connect(port_);
  ASSERT_TRUE(run_until([&] { return raw.connected; }));
  raw.send(
      "1 HELLO 1 c 5000\n"
      "2 TRAJ 1 1 1 00000000\n"
      "3 CHUNK 1 0 1\n"
      "4 P 0 10.000 0.000 100.000 10.000 0 0 G\n"
      "5 Q 0 1.000000 0.000000 0.000000 0.000000\n"
      "6 END 1\n");
  ASSERT_TRUE(run_until([&] { return raw.has_line_containing("NAK 6 CRC"); }));
  EXPECT_TRUE(raw.has_line_containing("ACK 3"));  // the chunk itself was fine
  raw.send(
      "7 TRAJ 2 1 1 00000000\n"
      "8 CHUNK 1 0 1\n"
      "9 P 0 10.000 0.000 100.000 10.000 0 0 G\n"
      "10 Q 0 0.900000 0.000000 0.000000 0.000000\n");
  ASSERT_TRUE(run_until([&] { return raw.has_line_containing("NAK 10 QUAT"); }));
  raw.send("11 PING\n");
  ASSERT_TRUE(run_until([&] { return raw.has_line_containing("PONG 11"); }));
  raw.send("13 PING\n");  // a skipped sequence number: NAK SEQ and the robot hangs up
  ASSERT_TRUE(run_until([&] { return raw.closed; }));
  EXPECT_TRUE(raw.has_line_containing("NAK 13 SEQ"));
}

TEST_F(RobotLinkTest, SimWatchdogClosesASilentClient) {
  RawClient raw(io_);
  raw.connect(port_);
  ASSERT_TRUE(run_until([&] { return raw.connected; }));
  raw.send("1 HELLO 1 c 100\n");
  ASSERT_TRUE(run_until([&] { return raw.has_line_containing("ACK 1 1 fettle-sim-robot"); }));
  ASSERT_TRUE(run_until([&] { return raw.closed; }, 1000ms));
  EXPECT_NE(sim_->stats().last_close_reason.find("watchdog"), std::string::npos);
}

}  // namespace
