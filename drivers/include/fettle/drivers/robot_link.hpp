#pragma once
// The robot controller link: an asynchronous TCP client of the line protocol in
// docs/robot-protocol.md, on a caller-owned boost::asio::io_context.
//
// Everything runs on the io_context's thread: call every member from that thread
// (or before it runs). No call blocks; results arrive as Status values through
// completion handlers. After every fault the link is in a defined state:
//
//   disconnected --start()--> connecting --HELLO ACK--> ready
//   ready/uploaded --upload()--> uploading --END ACK--> uploaded --run()--> running
//   running --DONE--> uploaded      running --FAULT--> faulted --reset()--> ready
//   any connected state --stop()--> stopping --ACK--> ready (faulted stays faulted)
//   a lost connection, protocol error, missed PONGs or a reply timeout
//     --> disconnected (pending handlers fail with the reason) --> connecting again
//   a NAK fails only the request it answers (upload → ready, run → uploaded).
#include <functional>
#include <memory>
#include <string>
#include <string_view>

#include <boost/asio/io_context.hpp>

#include "fettle/config/robot.hpp"
#include "fettle/core/result.hpp"
#include "fettle/core/trajectory.hpp"
#include "fettle/drivers/device.hpp"

namespace fettle::drivers {

enum class RobotState { disconnected, connecting, ready, uploading, uploaded, running, stopping, faulted };
std::string_view to_string(RobotState s);

struct RobotLinkOptions {
  std::string address = "127.0.0.1";  ///< IPv4 address of the robot controller
  int port = 30100;
  std::string cell_id = "cell";       ///< sent in HELLO; the robot program checks it
  int connect_timeout_ms = 2000;      ///< TCP connect + HELLO
  int reply_timeout_ms = 2000;        ///< every ACK/NAK wait
  int ping_period_ms = 1000;          ///< PING period ...
  int missed_pings = 3;               ///< ... this many without PONG → link down
  int chunk_points = 20;              ///< points per upload chunk
  int run_timeout_ms = 600000;        ///< RUN accepted → DONE/FAULT
  int reconnect_initial_ms = 100;     ///< reconnect backoff, doubling ...
  int reconnect_max_ms = 5000;        ///< ... up to this
  bool reconnect = true;              ///< reconnect after the link goes down

  static RobotLinkOptions from_config(const config::RobotSection& s);
};

struct RobotProgress {
  int trajectory_id = 0;
  int segment = 0;
  int point_index = 0;  ///< first point of the segment the robot now moves on
};

/// The robot controller as a device (device.hpp): what the cycle uses. activate() starts
/// connecting; the link's state (ready, running, ...) and on_state() say where it is.
class RobotDevice : public Device {
 public:
  using Handler = std::function<void(Status)>;
  using StateHandler = std::function<void(RobotState, const Error& cause)>;

  [[nodiscard]] std::string_view kind() const override { return "robot"; }
  virtual void upload(const Trajectory& trajectory, Handler done) = 0;
  virtual void run(Handler done) = 0;
  virtual void stop(Handler done) = 0;
  virtual void reset(Handler done) = 0;
  [[nodiscard]] virtual RobotState state() const = 0;
  virtual void on_state(StateHandler h) = 0;
};

class RobotLink final : public RobotDevice {
 public:
  using ProgressHandler = std::function<void(const RobotProgress&)>;

  RobotLink(boost::asio::io_context& io, RobotLinkOptions options);
  ~RobotLink() override;  ///< closes the connection; pending handlers are not called

  /// Checks the options (address, port, timeouts); an error names the [robot] key.
  Status configure() override;
  /// start() once configured.
  Status activate() override;
  /// shutdown().
  void deactivate() override;
  [[nodiscard]] Lifecycle lifecycle() const override { return lifecycle_; }

  /// Connects (and keeps reconnecting while options.reconnect).
  void start();
  /// Closes the link and stops reconnecting; pending handlers fail with robot.shutdown.
  void shutdown();

  /// Uploads a trajectory (state ready or uploaded). `done` gets ok once the robot
  /// acknowledged END (CRC verified); state uploaded. Errors: robot.state,
  /// robot.invalid_point, robot.nak.<code>, robot.reply_timeout, link errors.
  void upload(const Trajectory& trajectory, Handler done) override;
  /// Runs the uploaded trajectory (state uploaded). `done` gets ok at DONE, or
  /// robot.fault.<code>, robot.stopped, robot.run_timeout, robot.nak.<code>, link errors.
  void run(Handler done) override;
  /// Stops motion / aborts an upload at any time while connected. `done` gets ok at the ACK.
  /// While a STOP is pending, another stop() sends nothing and completes with that STOP.
  void stop(Handler done) override;
  /// Clears a robot fault (RESET): faulted → ready.
  void reset(Handler done) override;

  [[nodiscard]] RobotState state() const override;
  /// The cause of the last transition into disconnected or faulted, or of a refused
  /// configure() (code empty if none).
  [[nodiscard]] const Error& last_error() const override;
  /// Id and protocol version the robot announced in its HELLO ACK.
  [[nodiscard]] const std::string& robot_id() const;
  /// The id of the last trajectory uploaded (0 if none).
  [[nodiscard]] int trajectory_id() const;
  /// Number of successful HELLOs so far (reconnects show as increments).
  [[nodiscard]] int connections() const;

  void on_state(StateHandler h) override;
  void on_progress(ProgressHandler h);

 private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
  Lifecycle lifecycle_ = Lifecycle::unconfigured;
};

}  // namespace fettle::drivers
