// The PLC link: libmodbus TCP client on its own thread; events posted to an executor.
#include "fettle/drivers/plc_link.hpp"

#include <modbus.h>
#include <poll.h>
#include <sys/socket.h>

#include <algorithm>
#include <array>
#include <optional>
#include <atomic>
#include <cerrno>
#include <deque>
#include <tuple>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <utility>
#include <vector>

#include <boost/asio/ip/address_v4.hpp>
#include <boost/asio/post.hpp>

#include "fettle/core/log.hpp"
#include "fettle/drivers/modbus_frame.hpp"

namespace fettle::drivers::plc {

using Clock = std::chrono::steady_clock;
using std::chrono::milliseconds;

std::string_view name(LinkDownReason r) {
  switch (r) {
    case LinkDownReason::connect_failed: return "connect_failed";
    case LinkDownReason::timeout: return "timeout";
    case LinkDownReason::io_error: return "io_error";
    case LinkDownReason::bad_reply: return "bad_reply";
    case LinkDownReason::heartbeat_stale: return "heartbeat_stale";
  }
  return "?";
}

namespace {
struct Describer {
  std::string operator()(const LinkUp& e) const { return "LinkUp(" + e.peer + ")"; }
  std::string operator()(const LinkDown& e) const {
    return "LinkDown(" + std::string(name(e.reason)) + ": " + e.detail + ")";
  }
  std::string operator()(const Reconnecting& e) const {
    return "Reconnecting(attempt " + std::to_string(e.attempt) + " in " + std::to_string(e.delay_ms) + " ms)";
  }
  std::string operator()(const CycleRequest& e) const { return "CycleRequest(recipe " + std::to_string(e.recipe_id) + ")"; }
  std::string operator()(const SlideState& e) const {
    return "SlideState(" + std::string(name(e.status)) + ", position " + std::to_string(e.position) +
           ", command " + std::to_string(e.command_acked) + " acknowledged)";
  }
  std::string operator()(const ResultAcknowledged& e) const {
    return "ResultAcknowledged(" + std::string(name(e.result)) + ")";
  }
  std::string operator()(const PackMLCommand& e) const { return "PackMLCommand(" + std::string(packml::name(e.command)) + ")"; }
  std::string operator()(const ValueOutOfRange& e) const {
    return "ValueOutOfRange(address " + std::to_string(e.address) + ": " +
           describe(RangeViolation{e.offset, e.value, e.allowed}) + ")";
  }
};
}  // namespace

std::string describe(const Event& e) { return std::visit(Describer{}, e); }

LinkOptions LinkOptions::from_config(const config::CellConfig& cell) {
  LinkOptions o;
  const auto& p = cell.plc;
  o.address = p.address;
  o.port = p.port;
  o.unit_id = p.unit_id;
  o.register_base = p.register_base;
  o.response_timeout_ms = p.response_timeout_ms;
  o.poll_period_ms = p.poll_period_ms;
  o.heartbeat_timeout_ms = p.heartbeat_timeout_ms;
  o.reconnect_initial_ms = p.reconnect_initial_ms;
  o.reconnect_max_ms = p.reconnect_max_ms;
  o.limits.slide_positions = static_cast<int>(std::max<std::size_t>(1, cell.slide.photo_positions_mm.size()));
  return o;
}

struct Link::Impl {
  Impl(boost::asio::any_io_executor ex, LinkOptions opts, Handler h)
      : executor(std::move(ex)), options(std::move(opts)), handler(std::move(h)), log(log::get("plc")) {}

  boost::asio::any_io_executor executor;
  const LinkOptions options;
  const Handler handler;
  std::shared_ptr<spdlog::logger> log;

