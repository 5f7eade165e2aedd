#pragma once
// The simulated robot controller: the robot side of docs/robot-protocol.md as a TCP
// server on a caller-owned boost::asio::io_context (use it in-process from tests and
// `fettle-sim cell`, or through `fettle-sim robot`).
//
// It validates what it receives (syntax, sequence numbers, chunk order, CRC, unit
// quaternions, its own envelope and limits → NAK), "executes" trajectories in real or
// accelerated time, reports progress by segment, hands the executed path to a
// callback, and injects faults on request. Garbage or oversize input closes that
// client's connection with a logged reason; the server keeps serving. One client at a
// time: a second one gets NAK BUSY and is closed.
//
// Every member must be called on the io_context's thread (or before it runs).
#include <array>
#include <functional>
#include <memory>
#include <string>

#include <boost/asio/io_context.hpp>

#include "fettle/core/trajectory.hpp"

namespace fettle::sim {

/// Where the simulated robot can reach and how fast it may go.
struct RobotEnvelope {
  std::array<double, 3> min_mm{-2000.0, -2000.0, -1000.0};  ///< axis-aligned box in the base frame
  std::array<double, 3> max_mm{2000.0, 2000.0, 2500.0};
  double max_speed_mm_s = 2000.0;
  double max_spindle_rpm = 30000.0;
};

/// Faults to inject. One-shot faults clear themselves once they fired.
struct RobotFaults {
  std::string nak_verb;           ///< one-shot: NAK the next line with this verb (e.g. "TRAJ", "CHUNK", "END", "RUN") ...
  std::string nak_code = "STATE"; ///< ... with this code
  int disconnect_at_chunk = 0;    ///< one-shot: close the connection when chunk k (1-based) begins; 0 = off
  int fault_at_point = -1;        ///< one-shot: FAULT when execution reaches this point index; -1 = off
  std::string fault_code = "COLLISION";
  int reply_delay_ms = 0;         ///< every reply (ACK, NAK, PONG) goes out this much later
  bool garbage_reply = false;     ///< one-shot: the next reply is replaced by binary garbage
  bool oversize_reply = false;    ///< one-shot: the next reply is replaced by a 200-character line
  bool ignore_pings = false;      ///< never answer PING (the client must declare the link down)
};

struct RobotSimOptions {
  std::string address = "127.0.0.1";
  int port = 0;                        ///< 0 = ephemeral; see RobotSim::port()
  std::string robot_id = "fettle-sim-robot";
  std::string expected_cell_id;        ///< empty = accept any cell id in HELLO
  double speedup = 1.0;                ///< 1 = real time, 100 = 100x faster; <= 0 executes instantly
  RobotEnvelope envelope;
  RobotFaults faults;
};

/// What the server has seen (for tests and the command's summary).
struct RobotSimStats {
  int connections = 0;        ///< accepted connections
  int closed_for_garbage = 0; ///< connections closed for bad input
  int naks = 0;
  /// NAKs for a point outside the robot's limits (ENVELOPE, SPEED, SPINDLE, QUAT), never
  /// injected: a trajectory that reached the robot without passing Fettle's validation.
  int limit_naks = 0;
  int trajectories_received = 0;
  int runs_started = 0;           ///< RUNs accepted
  int trajectories_executed = 0;  ///< runs that ended with DONE
  int trajectories_halted = 0;    ///< runs stopped before their end (STOP, RESET, connection lost)
  std::string last_halt_reason;   ///< "STOP", "RESET" or "connection closed"
  std::string last_close_reason;
};

class RobotSim {
 public:
  /// Gets the executed part of a trajectory after every run (DONE, FAULT or STOP).
  using ExecutedHandler = std::function<void(const Trajectory& executed)>;

  RobotSim(boost::asio::io_context& io, RobotSimOptions options);
  ~RobotSim();
  RobotSim(const RobotSim&) = delete;
  RobotSim& operator=(const RobotSim&) = delete;

  /// Binds and starts accepting; throws fettle::DeviceError if the address cannot be bound.
  void start();
  /// Stops accepting and closes every connection (a robot switched off).
  void close();
  /// Closes the current client connection but keeps listening.
  void drop_client();

  [[nodiscard]] int port() const;  ///< the bound port (after start())
  void set_faults(const RobotFaults& faults);
  [[nodiscard]] const RobotFaults& faults() const;
  void on_executed(ExecutedHandler h);
  /// Gets the executed trajectory when a run completes, BEFORE DONE is sent: a simulated world
  /// (e.g. a camera that shows what the robot holds) updates here, so it is current by the
  /// time the client hears DONE. Runs on the io_context's thread and delays DONE while it runs.
  void on_arrived(ExecutedHandler h);
  /// Like on_arrived, but DONE waits until the handler calls `done` (from any thread) without
  /// blocking the robot's I/O meanwhile: a simulated process that takes real time (grinding the
  /// casting's material) finishes before the client hears DONE, as on a real cell. A STOP or a
  /// dropped connection in between cancels the DONE.
  using SettleHandler = std::function<void(const Trajectory& executed, std::function<void()> done)>;
  void on_settle(SettleHandler h);
  [[nodiscard]] const RobotSimStats& stats() const;

 private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

}  // namespace fettle::sim
