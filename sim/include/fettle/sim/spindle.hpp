#pragma once
// The simulated grinding spindle drive: a CANopen (CiA 301) node with the CiA 402 power state
// machine in profile velocity (0x6060 = 3) or vl (2) mode, a speed ramp, heartbeat producer and
// consumer, TPDO1 with configurable mapping, EMCY on faults, and a load current that rises with
// the material removal rate the grinding simulation sets.
//
// It sits on any CanTransport (the in-process bus, SocketCAN vcan0), and SocketcandServer
// exposes an in-process bus to other processes with socketcand's rawmode protocol.
// Everything runs on the io_context it is given; the setters marked thread-safe may be called
// from other threads.
#include <atomic>
#include <cstdint>
#include <memory>
#include <string>

#include <boost/asio/io_context.hpp>

#include "fettle/core/result.hpp"
#include "fettle/drivers/canopen.hpp"
#include "fettle/drivers/canopen_transport.hpp"

namespace fettle::sim {

struct SpindleSimOptions {
  std::uint8_t node_id = 1;
  double ramp_rpm_s = 20000.0;          ///< acceleration and deceleration
  double max_rpm = 12000.0;             ///< targets are clamped to this
  double rated_current_a = 8.0;         ///< 0x6075 (written in mA)
  double idle_current_a = 0.6;          ///< at speed, no load
  double accel_current_a = 3.0;         ///< extra while ramping
  double current_per_removal_a = 0.05;  ///< extra per mm³/s of material removed
  double trip_current_a = 16.0;         ///< above this the drive faults with over-current (0x2310)
  int tick_ms = 5;                      ///< simulation step
  std::uint32_t vendor_id = 0x00F377E1; ///< 0x1018:01
};

enum class SpindleFault { overcurrent, overtemperature, heartbeat_loss };
/// "overcurrent" | "overtemperature" | "heartbeat_loss"
Result<SpindleFault> parse_spindle_fault(const std::string& name);

class SimulatedSpindleDrive {
 public:
  SimulatedSpindleDrive(boost::asio::io_context& io, std::shared_ptr<canopen::CanTransport> transport,
                        SpindleSimOptions options = {});
  ~SimulatedSpindleDrive();
  SimulatedSpindleDrive(const SimulatedSpindleDrive&) = delete;
  SimulatedSpindleDrive& operator=(const SimulatedSpindleDrive&) = delete;

  /// Powers the drive: boot-up message, pre-operational, simulation ticking.
  void power_on();
  /// Injects a fault: EMCY with its code, error register, CiA 402 "fault" (thread-safe).
  void inject_fault(SpindleFault fault);
  /// Material removal rate of the grinding process in mm³/s: raises the load current (thread-safe).
  void set_material_removal_rate(double mm3_s);
  /// Stops (false) or resumes (true) this drive's heartbeat, as a broken cable would (thread-safe).
  void set_heartbeat_enabled(bool enabled);

  // Observation (io_context thread, or after it stopped).
  [[nodiscard]] canopen::DriveState state() const;
  [[nodiscard]] canopen::NmtState nmt_state() const;
  [[nodiscard]] double velocity_rpm() const;
  [[nodiscard]] double current_a() const;
  [[nodiscard]] std::int8_t mode() const;
  [[nodiscard]] std::uint16_t heartbeat_producer_ms() const;

  struct Impl;

 private:
  std::shared_ptr<Impl> impl_;
};

/// A socketcand server (rawmode only) bridging TCP clients onto an in-process bus: every client
/// that opened `bus_name` and switched to rawmode sees the bus's frames and may send onto it.
class SocketcandServer {
 public:
  /// Binds address:port (port 0: any free port) and starts accepting. Throws fettle::DeviceError.
  SocketcandServer(boost::asio::io_context& io, std::shared_ptr<canopen::InProcessBus> bus, const std::string& address,
                   int port, std::string bus_name = "can0");
  ~SocketcandServer();
  SocketcandServer(const SocketcandServer&) = delete;
  SocketcandServer& operator=(const SocketcandServer&) = delete;
  [[nodiscard]] int port() const;
  /// Clients currently connected.
  [[nodiscard]] std::size_t clients() const;
  /// Drops every client connection (to test link loss).
  void disconnect_all();

  struct Impl;

 private:
  std::shared_ptr<Impl> impl_;
};

}  // namespace fettle::sim