  // Shared with callers (under mutex).
  mutable std::mutex mutex;
  std::condition_variable wake;
  bool stop_requested = false;
  std::vector<std::function<void(FettleOutputs&)>> commands;
  /// PackML states not yet written, oldest first: one per poll, so a PLC sees every state
  /// fettled enters (acting states last microseconds), in order (docs/plc-interface.md).
  std::deque<packml::State> states;
  std::optional<packml::State> last_state_queued;
  /// The slide command not yet written (its number, its target): one on the wire at a time, the
  /// next once the PLC acknowledged the previous one; a newer command replaces it (only the
  /// latest target matters).
  std::optional<std::pair<std::uint64_t, int>> slide_command;
  std::uint64_t slide_commands_numbered = 0;
  /// Results not yet written: one at a time, each once the PLC acknowledged the previous one.
  std::deque<CycleResult> results;
  LinkStatus shared_status;

  std::thread thread;

  // Link-thread state.
  modbus_t* ctx = nullptr;
  FettleOutputs outputs;
  bool up = false;
  bool down_reported = false;
  bool first_read_since_start = true;
  bool first_read_since_connect = true;
  std::uint16_t last_plc_heartbeat = 0;
  bool heartbeat_seen_change = false;
  Clock::time_point heartbeat_changed_at{};
  int posted_request_toggle = -1;  // request toggle value already posted as CycleRequest
  std::optional<SlideState> posted_slide;
  std::uint64_t slide_command_written = 0;  // number of the slide command on the wire
  std::uint64_t slide_command_acked = 0;
  bool result_unacked = false;  // a published result the PLC has not acknowledged yet
  std::vector<RangeViolation> active_violations;
  int attempt = 0;  // reconnect attempts in this outage
  std::uint16_t transaction = 0;  // the MBAP transaction id of the last request
  LinkStatus st;    // published to shared_status after each step

  void post(Event e) {
    log->debug("plc event: {}", describe(e));
    boost::asio::post(executor, [h = handler, ev = std::move(e)] { h(ev); });
  }

  std::string peer() const { return options.address + ":" + std::to_string(options.port); }

  /// Sleeps up to `d`; returns false if stop was requested.
  bool sleep_for(milliseconds d) {
    std::unique_lock lock(mutex);
    wake.wait_for(lock, d, [this] { return stop_requested; });
    return !stop_requested;
  }

  void publish() {
    st.outputs = outputs;
    st.up = up;
    st.connected = ctx != nullptr;
    st.results_waiting = result_unacked ? 1 : 0;
    std::lock_guard lock(mutex);
    shared_status = st;
  }

  void went_down(LinkDownReason reason, std::string detail) {
    const bool report = up || !down_reported;
    up = false;
    down_reported = true;
    publish();  // status() agrees with the event by the time it arrives
    if (report) {
      log->warn("PLC link down ({}): {}", name(reason), detail);
      post(LinkDown{reason, std::move(detail)});
    }
  }

  void disconnect() {
    if (ctx != nullptr) {
      modbus_close(ctx);
      modbus_free(ctx);
      ctx = nullptr;
    }
  }

  void drop(LinkDownReason reason, std::string detail) {
    disconnect();
    went_down(reason, std::move(detail));
  }

  bool connect() {
    ++st.connect_attempts;
    ctx = modbus_new_tcp(options.address.c_str(), options.port);
    if (ctx == nullptr) {
      went_down(LinkDownReason::connect_failed, "cannot create a Modbus context for " + peer() + ": " +
                                                    modbus_strerror(errno));
      return false;
    }
    const auto to_us = static_cast<std::uint32_t>(options.response_timeout_ms) * 1000U;
    modbus_set_response_timeout(ctx, to_us / 1000000U, to_us % 1000000U);
    modbus_set_byte_timeout(ctx, to_us / 1000000U, to_us % 1000000U);
    modbus_set_error_recovery(ctx, MODBUS_ERROR_RECOVERY_NONE);  // we reconnect ourselves
    if (modbus_connect(ctx) == -1) {
      const std::string err = modbus_strerror(errno);
      modbus_free(ctx);
      ctx = nullptr;
      went_down(LinkDownReason::connect_failed,
                "cannot connect to the PLC at " + peer() + ": " + err + " (is it on and is [plc] address/port right?)");
      return false;
    }
    ++st.connects;
    first_read_since_connect = true;
    heartbeat_seen_change = false;
    heartbeat_changed_at = Clock::now();
    posted_request_toggle = -1;
    posted_slide.reset();
    active_violations.clear();
    log->info("PLC link connected to {}", peer());
    return true;
  }

