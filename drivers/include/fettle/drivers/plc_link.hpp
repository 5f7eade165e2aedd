#pragma once
// The PLC link: a Modbus TCP client (libmodbus) on its own thread.
//
// libmodbus is blocking and not thread-safe, so the link owns its modbus context on a
// thread of its own and never blocks the caller. It talks to the daemon in two ways:
//   - events (LinkUp, LinkDown, CycleRequest, ...) are posted to the executor given at
//     construction, so a daemon that keeps all its state on one asio::io_context thread
//     receives them there;
//   - commands (set_state, command_slide, ...) are thread-safe, queued, and written to
//     the PLC at the next poll.
// Every poll reads the PLC block and writes the Fettle block (docs/plc-interface.md).
// Failures never throw on this path: they become LinkDown events, and the link
// reconnects by itself with exponential back-off (reconnect_initial_ms → reconnect_max_ms).
//
// The cycle uses the PLC as a device with the cell's common lifecycle (device.hpp):
//   plc::Link link(io.get_executor(), LinkOptions::from_config(cell), on_event);
//   link.configure();  link.activate();  ...  link.deactivate();   // starts / stops the thread
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <variant>

#include <boost/asio/any_io_executor.hpp>

#include "fettle/config/cell.hpp"
#include "fettle/core/result.hpp"
#include "fettle/drivers/device.hpp"
#include "fettle/drivers/packml.hpp"
#include "fettle/drivers/plc_registers.hpp"

namespace fettle::drivers::plc {

enum class LinkDownReason {
  connect_failed,   ///< TCP connect refused or timed out
  timeout,          ///< a request got no reply within response_timeout_ms
  io_error,         ///< the connection broke (peer closed, reset, Modbus exception)
  bad_reply,        ///< a reply that does not match its request (modbus_frame.hpp's checks)
  heartbeat_stale,  ///< the PLC's heartbeat did not change for heartbeat_timeout_ms
};
std::string_view name(LinkDownReason r);

/// The PLC answered with a valid block and its heartbeat is alive.
struct LinkUp {
  std::string peer;  ///< "address:port"
};
/// The link is not usable. Posted once per outage (not once per reconnect attempt).
struct LinkDown {
  LinkDownReason reason;
  std::string detail;  ///< for people: what failed, where
};
/// The link will try to connect again after delay_ms (attempt counts from 1 per outage).
struct Reconnecting {
  int attempt = 0;
  int delay_ms = 0;
};
/// The PLC requests a cycle (its request toggle differs from our acknowledge toggle).
/// Posted once per request while it is pending, and again after a reconnect. Accept it
/// with Link::accept_cycle().
struct CycleRequest {
  int recipe_id = 0;
};
/// The slide's state changed, or the PLC acknowledged a slide command (and once after every
/// LinkUp). A commanded move is done when `command_acked` reached the number command_slide()
/// returned and the status says the slide is at the target: a move shorter than one poll never
/// shows "moving", and an old toggle after a reconnect is never taken for a new command.
struct SlideState {
  SlideStatus status = SlideStatus::unknown;
  int position = 0;               ///< 0 = home, 1..n photo position
  std::uint64_t command_acked = 0;  ///< the last slide command (numbered from 1) the PLC acknowledged

  /// The move of slide command `command` to `target` (0 = home) is done: that command, or a
  /// later one, is acknowledged and the slide reports the target.
  [[nodiscard]] bool reached(std::uint64_t command, int target) const {
    return command_acked >= command && (target == 0 ? status == SlideStatus::at_home
                                                    : status == SlideStatus::at_position && position == target);
  }
};
/// The PLC acknowledged the last published cycle result (cycle_result_ack): the next one may be
/// published, and the next cycle request may be accepted.
struct ResultAcknowledged {
  CycleResult result = CycleResult::none;
};
/// The PLC sent a PackML command. The link acknowledges it to the PLC itself; a Reset
/// also clears the latched fault.
struct PackMLCommand {
  packml::Command command = packml::Command::none;
};
/// A register read from the PLC holds an impossible value. Nothing from that poll is
/// acted upon. Posted once per distinct violation while it lasts.
struct ValueOutOfRange {
  int address = 0;  ///< Modbus holding-register address (register_base + offset)
  int offset = 0;   ///< offset in the map
  int value = 0;
  std::string allowed;
};

using Event = std::variant<LinkUp, LinkDown, Reconnecting, CycleRequest, SlideState, ResultAcknowledged, PackMLCommand,
                           ValueOutOfRange>;
/// One line for logs and tests, e.g. "LinkDown(timeout: ...)".
std::string describe(const Event& e);

struct LinkOptions {
  std::string address = "127.0.0.1";
  int port = 502;
  int unit_id = 1;
  int register_base = 0;
  int response_timeout_ms = 200;
  int poll_period_ms = 50;
  int heartbeat_timeout_ms = 1000;
  int reconnect_initial_ms = 100;
  int reconnect_max_ms = 5000;
  Limits limits;

