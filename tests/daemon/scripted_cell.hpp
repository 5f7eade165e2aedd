#pragma once
// A cell of scripted devices for the runtime (RuntimeOptions' makers): each implements its
// device interface (drivers/device.hpp) without a wire behind it, answers at once on the loop
// thread, and lets a test provoke one fault at the step it chooses. With ScriptedProcessing
// (no vision, no planning) a whole cycle runs in milliseconds, so every fault case is a test of
// its own (test_cycle_faults.cpp). The wire protocols are tested against the loopback
// simulators in the link tests and end to end in test_fettled.cpp.
#include <atomic>
#include <chrono>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>

#include "fettle/core/error.hpp"
#include "fettle/daemon/processing.hpp"
#include "fettle/drivers/camera.hpp"
#include "fettle/drivers/plc_link.hpp"
#include "fettle/drivers/robot_link.hpp"
#include "fettle/drivers/spindle.hpp"

namespace fettle::test {

/// The lifecycle every scripted device shares (configure -> inactive -> activate -> active).
template <class Interface>
class ScriptedDevice : public Interface {
 public:
  Status configure() override {
    if (lifecycle_ == drivers::Lifecycle::unconfigured) lifecycle_ = drivers::Lifecycle::inactive;
    return {};
  }
  Status activate() override {
    if (lifecycle_ == drivers::Lifecycle::unconfigured)
      return Error{std::string(this->kind()) + ".lifecycle", "activate() before configure()", ErrorKind::unavailable};
    lifecycle_ = drivers::Lifecycle::active;
    return {};
  }
  void deactivate() override {
    if (lifecycle_ == drivers::Lifecycle::active) lifecycle_ = drivers::Lifecycle::inactive;
  }
  [[nodiscard]] drivers::Lifecycle lifecycle() const override { return lifecycle_; }
  [[nodiscard]] const Error& last_error() const override { return last_error_; }

 protected:
  drivers::Lifecycle lifecycle_ = drivers::Lifecycle::unconfigured;
  Error last_error_;
};

/// Captures on the runtime's camera thread: a small flat cloud, or the next scripted error.
class ScriptedCamera final : public ScriptedDevice<drivers::CameraDevice> {
 public:
  struct Script {
    std::mutex mutex;
    std::deque<Error> failures;  ///< returned by the next captures, one each
    std::atomic<int> captures{0};
  };
  explicit ScriptedCamera(std::shared_ptr<Script> script) : script_(std::move(script)) {}

  Result<drivers::CameraCapture> capture() override {
    ++script_->captures;
    {
      std::lock_guard lock(script_->mutex);
      if (!script_->failures.empty()) {
        Error e = script_->failures.front();
        script_->failures.pop_front();
        return e;
      }
    }
    drivers::CameraCapture c;
    c.cloud.width = 8;
    c.cloud.height = 6;
    for (std::uint32_t i = 0; i < c.cloud.width * c.cloud.height; ++i)
      c.cloud.points.emplace_back(static_cast<float>(i % 8), static_cast<float>(i / 8), 500.0F);
    c.stats.attempts = 1;
    return c;
  }
  [[nodiscard]] drivers::CameraInfo info() const override {
    drivers::CameraInfo i;
    i.model = "scripted";
    return i;
  }

 private:
  std::shared_ptr<Script> script_;
};

/// The robot controller: uploads and runs complete after a few milliseconds unless scripted
/// otherwise; drop() and fault() act as the real link reports a lost connection or a FAULT.
class ScriptedRobot final : public ScriptedDevice<drivers::RobotDevice> {
 public:
  explicit ScriptedRobot(boost::asio::io_context& io) : io_(io), run_timer_(io) {}

  std::optional<Error> upload_error;  ///< the next upload's answer (e.g. robot.nak.ENVELOPE)
  std::chrono::milliseconds run_time{30};
  std::function<void()> on_run_started;  ///< called (posted) when a run begins
  int uploads = 0;
  int runs = 0;
  int stops = 0;