  void io_failure(const char* what, int err) {
    const auto reason = err == ETIMEDOUT ? LinkDownReason::timeout : LinkDownReason::io_error;
    std::string detail = std::string(what) + " at " + peer() + " failed: " + modbus_strerror(err);
    if (reason == LinkDownReason::timeout)
      detail += " (no reply within " + std::to_string(options.response_timeout_ms) + " ms)";
    drop(reason, std::move(detail));
  }

  void report_violations(const std::vector<RangeViolation>& now) {
    for (const auto& v : now)
      if (std::find(active_violations.begin(), active_violations.end(), v) == active_violations.end()) {
        log->error("PLC value out of range: {}", describe(v));
        post(ValueOutOfRange{options.register_base + v.offset, v.offset, v.value, v.allowed});
      }
    active_violations = now;
  }

  /// Violations that depend on the handshake state, not on one register alone.
  void check_handshakes(const PlcInputs& in, std::vector<RangeViolation>& out) const {
    if (in.command_toggle != outputs.command_ack_toggle && in.command == packml::Command::none)
      out.push_back({reg::packml_command, 0, "1 to 9 when packml_command_toggle changes"});
    if (in.cycle_request_toggle != outputs.cycle_ack_toggle && in.recipe_id == 0)
      out.push_back({reg::recipe_id, 0, "1 to 65535 when a cycle is requested"});
  }

  /// Acts on a valid PLC block.
  void process(const PlcInputs& in) {
    st.inputs = in;
    // PackML command handshake: pending while the toggles differ.
    if (in.command_toggle != outputs.command_ack_toggle) {
      post(PackMLCommand{in.command});
      outputs.command_ack_toggle = in.command_toggle;
      if (in.command == packml::Command::reset && outputs.fault_latched) {
        log->info("PLC reset clears latched fault {}", outputs.fault_code);
        outputs.fault_latched = false;
        outputs.fault_code = 0;
      }
    }
    // Cycle request handshake: pending while the toggles differ.
    if (in.cycle_request_toggle != outputs.cycle_ack_toggle) {
      if (posted_request_toggle != in.cycle_request_toggle) {
        post(CycleRequest{in.recipe_id});
        posted_request_toggle = in.cycle_request_toggle;
      }
    } else {
      posted_request_toggle = -1;
    }
    // Slide and result handshakes: acknowledged when the PLC's copy equals our toggle.
    if (in.slide_command_ack == outputs.slide_command_toggle) slide_command_acked = slide_command_written;
    if (result_unacked && in.result_ack == outputs.result_toggle) {
      result_unacked = false;
      publish();  // status() agrees with the event by the time it arrives
      post(ResultAcknowledged{outputs.result});
    }
    const SlideState slide{in.slide_status, in.slide_position, slide_command_acked};
    if (!posted_slide || posted_slide->status != slide.status || posted_slide->position != slide.position ||
        posted_slide->command_acked != slide.command_acked) {
      post(slide);
      posted_slide = slide;
    }
  }

