#pragma once
// The grinding spindle: a CANopen master for one CiA 402 drive in velocity mode.
//
// Asynchronous on the io_context it is given (the daemon's one thread): every call returns at
// once and completes through its handler with a Status; nothing blocks. Every step has a
// timeout. A drive in fault (EMCY, fault statusword, heartbeat lost, reboot) is latched and
// reported as an event; it is never re-enabled until fault_reset() is called explicitly.
// See docs/spindle-canopen.md for the objects used and the start-up sequence.
//
// The cycle uses the spindle as a device with the cell's common lifecycle (device.hpp):
//   SpindleDrive drive(io, transport, options);
//   drive.configure();                 // checks the options, no bus traffic
//   drive.activate_async(done);        // NMT reset, boot-up, SDO configuration, NMT start
//   drive.spin_up(rpm, done);  drive.spin_down(done);
//   drive.deactivate();                // target 0, the drive ramps down; a later activate() starts again
//   drive.deactivate_async(done);      // ... and releases the drive before the program exits
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>

#include <boost/asio/io_context.hpp>

#include "fettle/config/spindle.hpp"
#include "fettle/core/result.hpp"
#include "fettle/drivers/canopen.hpp"
#include "fettle/drivers/canopen_transport.hpp"
#include "fettle/drivers/device.hpp"

namespace fettle::drivers {

struct SpindleOptions {
  std::uint8_t node_id = 1;
  std::uint8_t master_node_id = 127;  ///< our heartbeat's id; the drive consumes it (0x1016)
  canopen::OperationMode mode = canopen::OperationMode::profile_velocity;
  int heartbeat_producer_ms = 100;  ///< written to the drive's 0x1017; also our own heartbeat period
  int heartbeat_timeout_ms = 300;   ///< drive heartbeat missing longer → fault; drive's 0x1016 time for ours
  int sdo_timeout_ms = 200;
  int step_timeout_ms = 1000;        ///< each state-machine transition, boot-up, NMT start
  int spin_up_timeout_ms = 10000;    ///< reaching (or leaving) speed
  int feedback_period_ms = 20;       ///< TPDO1 event timer (0x1800:05)
  double at_speed_tolerance_rpm = 100.0;
  double max_rpm = 12000.0;

  static SpindleOptions from_config(const config::SpindleSection& s);
};

/// What the master knows about the drive (updated from TPDO1, heartbeats, EMCY, SDO reads).
struct SpindleStatus {
  bool configured = false;                 ///< activate() finished its SDO configuration
  bool heartbeat_ok = false;               ///< the drive's heartbeat arrives in time
  canopen::NmtState nmt = canopen::NmtState::boot_up;
  std::uint16_t statusword = 0;
  canopen::DriveState state = canopen::DriveState::unknown;
  double velocity_rpm = 0.0;               ///< 0x606C (drive velocity units taken as rpm)
  double current_permille = 0.0;           ///< 0x6078, thousandths of the rated current
  double current_a = 0.0;                  ///< from 0x6078 and the rated current 0x6075
  double rated_current_a = 0.0;            ///< 0x6075
  double target_rpm = 0.0;
  std::uint64_t feedback_frames = 0;       ///< TPDO1 frames received
  std::optional<Error> fault;              ///< latched fault: cleared only by fault_reset()
  std::optional<canopen::Emergency> last_emcy;
};

struct SpindleEvent {
  enum class Kind {
    fault,               ///< a fault was latched (EMCY, statusword, heartbeat lost, reboot, link lost)
    emergency,           ///< any EMCY frame (including 0x0000 "error reset")
    heartbeat_lost,
    heartbeat_restored,
    link_error,          ///< transport problem (error frame, socket error)
    state_changed,       ///< CiA 402 state changed
  };
  Kind kind = Kind::fault;
  std::string message;
  std::optional<canopen::Emergency> emcy;
  canopen::DriveState state = canopen::DriveState::unknown;
};
std::string to_string(SpindleEvent::Kind k);

/// The grinding spindle as a device (device.hpp): what the cycle uses. Asynchronous: every
/// operation completes through its handler on the io_context's thread.
class SpindleDevice : public Device {
 public:
  using Done = std::function<void(Status)>;