  /// From [plc] and the number of [slide] photo positions.
  static LinkOptions from_config(const config::CellConfig& cell);
};

/// A snapshot for status displays and tests.
struct LinkStatus {
  bool connected = false;  ///< TCP connection open
  bool up = false;         ///< last event was LinkUp
  int connects = 0;        ///< successful TCP connects
  int connect_attempts = 0;
  long long polls = 0;  ///< completed read+write exchanges
  FettleOutputs outputs;
  PlcInputs inputs;  ///< last valid PLC block
  /// Results queued or published and not yet acknowledged by the PLC (cycle_result_ack); the
  /// next cycle request is accepted only at 0 (docs/plc-interface.md, "Result").
  int results_waiting = 0;
};

}  // namespace fettle::drivers::plc

namespace fettle::drivers {

/// The line PLC as a device (device.hpp): what the cycle uses. Its events (plc::Event) go to
/// the handler its maker was given; commands are thread-safe and queued for the PLC.
class PlcDevice : public Device {
 public:
  using Handler = std::function<void(const plc::Event&)>;

  [[nodiscard]] std::string_view kind() const override { return "plc"; }
  /// The PackML state shown to the PLC.
  virtual Status set_state(packml::State state) = 0;
  /// Commands the camera slide: 0 = home, 1..n photo position n. Returns the command's number
  /// (1, 2, ...): the move is done when a SlideState with that `command_acked` or later shows the
  /// slide at the target.
  virtual Result<std::uint64_t> command_slide(int target) = 0;
  /// Accepts the pending cycle request.
  virtual void accept_cycle() = 0;
  virtual Status report_result(plc::CycleResult result) = 0;
  /// Raises fault `code` (1..65535); the first stays latched until the PLC's Reset.
  virtual Status raise_fault(std::uint16_t code) = 0;
  [[nodiscard]] virtual plc::LinkStatus status() const = 0;
};

}  // namespace fettle::drivers

namespace fettle::drivers::plc {

class Link final : public PlcDevice {
 public:
  /// Events are posted to `executor` and delivered to `on_event` there.
  Link(boost::asio::any_io_executor executor, LinkOptions options, Handler on_event);
  ~Link() override;  ///< stops the thread

  /// Checks the options (address, port, unit id, poll period and timeouts); an error names
  /// the [plc] key ("plc.config"). Call from the thread that owns the link.
  Status configure() override;
  /// start() once configured.
  Status activate() override;
  /// stop().
  void deactivate() override;
  [[nodiscard]] Lifecycle lifecycle() const override { return lifecycle_; }
  /// Why configure() or activate() refused (link outages are LinkDown events).
  [[nodiscard]] const Error& last_error() const override { return last_error_; }

  void start();
  /// Stops the thread and closes the connection; no event is posted after stop() returns.
  void stop();

  // Commands: validated here, queued, written at the next poll. An invalid argument is
  // an Error (and nothing is queued).
  Status set_state(packml::State state) override;
  /// 0 = home, 1..n photo position n. Commands go out one at a time: the next is written once
  /// the PLC acknowledged the previous one (slide_command_ack).
  Result<std::uint64_t> command_slide(int target) override;
  /// Accepts the pending cycle request: copies the request toggle to the acknowledge toggle.
  void accept_cycle() override;
  /// Results go out one at a time, in order: the next is written once the PLC acknowledged the
  /// previous one (cycle_result_ack), so none is overwritten unread.
  Status report_result(CycleResult result) override;
  /// Raises fault `code` (1..65535) and sets the latched fault bit. While latched, the
  /// first code stays; only a PackML Reset from the PLC clears it.
  Status raise_fault(std::uint16_t code) override;

  [[nodiscard]] LinkStatus status() const override;
  [[nodiscard]] const LinkOptions& options() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  Lifecycle lifecycle_ = Lifecycle::unconfigured;
  Error last_error_;
};

}  // namespace fettle::drivers::plc