  /// Sends `request` on libmodbus's socket, lets libmodbus read the reply off the stream and
  /// checks every field of it (modbus_frame.hpp says why libmodbus's own checks are not
  /// enough). The reply, or nothing when the link dropped, having said why.
  std::optional<modbus::Reply> transact(const modbus::Request& request, const char* what, Clock::time_point deadline) {
    const int fd = modbus_get_socket(ctx);
    std::size_t sent = 0;
    while (sent < request.adu.size()) {
      const auto n = ::send(fd, request.adu.data() + sent, request.adu.size() - sent, MSG_NOSIGNAL);
      if (n > 0) {
        sent += static_cast<std::size_t>(n);
        continue;
      }
      if (n == -1 && errno == EINTR) continue;
      if (n == -1 && (errno == EAGAIN || errno == EWOULDBLOCK)) {  // the socket is non-blocking
        const auto left = std::chrono::duration_cast<milliseconds>(deadline - Clock::now()).count();
        pollfd p{fd, POLLOUT, 0};
        if (left > 0 && ::poll(&p, 1, static_cast<int>(left)) > 0) continue;
        io_failure(what, ETIMEDOUT);
        return std::nullopt;
      }
      io_failure(what, errno);
      return std::nullopt;
    }
    std::array<std::uint8_t, MODBUS_TCP_MAX_ADU_LENGTH> raw{};
    const int n = modbus_receive_confirmation(ctx, raw.data());
    if (n == -1) {
      io_failure(what, errno);
      return std::nullopt;
    }
    auto reply = modbus::check_reply(request, std::span<const std::uint8_t>(raw.data(), static_cast<std::size_t>(n)));
    if (!reply.ok()) {
      // An exception is the PLC refusing (wrong register_base, say); anything else is a peer
      // that does not speak Modbus TCP as the standard says (test PlcBadPeer.*).
      drop(reply.exception_code != 0 ? LinkDownReason::io_error : LinkDownReason::bad_reply,
           std::string(what) + " at " + peer() + ": " + reply.error);
      return std::nullopt;
    }
    return reply;
  }

  void poll_once() {
    const auto started = Clock::now();
    const auto read = transact(modbus::read_holding_registers(++transaction, static_cast<std::uint8_t>(options.unit_id),
                                                              static_cast<std::uint16_t>(options.register_base + reg::plc_block_start),
                                                              reg::plc_block_size),
                               "reading the PLC block", started + milliseconds(options.response_timeout_ms));
    if (!read) return;
    const auto& regs = read->registers;  // plc_block_size of them: check_reply saw to it
    const auto now = Clock::now();
    // libmodbus times each byte, not the reply: a PLC dripping a byte every 150 ms answered in
    // 5.6 s and stayed "up". The whole read has response_timeout_ms (docs/plc-interface.md;
    // test PlcBadPeer.AReplyDrippedSlowerThanTheDeadlineIsATimeout).
    if (const auto took = std::chrono::duration_cast<milliseconds>(now - started);
        took > milliseconds(options.response_timeout_ms)) {
      drop(LinkDownReason::timeout, "reading the PLC block at " + peer() + " took " + std::to_string(took.count()) +
                                        " ms, more than the poll's deadline ([plc] response_timeout_ms = " +
                                        std::to_string(options.response_timeout_ms) + " ms)");
      return;
    }
    const auto decoded = decode_plc_block(regs, options.limits);
    // Heartbeat: the raw register is always a valid value.
    const auto hb = regs[reg::plc_heartbeat - reg::plc_block_start];
    if (first_read_since_connect) {
      last_plc_heartbeat = hb;
      heartbeat_changed_at = now;
    } else if (hb != last_plc_heartbeat) {
      last_plc_heartbeat = hb;
      heartbeat_changed_at = now;
      heartbeat_seen_change = true;
    }
    first_read_since_connect = false;
    const bool stale = now - heartbeat_changed_at > milliseconds(options.heartbeat_timeout_ms);
    if (stale) {
      went_down(LinkDownReason::heartbeat_stale, "the PLC heartbeat (register " +
                                                     std::to_string(options.register_base + reg::plc_heartbeat) +
                                                     ") did not change for " +
                                                     std::to_string(options.heartbeat_timeout_ms) + " ms at " + peer());
    }

    auto violations = decoded.violations;
    if (decoded.ok()) {
      // At the link's very first read a differing command toggle is a leftover from
      // before we ran: adopt it, never obey it.
      // Likewise the PLC's acknowledges of our slide commands and results: nothing of ours is
      // pending when we start.
      if (first_read_since_start) {
        outputs.command_ack_toggle = decoded.value.command_toggle;
        outputs.slide_command_toggle = decoded.value.slide_command_ack;
        outputs.result_toggle = decoded.value.result_ack;
      }
      first_read_since_start = false;
      check_handshakes(decoded.value, violations);
    }
    if (!violations.empty()) {
      report_violations(violations);
    } else {
      if (!active_violations.empty()) log->info("PLC values back in range");
      active_violations.clear();
      if (!up && heartbeat_seen_change && !stale) {
        up = true;
        down_reported = false;
        attempt = 0;
        log->info("PLC link up: {}", peer());
        {
          // after an outage the PLC needs where fettled is, not the states it went through meanwhile
          std::lock_guard lock(mutex);
          while (states.size() > 1) states.pop_front();
        }
        publish();
        post(LinkUp{peer()});
      }
      if (up) process(decoded.value);
    }
    const bool acted = up && violations.empty();

    // Write our block (heartbeat, acknowledgements, state, commands).
    {
      std::vector<std::function<void(FettleOutputs&)>> pending;
      {
        std::lock_guard lock(mutex);
        pending.swap(commands);
      }
      for (auto& c : pending) c(outputs);
      std::lock_guard lock(mutex);
      if (!states.empty()) {
        outputs.state = states.front();
        states.pop_front();
      }
      // A slide command or result goes out only on a poll whose PLC block was read and valid, and
      // once the PLC acknowledged the previous one.
      if (acted && slide_command && slide_command_acked == slide_command_written) {
        std::tie(slide_command_written, outputs.slide_target) = *slide_command;
        outputs.slide_command_toggle ^= 1;
        slide_command.reset();
      }
      if (acted && !results.empty() && !result_unacked) {
        outputs.result = results.front();
        outputs.result_toggle ^= 1;
        result_unacked = true;
        results.pop_front();
      }
    }
    ++outputs.heartbeat;
    const auto block = encode_fettle_block(outputs);
    if (!transact(modbus::write_multiple_registers(++transaction, static_cast<std::uint8_t>(options.unit_id),
                                                   static_cast<std::uint16_t>(options.register_base + reg::fettle_block_start),
                                                   block),
                  "writing the Fettle block", Clock::now() + milliseconds(options.response_timeout_ms)))
      return;
    ++st.polls;
  }

