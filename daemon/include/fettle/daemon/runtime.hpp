#pragma once
// The cell controller's runtime (docs/daemon.md): one Boost.Asio event loop thread owns every
// piece of state; a worker pool runs the pipeline (process / verify); the camera, which blocks
// in Aravis, has a thread of its own; the PLC link has its own thread and posts its events to
// the loop. Every cycle step has a timeout.
//
// The PackML state machine (packml_machine.hpp) is mirrored to the PLC. In Execute each cycle
// request runs one cycle:
//   slide to photo position(s) -> capture(s) -> slide home -> process (pool) -> validate ->
//   upload -> spindle up -> run -> spindle down -> verification scan (OK | one re-grind | NOK)
//   -> result to the PLC
// Faults (faults.hpp, docs/faults.md) end in Held (recoverable) or Aborted (safety-relevant;
// the robot is stopped first). Every cycle gets its record (records.hpp).
//
//   boost::asio::io_context io;
//   Runtime runtime(io, config::load_cell(path), {});
//   runtime.start();            // setup: throws UserError (recipes, state dir) / DeviceError
//   io.run();                   // the event loop; stop with runtime.shutdown()
#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <string>

#include <boost/asio/io_context.hpp>

#include "fettle/config/cell.hpp"
#include "fettle/daemon/control.hpp"
#include "fettle/daemon/faults.hpp"
#include "fettle/drivers/packml.hpp"
#include "fettle/drivers/plc_link.hpp"

namespace fettle::drivers {
class CameraDevice;
class RobotDevice;
class SpindleDevice;
}  // namespace fettle::drivers

namespace fettle::daemon {
struct Processing;  // processing.hpp
}  // namespace fettle::daemon

namespace fettle::daemon {

struct RuntimeOptions {
  /// > 0: after this many cycles Execute completes (Completing -> Complete). 0 = run forever.
  int max_cycles = 0;
  /// Extra time on top of each device's own timeout before the cycle gives up on a step.
  std::chrono::milliseconds step_margin{5000};
  /// Keep raw captures in the records (capture_N.ply, rescan_N.ply).
  bool keep_captures = true;
  /// Called on the loop thread after every PackML state change (e.g. sd_notify STATUS=).
  std::function<void(packml::State, const std::string& status_line)> on_state;

  // The devices and the processing the cycle runs on. Empty: the cell's real ones (the
  // GigE Vision camera, the robot's TCP line protocol, the CANopen spindle, the Modbus PLC,
  // fettle::process). Tests give scripted ones (tests/daemon/test_cycle_faults.cpp); each
  // device is configured and activated by the runtime.
  std::function<std::unique_ptr<drivers::CameraDevice>(const config::CellConfig&)> make_camera;
  std::function<std::unique_ptr<drivers::RobotDevice>(boost::asio::io_context&, const config::CellConfig&)> make_robot;
  std::function<std::unique_ptr<drivers::SpindleDevice>(boost::asio::io_context&, const config::CellConfig&)>
      make_spindle;
  /// `on_event` must be called on the loop thread (post there).
  std::function<std::unique_ptr<drivers::PlcDevice>(boost::asio::io_context&, const config::CellConfig&,
                                                    drivers::PlcDevice::Handler on_event)>
      make_plc;
  std::shared_ptr<const Processing> processing;
};

/// A snapshot for the control socket and tests.
struct RuntimeStatus {
  packml::State state = packml::State::stopped;
  std::optional<Fault> fault;  ///< the latched fault, until a Reset
  std::string cycle_id;        ///< the running cycle, empty if none
  std::string step;            ///< its current step
  long long cycles_total = 0;  ///< cycles run since start
  std::string last_result;
  bool plc_up = false;
  std::string robot_state;
  bool spindle_configured = false;
};

class Runtime : public control::Handler {
 public:
  Runtime(boost::asio::io_context& io, config::CellConfig cell, RuntimeOptions options = {});
  ~Runtime() override;
  Runtime(const Runtime&) = delete;
  Runtime& operator=(const Runtime&) = delete;

  /// Loads the recipes and the calibration, opens the records (marking interrupted cycles),
  /// starts the device links. Throws UserError / DeviceError (setup only).
  void start();
  /// Stops motion (robot first, then spindle), ends a running cycle as interrupted-by-shutdown,
  /// closes the links; calls `done` on the loop when everything is closed.
  void shutdown(std::function<void()> done = {});

  /// Applies a PackML command as if the PLC had sent it (loop thread).
  Status command(packml::Command command, const std::string& source);
  [[nodiscard]] RuntimeStatus status_snapshot() const;
  [[nodiscard]] packml::State state() const;

  // control::Handler (loop thread)
  control::json status() override;
  Result<control::json> last_cycle() override;
  Result<control::json> cycles(std::size_t limit) override;
  Result<control::json> reset() override;
  Result<control::json> hold() override;
  Result<control::json> unhold() override;
  Result<control::json> dry_cycle() override;
  Result<control::json> tool_changed(const std::string& tool) override;
  Status maintenance_changing(bool on) override;

  struct Impl;

 private:
  std::shared_ptr<Impl> impl_;
};

}  // namespace fettle::daemon