  Status activate() override {
    if (auto st = ScriptedDevice::activate(); !st) return st;
    boost::asio::post(io_, [this] { set(drivers::RobotState::ready); });
    return {};
  }
  void deactivate() override {
    ScriptedDevice::deactivate();
    finish_run(Error{"robot.shutdown", "deactivated", ErrorKind::cancelled});
    state_ = drivers::RobotState::disconnected;
  }
  void upload(const Trajectory& /*trajectory*/, Handler done) override {
    if (state_ != drivers::RobotState::ready && state_ != drivers::RobotState::uploaded)
      return done(Error{"robot.state", "upload in state " + std::string(drivers::to_string(state_)), ErrorKind::unavailable});
    ++uploads;
    set(drivers::RobotState::uploading);
    boost::asio::post(io_, [this, done = std::move(done)] {
      if (state_ != drivers::RobotState::uploading) return done(Error{"robot.stopped", "upload aborted", ErrorKind::cancelled});
      if (upload_error) {
        set(drivers::RobotState::ready);
        return done(*std::exchange(upload_error, std::nullopt));
      }
      set(drivers::RobotState::uploaded);
      done({});
    });
  }
  void run(Handler done) override {
    if (state_ != drivers::RobotState::uploaded)
      return done(Error{"robot.state", "run in state " + std::string(drivers::to_string(state_)), ErrorKind::unavailable});
    ++runs;
    set(drivers::RobotState::running);
    run_done_ = std::move(done);
    if (on_run_started) boost::asio::post(io_, on_run_started);
    run_timer_.expires_after(run_time);
    run_timer_.async_wait([this](const boost::system::error_code& ec) {
      if (ec || state_ != drivers::RobotState::running) return;
      set(drivers::RobotState::uploaded);
      finish_run({});
    });
  }
  void stop(Handler done) override {
    ++stops;
    boost::asio::post(io_, [this, done = std::move(done)] {
      if (state_ == drivers::RobotState::running || state_ == drivers::RobotState::uploading) {
        run_timer_.cancel();
        set(drivers::RobotState::ready);
        finish_run(Error{"robot.stopped", "stopped by STOP", ErrorKind::cancelled});
      } else if (state_ == drivers::RobotState::uploaded) {
        set(drivers::RobotState::ready);
      }
      done({});
    });
  }
  void reset(Handler done) override {
    boost::asio::post(io_, [this, done = std::move(done)] {
      set(drivers::RobotState::ready);
      done({});
    });
  }
  [[nodiscard]] drivers::RobotState state() const override { return state_; }
  void on_state(StateHandler h) override { on_state_ = std::move(h); }

  /// The connection is lost (the controller halts on its own); it comes back 50 ms later.
  void drop() {
    run_timer_.cancel();
    const Error e{"robot.connection_lost", "scripted: the robot controller closed the connection", ErrorKind::link_lost};
    set(drivers::RobotState::disconnected, e);
    finish_run(e);
    run_timer_.expires_after(std::chrono::milliseconds(50));
    run_timer_.async_wait([this](const boost::system::error_code& ec) {
      if (!ec && lifecycle_ == drivers::Lifecycle::active) set(drivers::RobotState::ready);
    });
  }
  /// The robot reports FAULT <code> while running.
  void fault(const std::string& code) {
    run_timer_.cancel();
    const Error e{"robot.fault." + code, "scripted: the robot reported FAULT " + code, ErrorKind::device_fault};
    set(drivers::RobotState::faulted, e);
    finish_run(e);
  }

 private:
  void set(drivers::RobotState s, const Error& cause = {}) {
    state_ = s;
    if (on_state_) on_state_(s, cause);
  }
  void finish_run(Status s) {
    if (auto d = std::exchange(run_done_, nullptr)) d(std::move(s));
  }

  boost::asio::io_context& io_;
  boost::asio::steady_timer run_timer_;
  drivers::RobotState state_ = drivers::RobotState::disconnected;
  StateHandler on_state_;
  Handler run_done_;
};

/// The spindle: at speed (or stopped) at once; inject_fault() latches a drive fault as an EMCY would.
class ScriptedSpindle final : public ScriptedDevice<drivers::SpindleDevice> {
 public:
  explicit ScriptedSpindle(boost::asio::io_context& io) : io_(io) {}

  int spin_ups = 0;