  void run() {
    log::Scope device{"DEVICE", "plc"};
    bool first = true;
    while (true) {
      {
        std::lock_guard lock(mutex);
        if (stop_requested) break;
      }
      if (ctx == nullptr) {
        if (!first) {
          const int delay = backoff_delay_ms(attempt, options.reconnect_initial_ms, options.reconnect_max_ms);
          ++attempt;
          post(Reconnecting{attempt, delay});
          publish();
          if (!sleep_for(milliseconds(delay))) break;
        }
        first = false;
        if (!connect()) {
          publish();
          continue;
        }
      }
      const auto started = Clock::now();
      poll_once();
      publish();
      if (ctx == nullptr) continue;  // dropped: back-off first
      const auto next = started + milliseconds(options.poll_period_ms);
      if (!sleep_for(std::chrono::duration_cast<milliseconds>(std::max(next - Clock::now(), Clock::duration::zero()))))
        break;
    }
    disconnect();
    up = false;
    publish();
  }

  void queue(std::function<void(FettleOutputs&)> c) {
    std::lock_guard lock(mutex);
    commands.push_back(std::move(c));
  }
};

Link::Link(boost::asio::any_io_executor executor, LinkOptions options, Handler on_event)
    : impl_(std::make_unique<Impl>(std::move(executor), std::move(options), std::move(on_event))) {}

Link::~Link() { stop(); }

Status Link::configure() {
  if (lifecycle_ != Lifecycle::unconfigured) return {};
  const auto& o = impl_->options;
  auto refuse = [&](const std::string& why) {
    last_error_ = Error{"plc.config", "[plc] " + why};
    return Status{last_error_};
  };
  boost::system::error_code ec;
  (void)boost::asio::ip::make_address_v4(o.address, ec);
  if (ec) return refuse("address '" + o.address + "' is not an IPv4 address");
  if (o.port <= 0 || o.port > 65535) return refuse("port " + std::to_string(o.port) + " is not 1-65535");
  if (o.unit_id < 0 || o.unit_id > 255) return refuse("unit_id " + std::to_string(o.unit_id) + " is not 0-255");
  if (o.poll_period_ms <= 0 || o.response_timeout_ms <= 0 || o.reconnect_initial_ms <= 0 ||
      o.reconnect_max_ms < o.reconnect_initial_ms)
    return refuse("poll_period_ms, response_timeout_ms and reconnect_initial_ms must be above 0, reconnect_max_ms "
                  "at least reconnect_initial_ms");
  if (o.heartbeat_timeout_ms <= o.poll_period_ms)
    return refuse("heartbeat_timeout_ms (" + std::to_string(o.heartbeat_timeout_ms) + ") must exceed poll_period_ms (" +
                  std::to_string(o.poll_period_ms) + "): the PLC's heartbeat is read once per poll");
  lifecycle_ = Lifecycle::inactive;
  last_error_ = {};
  return {};
}

Status Link::activate() {
  if (lifecycle_ == Lifecycle::active) return {};
  if (lifecycle_ == Lifecycle::unconfigured)
    return last_error_ = Error{"plc.lifecycle", "PLC " + impl_->options.address + ": activate() before configure()"};
  start();
  lifecycle_ = Lifecycle::active;
  return {};
}

void Link::deactivate() {
  if (lifecycle_ != Lifecycle::active) return;
  stop();
  lifecycle_ = Lifecycle::inactive;
}

void Link::start() {
  if (impl_->thread.joinable()) return;
  {
    std::lock_guard lock(impl_->mutex);
    impl_->stop_requested = false;
  }
  impl_->thread = std::thread([this] { impl_->run(); });
}

void Link::stop() {
  {
    std::lock_guard lock(impl_->mutex);
    impl_->stop_requested = true;
  }
  impl_->wake.notify_all();
  if (impl_->thread.joinable()) impl_->thread.join();
}

Status Link::set_state(packml::State state) {
  if (state == packml::State::undefined)
    return Error{"plc.bad_state", "PackML state Undefined (0) is never sent to the PLC"};
  std::lock_guard lock(impl_->mutex);
  if (impl_->last_state_queued != state) impl_->states.push_back(state);
  impl_->last_state_queued = state;
  return {};
}

Result<std::uint64_t> Link::command_slide(int target) {
  const int n = impl_->options.limits.slide_positions;
  if (target < 0 || target > n)
    return Error{"plc.bad_slide_target", "slide target " + std::to_string(target) + " does not exist: allowed 0 (home) to " +
                                             std::to_string(n) + " ([slide] photo_positions_mm has " +
                                             std::to_string(n) + ")"};
  std::lock_guard lock(impl_->mutex);
  const auto number = ++impl_->slide_commands_numbered;
  impl_->slide_command = std::make_pair(number, target);
  return number;
}

void Link::accept_cycle() {
  impl_->queue([impl = impl_.get()](FettleOutputs& o) { o.cycle_ack_toggle = impl->st.inputs.cycle_request_toggle; });
}

Status Link::report_result(CycleResult result) {
  if (result == CycleResult::none) return Error{"plc.bad_result", "a cycle result must be OK, NOK, re-grind or FAULT"};
  std::lock_guard lock(impl_->mutex);
  impl_->results.push_back(result);
  return {};
}

Status Link::raise_fault(std::uint16_t code) {
  if (code == 0) return Error{"plc.bad_fault_code", "fault code 0 means 'no fault'; raise a code from 1 to 65535"};
  impl_->queue([code](FettleOutputs& o) {
    if (o.fault_latched) return;  // first fault stays until a PLC reset
    o.fault_code = code;
    o.fault_latched = true;
  });
  return {};
}

LinkStatus Link::status() const {
  std::lock_guard lock(impl_->mutex);
  auto s = impl_->shared_status;
  s.results_waiting += static_cast<int>(impl_->results.size());
  return s;
}

const LinkOptions& Link::options() const { return impl_->options; }

}  // namespace fettle::drivers::plc