  [[nodiscard]] std::string_view kind() const override { return "spindle"; }
  /// activate() with its completion: brings the drive up (for SpindleDrive: NMT reset,
  /// boot-up, configuration, NMT start); `done` when it is ready to spin up. activate() begins
  /// the same and returns at once; status().configured says when it is done.
  virtual void activate_async(Done done) = 0;
  /// deactivate() with its completion: the device is also released, so the program may exit
  /// next without the device faulting (for SpindleDrive: the drive stops watching our heartbeat
  /// and goes to "switch on disabled").
  virtual void deactivate_async(Done done) = 0;
  /// Enables the drive and reaches `rpm`; refused while a fault is latched.
  virtual void spin_up(double rpm, Done done) = 0;
  /// Target 0, waits for standstill, then leaves the drive switched on but without torque.
  virtual void spin_down(Done done) = 0;
  /// Clears a latched drive fault (the drive's fault reset), explicitly only.
  virtual void fault_reset(Done done) = 0;
  /// Faults, EMCY, heartbeat and link events as they happen.
  virtual void on_event(std::function<void(const SpindleEvent&)> handler) = 0;
  [[nodiscard]] virtual const SpindleStatus& status() const = 0;
};

class SpindleDrive final : public SpindleDevice {
 public:
  using ValueDone = std::function<void(Result<std::uint32_t>)>;

  SpindleDrive(boost::asio::io_context& io, std::shared_ptr<canopen::CanTransport> transport,
               SpindleOptions options);
  ~SpindleDrive() override;

  /// Checks the options (node ids, heartbeat periods, timeouts, max_rpm); an error names the
  /// [spindle] key ("spindle.config").
  Status configure() override;
  /// activate_async() with a handler that logs a failure.
  Status activate() override;
  /// NMT reset communication, wait for boot-up, configure (0x1017, 0x1016, 0x6075, TPDO1, 0x6060),
  /// NMT start. Fails with "spindle.fault" if the drive is in fault afterwards, with
  /// "spindle.lifecycle" before configure().
  void activate_async(Done done) override;
  /// Fails the running operation ("spindle.inactive") and sets the target to 0 (the drive ramps
  /// down on its own); the bus and both heartbeats stay, so the drive does not fault.
  void deactivate() override;
  /// deactivate(), then disable voltage (controlword 0x00: "switch on disabled") and switch the
  /// drive's heartbeat consumer off (0x1016:01 = 0): a clean stop of fettled leaves the drive
  /// without the heartbeat fault 0x8130 (docs/spindle-canopen.md). A spinning wheel coasts: spin
  /// it down first.
  void deactivate_async(Done done) override;
  [[nodiscard]] Lifecycle lifecycle() const override;
  [[nodiscard]] const Error& last_error() const override;

  /// Enables the drive (shutdown → switch on → enable operation) and sets the target; completes
  /// when |actual − rpm| ≤ tolerance. Refused while a fault is latched.
  void spin_up(double rpm, Done done) override;
  /// Target 0, waits for standstill, then shutdown (ready to switch on). Cancels a running spin_up.
  void spin_down(Done done) override;
  /// Fault reset (controlword bit 7), waits for "switch on disabled", clears the latched fault.
  void fault_reset(Done done) override;

  /// Events (faults, EMCY, heartbeat, link) as they happen, on the io_context thread.
  void on_event(std::function<void(const SpindleEvent&)> handler) override;
  [[nodiscard]] const SpindleStatus& status() const override;

  // Lower-level services, for commissioning and tests.
  void sdo_read(std::uint16_t index, std::uint8_t sub, ValueDone done);
  void sdo_write(std::uint16_t index, std::uint8_t sub, std::uint32_t value, std::uint8_t size, Done done);
  void nmt(canopen::NmtCommand command);

  struct Impl;

 private:
  std::shared_ptr<Impl> impl_;
};

/// The transport the [spindle] section names: "socketcan" (CAN_RAW on `interface`, filtered to
/// the drive's COB-IDs) or "socketcand" (address:port, bus `interface`). "sim" needs the
/// simulated drive in the same process and throws fettle::UserError here.
std::shared_ptr<canopen::CanTransport> make_spindle_transport(boost::asio::io_context& io,
                                                              const config::SpindleSection& s);

}  // namespace fettle::drivers