  void activate_async(Done done) override {
    if (auto st = ScriptedDevice::activate(); !st) return done(st);
    boost::asio::post(io_, [this, done = std::move(done)] {
      st_.configured = true;
      st_.heartbeat_ok = true;
      st_.state = canopen::DriveState::switch_on_disabled;
      done({});
    });
  }
  void deactivate() override {
    ScriptedDevice::deactivate();
    st_.target_rpm = st_.velocity_rpm = 0.0;
    st_.configured = false;
  }
  bool released = false;  ///< deactivate_async() completed: the program may exit

  void deactivate_async(Done done) override {
    deactivate();
    released = true;
    boost::asio::post(io_, [done = std::move(done)] { done({}); });
  }
  void spin_up(double rpm, Done done) override {
    boost::asio::post(io_, [this, rpm, done = std::move(done)] {
      if (!st_.configured) return done(Error{"spindle.not_started", "spin_up before activate()", ErrorKind::unavailable});
      if (st_.fault) return done(*st_.fault);
      ++spin_ups;
      st_.target_rpm = st_.velocity_rpm = rpm;
      st_.state = canopen::DriveState::operation_enabled;
      done({});
    });
  }
  void spin_down(Done done) override {
    boost::asio::post(io_, [this, done = std::move(done)] {
      if (st_.fault) return done(*st_.fault);
      st_.target_rpm = st_.velocity_rpm = 0.0;
      st_.state = canopen::DriveState::ready_to_switch_on;
      done({});
    });
  }
  void fault_reset(Done done) override {
    boost::asio::post(io_, [this, done = std::move(done)] {
      st_.fault.reset();
      st_.state = canopen::DriveState::switch_on_disabled;
      done({});
    });
  }
  void on_event(std::function<void(const drivers::SpindleEvent&)> handler) override { on_event_ = std::move(handler); }
  [[nodiscard]] const drivers::SpindleStatus& status() const override { return st_; }

  /// The drive faults (its power stage off, the wheel coasts down) and says so.
  void inject_fault(const std::string& what) {
    st_.fault = Error{"spindle.fault", "scripted: " + what, ErrorKind::device_fault};
    st_.state = canopen::DriveState::fault;
    st_.target_rpm = st_.velocity_rpm = 0.0;
    if (on_event_) on_event_(drivers::SpindleEvent{drivers::SpindleEvent::Kind::fault, st_.fault->message, {}, st_.state});
  }

 private:
  boost::asio::io_context& io_;
  drivers::SpindleStatus st_;
  std::function<void(const drivers::SpindleEvent&)> on_event_;
};

/// The line PLC: the test sends its commands and cycle requests; the slide reaches a commanded
/// position after slide_time unless it is faulted.
class ScriptedPlc final : public ScriptedDevice<drivers::PlcDevice> {
 public:
  ScriptedPlc(boost::asio::io_context& io, Handler on_event) : io_(io), on_event_(std::move(on_event)) {}

  std::chrono::milliseconds slide_time{5};
  std::vector<drivers::plc::CycleResult> results;
  int accepted = 0;
  int slide_commands = 0;
  std::uint16_t fault_code = 0;  ///< the latched fault the PLC sees (0: none)
  packml::State shown = packml::State::undefined;  ///< the state fettled shows the PLC
  std::vector<packml::State> states;  ///< every state fettled showed, in order (changes only)

  Status activate() override {
    if (auto st = ScriptedDevice::activate(); !st) return st;
    link_up();
    return {};
  }
  Status set_state(packml::State s) override {
    if (states.empty() || states.back() != s) states.push_back(s);
    shown = s;
    return {};
  }
  Result<std::uint64_t> command_slide(int target) override {
    const auto number = static_cast<std::uint64_t>(++slide_commands);
    if (slide_faulted_) return number;  // a faulted axis does not move
    acked_ = number;
    emit(drivers::plc::SlideState{drivers::plc::SlideStatus::moving, target, acked_});
    auto timer = std::make_shared<boost::asio::steady_timer>(io_, slide_time);
    timer->async_wait([this, timer, target](const boost::system::error_code& ec) {
      if (ec || slide_faulted_) return;
      position_ = target;
      emit(drivers::plc::SlideState{
          target == 0 ? drivers::plc::SlideStatus::at_home : drivers::plc::SlideStatus::at_position, target, acked_});
    });
    return number;
  }
  void accept_cycle() override { ++accepted; }
  Status report_result(drivers::plc::CycleResult r) override {
    results.push_back(r);
    if (holds_results) ++unacknowledged_;
    return {};
  }
  Status raise_fault(std::uint16_t code) override {
    if (fault_code == 0) fault_code = code;
    return {};
  }
  [[nodiscard]] drivers::plc::LinkStatus status() const override {
    drivers::plc::LinkStatus s;
    s.up = up_;
    s.results_waiting = unacknowledged_;
    return s;
  }

  // What the PLC does.
  void command(packml::Command c) {
    if (c == packml::Command::reset) fault_code = 0;  // a Reset clears the latch (docs/plc-interface.md)
    emit(drivers::plc::PackMLCommand{c});
  }
  void request(int recipe_id) { emit(drivers::plc::CycleRequest{recipe_id}); }
  /// While set, the PLC does not acknowledge the results it gets (cycle_result_ack).
  bool holds_results = false;
  /// The PLC acknowledges the results it got.
  void acknowledge_results() {
    holds_results = false;
    unacknowledged_ = 0;
    emit(drivers::plc::ResultAcknowledged{results.empty() ? drivers::plc::CycleResult::none : results.back()});
  }
  void fault_slide() {
    slide_faulted_ = true;
    emit(drivers::plc::SlideState{drivers::plc::SlideStatus::fault, position_, acked_});
  }
  /// The PLC stops answering (its heartbeat froze).
  void drop() {
    up_ = false;
    emit(drivers::plc::LinkDown{drivers::plc::LinkDownReason::heartbeat_stale, "scripted: the PLC's heartbeat froze"});
  }
  /// The PLC answers again (the link reconnected).
  void restore() { link_up(); }
  [[nodiscard]] bool up() const { return up_; }

 private:
  void link_up() {
    up_ = true;
    emit(drivers::plc::LinkUp{"scripted"});
    emit(drivers::plc::SlideState{drivers::plc::SlideStatus::at_home, 0, acked_});
  }
  void emit(drivers::plc::Event e) {
    boost::asio::post(io_, [h = on_event_, e = std::move(e)] { h(e); });
  }

  boost::asio::io_context& io_;
  Handler on_event_;
  bool up_ = false;
  bool slide_faulted_ = false;
  int position_ = 0;
  std::uint64_t acked_ = 0;
  int unacknowledged_ = 0;
};

/// Processing without vision or planning: a short valid trajectory (or the scripted error)
/// and an OK verification. Called on the runtime's worker pool.
struct ScriptedProcessing {
  std::mutex mutex;
  std::optional<Error> process_error;  ///< the next process() call's answer
  std::atomic<int> processed{0};
  std::atomic<int> verified{0};

  std::shared_ptr<const daemon::Processing> make() {
    auto p = std::make_shared<daemon::Processing>();
    p->load_recipe = [](const std::filesystem::path& file) {
      auto r = std::make_shared<process::LoadedRecipe>();
      r->recipe.id = "scripted-part";
      r->recipe.source = file;
      return std::shared_ptr<const process::LoadedRecipe>(std::move(r));
    };
    p->process = [this](const process::LoadedRecipe& recipe, const config::CellConfig&,
                        const std::vector<process::View>&, const process::ProcessOptions&) -> Result<process::ProcessOutput> {
      ++processed;
      {
        std::lock_guard lock(mutex);
        if (process_error) return *std::exchange(process_error, std::nullopt);
      }
      process::ProcessOutput out;
      out.trajectory.part_id = recipe.recipe.id;
      out.trajectory.segment_regions = {"riser"};
      const MoveKind kinds[] = {MoveKind::approach, MoveKind::grind, MoveKind::grind, MoveKind::retract};
      for (int i = 0; i < 4; ++i) {
        TrajectoryPoint pt;
        pt.T_base_tool.position_mm = Vec3(10.0 * i, 0.0, 100.0);
        pt.speed_mm_s = 20.0;
        pt.spindle_rpm = 6000.0;
        pt.kind = kinds[i];
        out.trajectory.points.push_back(pt);
      }
      return out;
    };
    p->verify = [this](const process::LoadedRecipe&, const config::CellConfig&, const std::vector<process::View>&,
                       const std::vector<Trajectory>&, const process::VerifyOptions&) -> Result<process::VerificationResult> {
      ++verified;
      return process::VerificationResult{};
    };
    return p;
  }
};

}  // namespace fettle::test
