// CANopen master for the grinding spindle drive (CiA 301 + CiA 402 velocity modes).
#include <cmath>
#include <cstdio>
#include <deque>

#include <boost/asio/steady_timer.hpp>

#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/drivers/spindle.hpp"

namespace fettle::drivers {

using namespace fettle::canopen;
using Clock = std::chrono::steady_clock;

namespace {

std::string hex(std::uint32_t v, int digits) {
  char buf[16];
  std::snprintf(buf, sizeof buf, "0x%0*X", digits, v);
  return buf;
}

std::string object_name(std::uint16_t index, std::uint8_t sub) { return hex(index, 4) + ":" + hex(sub, 2).substr(2); }

Error make_error(std::string code, std::string message, ErrorKind kind) {
  return Error{std::move(code), std::move(message), kind};
}

}  // namespace

std::string to_string(SpindleEvent::Kind k) {
  switch (k) {
    case SpindleEvent::Kind::fault: return "fault";
    case SpindleEvent::Kind::emergency: return "emergency";
    case SpindleEvent::Kind::heartbeat_lost: return "heartbeat_lost";
    case SpindleEvent::Kind::heartbeat_restored: return "heartbeat_restored";
    case SpindleEvent::Kind::link_error: return "link_error";
    case SpindleEvent::Kind::state_changed: return "state_changed";
  }
  return "unknown";
}

SpindleOptions SpindleOptions::from_config(const config::SpindleSection& s) {
  SpindleOptions o;
  o.node_id = static_cast<std::uint8_t>(s.node_id);
  o.master_node_id = static_cast<std::uint8_t>(s.master_node_id);
  o.mode = s.mode == "velocity" ? OperationMode::velocity : OperationMode::profile_velocity;
  o.heartbeat_producer_ms = s.heartbeat_producer_ms;
  o.heartbeat_timeout_ms = s.heartbeat_timeout_ms;
  o.sdo_timeout_ms = s.sdo_timeout_ms;
  o.spin_up_timeout_ms = s.spin_up_timeout_ms;
  o.at_speed_tolerance_rpm = s.at_speed_tolerance_rpm;
  o.max_rpm = s.max_rpm;
  return o;
}

struct SpindleDrive::Impl : std::enable_shared_from_this<Impl> {
  using Step = std::function<void(Done)>;

  Impl(boost::asio::io_context& io_, std::shared_ptr<CanTransport> transport_, SpindleOptions options_)
      : io(io_),
        transport(std::move(transport_)),
        opt(options_),
        sdo_timer(io_),
        heartbeat_timer(io_),
        producer_timer(io_),
        wait_timer(io_),
        log(log::get("spindle")) {}

  boost::asio::io_context& io;
  std::shared_ptr<CanTransport> transport;
  SpindleOptions opt;
  SpindleStatus st;
  bool transport_started = false;
  bool closed = false;
  bool boot_seen = false;
  std::optional<std::uint16_t> found_error_code;  ///< 0x603F read at activate() when the drive was in fault
  std::function<void(const SpindleEvent&)> on_event;
  Lifecycle lifecycle = Lifecycle::unconfigured;
  Error last_error;  ///< the last failed configure, activate or latched fault

  // SDO client: one transfer at a time.
  struct SdoRequest {
    CanFrame frame;
    bool upload = false;
    std::uint16_t index = 0;
    std::uint8_t sub = 0;
    ValueDone done;
  };
  std::deque<SdoRequest> sdo_queue;
  bool sdo_busy = false;
  boost::asio::steady_timer sdo_timer;

  boost::asio::steady_timer heartbeat_timer;  // consumer: drive's heartbeat
  boost::asio::steady_timer producer_timer;   // our own heartbeat

  // The one operation in progress (start, spin_up, stop, fault_reset).
  Done op_done;
  std::uint64_t op_gen = 0;
  bool op_abort_on_fault = false;
  struct Waiter {
    std::function<bool(const SpindleStatus&)> predicate;
    Done done;
  };
  std::optional<Waiter> waiter;
  boost::asio::steady_timer wait_timer;
  std::shared_ptr<spdlog::logger> log;

  // ------------------------------------------------------------------ plumbing
  void ensure_transport() {
    if (transport_started) return;
    transport_started = true;
    std::weak_ptr<Impl> weak = shared_from_this();
    transport->start(
        [weak](const CanFrame& f) {
          if (auto self = weak.lock()) self->on_frame(f);
        },
        [weak](const Error& e) {
          if (auto self = weak.lock()) self->on_link_error(e);
        });
    produce_heartbeat();
  }

  void send(const CanFrame& f) {
    log->trace("tx {}", to_string(f));
    transport->send(f);
  }

  void emit(SpindleEvent e) {
    if (on_event) on_event(e);
  }

  void produce_heartbeat() {
    if (closed) return;
    send(heartbeat_frame(opt.master_node_id, NmtState::operational));
    producer_timer.expires_after(std::chrono::milliseconds(opt.heartbeat_producer_ms));
    producer_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (!ec) self->produce_heartbeat();
    });
  }

  // ------------------------------------------------------------------ operations
  std::optional<std::uint64_t> begin_op(Done done, bool abort_on_fault) {
    if (op_done) {
      done(make_error("spindle.busy", "spindle: another operation is in progress; wait for it or call spin_down()", ErrorKind::unspecified));
      return std::nullopt;
    }
    op_done = std::move(done);
    op_abort_on_fault = abort_on_fault;
    return ++op_gen;
  }
  bool op_alive(std::uint64_t gen) const { return gen == op_gen && op_done != nullptr; }
  void finish_op(std::uint64_t gen, Status s) {
    if (!op_alive(gen)) return;
    auto done = std::move(op_done);
    op_done = nullptr;
    waiter.reset();
    wait_timer.cancel();
    done(std::move(s));
  }

  /// Runs steps in order for operation `gen`; the first failure (or a cancelled op) ends it.
  void run(std::uint64_t gen, std::vector<Step> steps) {
    auto list = std::make_shared<std::vector<Step>>(std::move(steps));
    auto next = std::make_shared<std::function<void(std::size_t)>>();
    std::weak_ptr<std::function<void(std::size_t)>> weak_next = next;
    *next = [self = shared_from_this(), gen, list, weak_next](std::size_t i) {
      if (!self->op_alive(gen)) return;
      if (i == list->size()) return self->finish_op(gen, Status{});
      auto again = weak_next.lock();
      (*list)[i]([self, gen, i, again](Status s) {
        if (!self->op_alive(gen)) return;
        if (!s) return self->finish_op(gen, std::move(s));
        (*again)(i + 1);
      });
    };
    // The chain keeps itself alive through the step callbacks.
    auto keep = next;
    (*keep)(0);
  }

  /// Completes `done` when `predicate` holds (checked on every status change) or fails after timeout.
  void wait_until(std::function<bool(const SpindleStatus&)> predicate, int timeout_ms, std::string what, Done done) {
    if (predicate(st)) return done(Status{});
    waiter = Waiter{std::move(predicate), std::move(done)};
    wait_timer.expires_after(std::chrono::milliseconds(timeout_ms));
    wait_timer.async_wait([self = shared_from_this(), timeout_ms, what](const boost::system::error_code& ec) {
      if (ec || !self->waiter) return;
      auto d = std::move(self->waiter->done);
      self->waiter.reset();
      char buf[160];
      std::snprintf(buf, sizeof buf, " (drive state: %s, statusword 0x%04X, velocity %.0f rpm, target %.0f rpm)",
                    canopen::to_string(self->st.state).c_str(), self->st.statusword, self->st.velocity_rpm,
                    self->st.target_rpm);
      d(make_error("spindle.timeout", "spindle: timed out after " + std::to_string(timeout_ms) + " ms waiting for " +
                                          what + buf, ErrorKind::timeout));
    });
  }

  void check_waiter() {
    if (waiter && waiter->predicate(st)) {
      auto d = std::move(waiter->done);
      waiter.reset();
      wait_timer.cancel();
      d(Status{});
    }
  }

  Step sdo_write_step(std::uint16_t index, std::uint8_t sub, std::uint32_t value, std::uint8_t size) {
    return [self = shared_from_this(), index, sub, value, size](Done d) {
      self->sdo_download(index, sub, value, size, std::move(d));
    };
  }

  // Steps are made for the operation in progress (op_gen); a step of an operation that was
  // cancelled meanwhile must not install its waiter over the current operation's.
  Step wait_step(std::function<bool(const SpindleStatus&)> predicate, int timeout_ms, std::string what) {
    return [self = shared_from_this(), gen = op_gen, predicate, timeout_ms, what](Done d) {
      if (!self->op_alive(gen)) return;
      self->wait_until(predicate, timeout_ms, what, std::move(d));
    };
  }

  Step state_step(std::uint16_t controlword_value, DriveState target) {
    return [self = shared_from_this(), gen = op_gen, controlword_value, target](Done d) {
      self->sdo_download(od::controlword, 0, controlword_value, 2,
                         [self, gen, target, d = std::move(d)](Status s) mutable {
                           if (!self->op_alive(gen)) return;
                           if (!s) return d(std::move(s));
                           self->wait_until([target](const SpindleStatus& x) { return x.state == target; },
                                            self->opt.step_timeout_ms, "state '" + canopen::to_string(target) + "'",
                                            std::move(d));
                         });
    };
  }

  Step read_statusword_step() {
    return [self = shared_from_this()](Done d) {
      self->sdo_upload(od::statusword, 0, [self, d = std::move(d)](Result<std::uint32_t> r) {
        if (!r) return d(r.error());
        self->set_statusword(static_cast<std::uint16_t>(*r));
        d(Status{});
      });
    };
  }

  Status fault_status() const {
    if (st.fault) return *st.fault;
    return Status{};
  }

  // ------------------------------------------------------------------ faults
  void latch_fault(Error e) {
    const bool first = !st.fault;
    if (first) {
      log->error("{}", e.message);
      last_error = e;
      st.fault = e;
      emit(SpindleEvent{SpindleEvent::Kind::fault, e.message, st.last_emcy, st.state});
    }
    if (op_abort_on_fault && op_done) finish_op(op_gen, *st.fault);
  }

  // ------------------------------------------------------------------ receive
  void on_link_error(const Error& e) {
    log->warn("{}", e.message);
    emit(SpindleEvent{SpindleEvent::Kind::link_error, e.message, std::nullopt, st.state});
    if (e.code == "can.socketcand" || e.code == "can.socket") {
      if (st.configured) latch_fault(make_error("spindle.link_lost", "spindle: CAN link lost: " + e.message, ErrorKind::device_fault));
      // Without a link nothing pending can complete: fail it now rather than at its timeout.
      if (op_done) finish_op(op_gen, make_error("spindle.link_lost", "spindle: CAN link lost: " + e.message, ErrorKind::device_fault));
    }
  }

  void on_frame(const CanFrame& f) {
    if (f.extended || f.rtr) return;
    const std::uint32_t node = opt.node_id;
    if (f.id == kSdoTxBase + node) return on_sdo(f);
    if (f.id == kHeartbeatBase + node) return on_heartbeat(f);
    if (f.id == kTpdo1Base + node) return on_tpdo1(f);
    if (f.id == kEmcyBase + node) return on_emcy(f);
  }

  void on_heartbeat(const CanFrame& f) {
    if (f.len < 1) return;
    const auto state = static_cast<NmtState>(f.data[0] & 0x7FU);
    if (state == NmtState::boot_up) {
      log->info("drive node {} booted", opt.node_id);
      boot_seen = true;
      if (st.configured && !op_done)
        latch_fault(make_error("spindle.rebooted", "spindle: the drive (node " + std::to_string(opt.node_id) +
                                                       ") rebooted; its configuration is lost: activate it again (a Reset does)", ErrorKind::device_fault));
      st.nmt = state;
      check_waiter();
      return;
    }
    st.nmt = state;
    if (!st.heartbeat_ok) {
      if (st.configured) emit(SpindleEvent{SpindleEvent::Kind::heartbeat_restored, "spindle: drive heartbeat is back",
                                           std::nullopt, st.state});
      st.heartbeat_ok = true;
    }
    heartbeat_timer.expires_after(std::chrono::milliseconds(opt.heartbeat_timeout_ms));
    heartbeat_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (!ec) self->on_heartbeat_timeout();
    });
    check_waiter();
  }

  void on_heartbeat_timeout() {
    st.heartbeat_ok = false;
    const std::string msg = "spindle: no heartbeat from the drive (node " + std::to_string(opt.node_id) + ") for " +
                            std::to_string(opt.heartbeat_timeout_ms) + " ms: check the CAN cable, termination and drive power";
    emit(SpindleEvent{SpindleEvent::Kind::heartbeat_lost, msg, std::nullopt, st.state});
    latch_fault(make_error("spindle.heartbeat_lost", msg, ErrorKind::device_fault));
  }

  void on_emcy(const CanFrame& f) {
    auto e = decode_emcy(f);
    if (!e) return;
    st.last_emcy = *e;
    const std::string text = "spindle: drive EMCY " + describe(*e);
    emit(SpindleEvent{SpindleEvent::Kind::emergency, text, e, st.state});
    if (e->error_code != 0) latch_fault(make_error("spindle.fault", text, ErrorKind::device_fault));
  }

  void on_tpdo1(const CanFrame& f) {
    if (f.len < 8) return;
    ++st.feedback_frames;
    const auto sw = static_cast<std::uint16_t>(f.data[0] | (f.data[1] << 8));
    std::uint32_t v = 0;
    for (int i = 0; i < 4; ++i) v |= static_cast<std::uint32_t>(f.data[2 + i]) << (8 * i);
    const auto cur = static_cast<std::int16_t>(f.data[6] | (f.data[7] << 8));
    st.velocity_rpm = static_cast<double>(static_cast<std::int32_t>(v));
    st.current_permille = static_cast<double>(cur);
    st.current_a = st.current_permille / 1000.0 * st.rated_current_a;
    set_statusword(sw);
  }

  void set_statusword(std::uint16_t sw) {
    st.statusword = sw;
    const DriveState s = decode_statusword(sw);
    if (s != st.state) {
      log->debug("drive state: {} -> {}", canopen::to_string(st.state), canopen::to_string(s));
      st.state = s;
      emit(SpindleEvent{SpindleEvent::Kind::state_changed, "spindle: drive state " + canopen::to_string(s),
                        std::nullopt, s});
    }
    if ((s == DriveState::fault || s == DriveState::fault_reaction_active) && st.configured) {
      std::string msg = "spindle: the drive is in fault";
      if (st.last_emcy && st.last_emcy->error_code != 0) msg += " (last EMCY " + describe(*st.last_emcy) + ")";
      latch_fault(make_error("spindle.fault", msg + "; fix the cause, then fault_reset()", ErrorKind::device_fault));
    }
    check_waiter();
  }

  // ------------------------------------------------------------------ SDO client
  void sdo_download(std::uint16_t index, std::uint8_t sub, std::uint32_t value, std::uint8_t size, Done done) {
    sdo_queue.push_back(SdoRequest{sdo_download_request(opt.node_id, index, sub, value, size), false, index, sub,
                                   [done = std::move(done)](Result<std::uint32_t> r) {
                                     if (!r) return done(r.error());
                                     done(Status{});
                                   }});
    sdo_next();
  }

  void sdo_upload(std::uint16_t index, std::uint8_t sub, ValueDone done) {
    sdo_queue.push_back(SdoRequest{sdo_upload_request(opt.node_id, index, sub), true, index, sub, std::move(done)});
    sdo_next();
  }

  void sdo_next() {
    if (sdo_busy || sdo_queue.empty() || closed) return;
    ensure_transport();
    sdo_busy = true;
    send(sdo_queue.front().frame);
    sdo_timer.expires_after(std::chrono::milliseconds(opt.sdo_timeout_ms));
    sdo_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (ec || !self->sdo_busy) return;
      const auto& r = self->sdo_queue.front();
      self->send(sdo_abort(self->opt.node_id, true, r.index, r.sub, abort_code::timeout));
      self->sdo_complete(make_error("spindle.sdo_timeout",
                                    "spindle: SDO " + std::string(r.upload ? "read of " : "write to ") +
                                        object_name(r.index, r.sub) + " on node " + std::to_string(self->opt.node_id) +
                                        ": no answer within " + std::to_string(self->opt.sdo_timeout_ms) +
                                        " ms (is the drive powered, on the bus, with node id " +
                                        std::to_string(self->opt.node_id) + "?)", ErrorKind::unavailable));
    });
  }

  void sdo_complete(Result<std::uint32_t> r) {
    auto req = std::move(sdo_queue.front());
    sdo_queue.pop_front();
    sdo_busy = false;
    sdo_timer.cancel();
    // Complete after starting the next transfer so a callback may queue more.
    sdo_next();
    req.done(std::move(r));
  }

  void on_sdo(const CanFrame& f) {
    if (!sdo_busy) return;
    auto m = decode_sdo(f, false);
    if (!m) return;
    const auto& req = sdo_queue.front();
    const std::string what = std::string(req.upload ? "read of " : "write to ") + object_name(req.index, req.sub) +
                             " on node " + std::to_string(opt.node_id);
    if (m->index != req.index || m->subindex != req.sub) {
      if (m->kind != SdoMessage::Kind::abort)
        send(sdo_abort(opt.node_id, true, req.index, req.sub, abort_code::general));
      return sdo_complete(make_error("spindle.sdo_mismatch", "spindle: SDO " + what + ": the answer is for " +
                                                                 object_name(m->index, m->subindex) +
                                                                 " (another SDO client on the bus with this node?)", ErrorKind::unavailable));
    }
    switch (m->kind) {
      case SdoMessage::Kind::abort:
        return sdo_complete(make_error("spindle.sdo_abort", "spindle: SDO " + what + " aborted by the drive: " +
                                                                hex(m->value, 8) + " " + abort_code_text(m->value), ErrorKind::refused));
      case SdoMessage::Kind::download_response:
        if (req.upload) break;
        return sdo_complete(std::uint32_t{0});
      case SdoMessage::Kind::upload_response:
        if (!req.upload) break;
        return sdo_complete(m->value);
      case SdoMessage::Kind::upload_segmented:
        send(sdo_abort(opt.node_id, true, req.index, req.sub, abort_code::bad_command));
        return sdo_complete(make_error("spindle.sdo_unsupported", "spindle: SDO " + what +
                                                                      ": the drive answered with a segmented transfer "
                                                                      "(only expedited transfers of up to 4 bytes are supported)", ErrorKind::unavailable));
      default: break;
    }
    send(sdo_abort(opt.node_id, true, req.index, req.sub, abort_code::bad_command));
    sdo_complete(make_error("spindle.sdo_protocol", "spindle: SDO " + what + ": unexpected answer " + to_string(f), ErrorKind::unavailable));
  }

  // ------------------------------------------------------------------ the sequences
  void start(Done done) {
    auto gen = begin_op(std::move(done), false);
    if (!gen) return;
    ensure_transport();
    st.configured = false;
    const std::uint8_t node = opt.node_id;
    const auto me = shared_from_this();
    std::vector<Step> steps;
    steps.push_back([me, node](Done d) {
      me->boot_seen = false;
      me->log->info("NMT reset communication of node {}", node);
      me->send(nmt_frame(NmtCommand::reset_communication, node));
      me->wait_until([me](const SpindleStatus&) { return me->boot_seen; }, me->opt.step_timeout_ms,
                     "the drive's boot-up message (node " + std::to_string(node) +
                         "; check the node id, the bit rate and that the drive is powered)",
                     std::move(d));
    });
    steps.push_back([me](Done d) {
      me->sdo_upload(od::identity, 1, [me, d = std::move(d)](Result<std::uint32_t> r) {
        if (!r) return d(r.error());
        me->log->info("drive vendor id {}", hex(*r, 8));
        d(Status{});
      });
    });
    steps.push_back(sdo_write_step(od::producer_heartbeat_time, 0, static_cast<std::uint32_t>(opt.heartbeat_producer_ms), 2));
    steps.push_back(sdo_write_step(od::consumer_heartbeat_time, 1,
                                   (static_cast<std::uint32_t>(opt.master_node_id) << 16U) |
                                       static_cast<std::uint32_t>(opt.heartbeat_timeout_ms),
                                   4));
    steps.push_back([me](Done d) {
      me->sdo_upload(od::motor_rated_current, 0, [me, d = std::move(d)](Result<std::uint32_t> r) {
        if (!r) return d(r.error());
        me->st.rated_current_a = static_cast<double>(*r) / 1000.0;
        d(Status{});
      });
    });
    // TPDO1: statusword, velocity actual, current actual; event-driven with an event timer.
    const std::uint32_t cob = kTpdo1Base + node;
    steps.push_back(sdo_write_step(od::tpdo1_communication, 1, 0x80000000U | cob, 4));
    steps.push_back(sdo_write_step(od::tpdo1_mapping, 0, 0, 1));
    steps.push_back(sdo_write_step(od::tpdo1_mapping, 1, 0x60410010U, 4));
    steps.push_back(sdo_write_step(od::tpdo1_mapping, 2, 0x606C0020U, 4));
    steps.push_back(sdo_write_step(od::tpdo1_mapping, 3, 0x60780010U, 4));
    steps.push_back(sdo_write_step(od::tpdo1_mapping, 0, 3, 1));
    steps.push_back(sdo_write_step(od::tpdo1_communication, 2, 0xFF, 1));
    steps.push_back(sdo_write_step(od::tpdo1_communication, 5, static_cast<std::uint32_t>(opt.feedback_period_ms), 2));
    steps.push_back(sdo_write_step(od::tpdo1_communication, 1, cob, 4));
    // Mode of operation, checked through the display object.
    const auto mode = static_cast<std::uint8_t>(opt.mode);
    steps.push_back(sdo_write_step(od::modes_of_operation, 0, mode, 1));
    steps.push_back([me, mode](Done d) {
      me->sdo_upload(od::modes_of_operation_display, 0, [mode, d = std::move(d)](Result<std::uint32_t> r) {
        if (!r) return d(r.error());
        if ((*r & 0xFFU) != mode)
          return d(make_error("spindle.mode", "spindle: the drive did not accept mode of operation " +
                                                  std::to_string(mode) + " (0x6061 reads " +
                                                  std::to_string(static_cast<std::int8_t>(*r & 0xFFU)) +
                                                  "): check that it supports it or set [spindle] mode", ErrorKind::unavailable));
        d(Status{});
      });
    });
    steps.push_back(read_statusword_step());
    steps.push_back([me, node](Done d) {
      me->send(nmt_frame(NmtCommand::start, node));
      me->wait_until([](const SpindleStatus& x) { return x.nmt == NmtState::operational && x.feedback_frames > 0; },
                     me->opt.step_timeout_ms, "the drive to become operational and send TPDO1", std::move(d));
    });
    // A drive found in fault: its error code (0x603F) says why. A heartbeat error (0x8130) means
    // the drive lost this master while it was not running (fettled restarted or killed): the
    // cause is gone now that the heartbeat is back, so the fault is reset here, with a warning.
    // Any other fault stays latched until an operator resets it.
    steps.push_back([me](Done d) {
      if (me->st.state != DriveState::fault) return d(Status{});
      me->sdo_upload(od::error_code, 0, [me, d = std::move(d)](Result<std::uint32_t> r) {
        me->found_error_code = r ? std::optional<std::uint16_t>(static_cast<std::uint16_t>(*r & 0xFFFFU)) : std::nullopt;
        d(Status{});
      });
    });
    steps.push_back([me](Done d) {
      if (me->st.state != DriveState::fault || me->found_error_code != kHeartbeatErrorCode) return d(Status{});
      me->log->warn("drive node {} was in fault {} when it was started: it lost the master's heartbeat while "
                    "fettled was not running; resetting that fault",
                    me->opt.node_id, hex(kHeartbeatErrorCode, 4) + " " + emcy_code_text(kHeartbeatErrorCode));
      me->chain(me->fault_reset_steps(), 0, std::move(d));
    });
    steps.push_back([me](Done d) {
      me->st.configured = true;
      me->log->info("drive node {} operational, state '{}', rated current {:.2f} A", me->opt.node_id,
                    canopen::to_string(me->st.state), me->st.rated_current_a);
      if (me->st.state == DriveState::fault || me->st.state == DriveState::fault_reaction_active) {
        if (me->found_error_code && *me->found_error_code != 0)
          me->latch_fault(make_error("spindle.fault", "spindle: the drive was in fault when started: error code (0x603F) " +
                                                          hex(*me->found_error_code, 4) + " " +
                                                          emcy_code_text(*me->found_error_code) +
                                                          "; fix the cause, then fault_reset()", ErrorKind::device_fault));
        else
          me->set_statusword(me->st.statusword);  // latches the fault now that we are configured
        return d(*me->st.fault);
      }
      d(me->fault_status());
    });
    run(*gen, std::move(steps));
  }

  Status check_ready(const char* what) const {
    if (!st.configured)
      return make_error("spindle.not_started", std::string("spindle: ") + what + " before activate() completed", ErrorKind::unavailable);
    if (st.fault) return *st.fault;
    return Status{};
  }

  void spin_up(double rpm, Done done) {
    if (auto s = check_ready("spin_up"); !s) return done(s);
    if (!std::isfinite(rpm) || std::abs(rpm) > opt.max_rpm)
      return done(make_error("spindle.bad_speed", "spindle: " + std::to_string(rpm) + " rpm is outside ±" +
                                                      std::to_string(opt.max_rpm) + " rpm ([spindle] max_rpm)", ErrorKind::invalid_request));
    auto gen = begin_op(std::move(done), true);
    if (!gen) return;
    const auto me = shared_from_this();
    const auto target = static_cast<std::int32_t>(std::lround(rpm));
    std::vector<Step> steps;
    if (opt.mode == OperationMode::profile_velocity)
      steps.push_back(sdo_write_step(od::target_velocity, 0, static_cast<std::uint32_t>(target), 4));
    else
      steps.push_back(sdo_write_step(od::vl_target_velocity, 0,
                                     static_cast<std::uint16_t>(static_cast<std::int16_t>(target)), 2));
    steps.push_back([me, target](Done d) {
      me->st.target_rpm = target;
      d(Status{});
    });
    // Walk the power state machine up from wherever it is.
    steps.push_back([me](Done d) {
      const DriveState s = me->st.state;
      std::vector<Step> more;
      if (s == DriveState::switch_on_disabled || s == DriveState::not_ready_to_switch_on ||
          s == DriveState::quick_stop_active)
        more.push_back(me->state_step(controlword::shutdown, DriveState::ready_to_switch_on));
      if (s != DriveState::switched_on && s != DriveState::operation_enabled)
        more.push_back(me->state_step(controlword::switch_on, DriveState::switched_on));
      if (s != DriveState::operation_enabled)
        more.push_back(me->state_step(controlword::enable_operation, DriveState::operation_enabled));
      me->chain(std::move(more), 0, std::move(d));
    });
    const double tol = opt.at_speed_tolerance_rpm;
    steps.push_back(wait_step(
        [tol, target](const SpindleStatus& x) {
          return x.state == DriveState::operation_enabled && std::abs(x.velocity_rpm - target) <= tol;
        },
        opt.spin_up_timeout_ms, std::to_string(target) + " rpm ±" + std::to_string(static_cast<int>(tol))));
    run(*gen, std::move(steps));
  }

  /// Runs steps inside one step (no operation bookkeeping).
  void chain(std::vector<Step> steps, std::size_t i, Done done) {
    chain_list(std::make_shared<std::vector<Step>>(std::move(steps)), i, std::move(done));
  }
  void chain_list(std::shared_ptr<std::vector<Step>> list, std::size_t i, Done done) {
    if (i == list->size()) return done(Status{});
    (*list)[i]([self = shared_from_this(), list, i, done = std::move(done)](Status s) mutable {
      if (!s) return done(std::move(s));
      self->chain_list(list, i + 1, std::move(done));
    });
  }

  void spin_down(Done done) {
    if (!st.configured)
      return done(make_error("spindle.not_started", "spindle: spin_down before activate() completed", ErrorKind::unavailable));
    if (op_done)  // stop wins over a running spin_up
      finish_op(op_gen, make_error("spindle.cancelled", "spindle: cancelled by spin_down()", ErrorKind::cancelled));
    auto gen = begin_op(std::move(done), true);
    if (!gen) return;
    if (st.fault) return finish_op(*gen, *st.fault);
    const auto me = shared_from_this();
    std::vector<Step> steps;
    if (opt.mode == OperationMode::profile_velocity)
      steps.push_back(sdo_write_step(od::target_velocity, 0, 0, 4));
    else
      steps.push_back(sdo_write_step(od::vl_target_velocity, 0, 0, 2));
    steps.push_back([me](Done d) {
      me->st.target_rpm = 0;
      d(Status{});
    });
    const double tol = opt.at_speed_tolerance_rpm;
    if (st.state == DriveState::operation_enabled)
      steps.push_back(wait_step([tol](const SpindleStatus& x) { return std::abs(x.velocity_rpm) <= tol; },
                                opt.spin_up_timeout_ms, "standstill"));
    if (st.state == DriveState::operation_enabled || st.state == DriveState::switched_on)
      steps.push_back(state_step(controlword::shutdown, DriveState::ready_to_switch_on));
    run(*gen, std::move(steps));
  }

  /// CiA 402 fault reset: a rising edge of controlword bit 7, then "switch on disabled".
  std::vector<Step> fault_reset_steps() {
    std::vector<Step> steps;
    steps.push_back(sdo_write_step(od::controlword, 0, controlword::disable_voltage, 2));  // bit 7 low first
    steps.push_back(sdo_write_step(od::controlword, 0, controlword::fault_reset, 2));
    steps.push_back(read_statusword_step());
    steps.push_back(wait_step([](const SpindleStatus& x) { return x.state == DriveState::switch_on_disabled; },
                              opt.step_timeout_ms, "state 'switch on disabled' after the fault reset"));
    steps.push_back(sdo_write_step(od::controlword, 0, controlword::disable_voltage, 2));
    return steps;
  }

  void fault_reset(Done done) {
    if (!st.configured && !st.fault)
      return done(make_error("spindle.not_started", "spindle: fault_reset before activate() completed", ErrorKind::unavailable));
    if (!st.heartbeat_ok)
      return done(make_error("spindle.heartbeat_lost",
                             "spindle: cannot reset the fault: the drive's heartbeat is missing (check cable and power)", ErrorKind::device_fault));
    auto gen = begin_op(std::move(done), false);
    if (!gen) return;
    const auto me = shared_from_this();
    std::vector<Step> steps = fault_reset_steps();
    steps.push_back([me](Done d) {
      me->log->info("fault reset: drive in '{}'", canopen::to_string(me->st.state));
      me->st.fault.reset();
      d(Status{});
    });
    run(*gen, std::move(steps));
  }

  /// Ends the running operation and sets the target to 0; the drive keeps its heartbeat
  /// consumer fed, so it ramps down instead of faulting.
  void deactivate() {
    if (op_done) finish_op(op_gen, make_error("spindle.inactive", "spindle: deactivated", ErrorKind::cancelled));
    if (st.configured && (st.target_rpm != 0.0 || st.state == DriveState::operation_enabled)) {
      const bool profile = opt.mode == OperationMode::profile_velocity;
      sdo_download(profile ? od::target_velocity : od::vl_target_velocity, 0, 0, profile ? 4 : 2, [](Status) {});
      st.target_rpm = 0;
    }
    st.configured = false;
  }

  void close() {
    closed = true;
    sdo_timer.cancel();
    heartbeat_timer.cancel();
    producer_timer.cancel();
    wait_timer.cancel();
    transport->close();
    op_done = nullptr;
    waiter.reset();
    sdo_queue.clear();
    on_event = nullptr;
  }
};

SpindleDrive::SpindleDrive(boost::asio::io_context& io, std::shared_ptr<CanTransport> transport,
                           SpindleOptions options)
    : impl_(std::make_shared<Impl>(io, std::move(transport), options)) {}

SpindleDrive::~SpindleDrive() { impl_->close(); }

Status SpindleDrive::configure() {
  if (impl_->lifecycle != Lifecycle::unconfigured) return {};
  const auto& o = impl_->opt;
  auto refuse = [&](const std::string& why) {
    impl_->last_error = make_error("spindle.config", "[spindle] " + why, ErrorKind::config);
    return Status{impl_->last_error};
  };
  if (o.node_id < 1 || o.node_id > 127) return refuse("node_id " + std::to_string(o.node_id) + " is not 1-127");
  if (o.master_node_id < 1 || o.master_node_id > 127 || o.master_node_id == o.node_id)
    return refuse("master_node_id " + std::to_string(o.master_node_id) + " must be 1-127 and differ from node_id");
  if (o.heartbeat_producer_ms <= 0 || o.heartbeat_timeout_ms <= o.heartbeat_producer_ms)
    return refuse("heartbeat_timeout_ms (" + std::to_string(o.heartbeat_timeout_ms) +
                  ") must exceed heartbeat_producer_ms (" + std::to_string(o.heartbeat_producer_ms) + "), both above 0");
  if (o.sdo_timeout_ms <= 0 || o.step_timeout_ms <= 0 || o.spin_up_timeout_ms <= 0)
    return refuse("sdo_timeout_ms and spin_up_timeout_ms must be above 0");
  if (!(o.max_rpm > 0.0)) return refuse("max_rpm must be above 0");
  impl_->lifecycle = Lifecycle::inactive;
  impl_->last_error = {};
  return {};
}

Status SpindleDrive::activate() {
  if (impl_->lifecycle == Lifecycle::unconfigured)
    return make_error("spindle.lifecycle", "spindle: activate() before configure()", ErrorKind::unavailable);
  activate_async([impl = std::weak_ptr<Impl>(impl_)](Status st) {
    if (auto self = impl.lock(); self && !st) self->log->warn("spindle not ready: {}", st.error().message);
  });
  return {};
}

void SpindleDrive::activate_async(Done done) {
  if (impl_->lifecycle == Lifecycle::unconfigured)
    return done(make_error("spindle.lifecycle", "spindle: activate() before configure()", ErrorKind::unavailable));
  impl_->lifecycle = Lifecycle::active;
  impl_->start([impl = std::weak_ptr<Impl>(impl_), done = std::move(done)](Status st) {
    if (auto self = impl.lock(); self && !st) self->last_error = st.error();
    done(std::move(st));
  });
}

void SpindleDrive::deactivate() {
  if (impl_->lifecycle != Lifecycle::active) return;
  impl_->deactivate();
  impl_->lifecycle = Lifecycle::inactive;
}

void SpindleDrive::deactivate_async(Done done) {
  if (impl_->lifecycle != Lifecycle::active) return done({});
  deactivate();
  const auto& me = impl_;
  me->log->info("releasing the drive: switch on disabled, heartbeat consumer off");
  me->chain({me->sdo_write_step(od::controlword, 0, controlword::disable_voltage, 2),
             me->sdo_write_step(od::consumer_heartbeat_time, 1, 0, 4)},
            0, std::move(done));
}

Lifecycle SpindleDrive::lifecycle() const { return impl_->lifecycle; }
const Error& SpindleDrive::last_error() const { return impl_->last_error; }
void SpindleDrive::spin_up(double rpm, Done done) { impl_->spin_up(rpm, std::move(done)); }
void SpindleDrive::spin_down(Done done) { impl_->spin_down(std::move(done)); }
void SpindleDrive::fault_reset(Done done) { impl_->fault_reset(std::move(done)); }
void SpindleDrive::on_event(std::function<void(const SpindleEvent&)> handler) { impl_->on_event = std::move(handler); }
const SpindleStatus& SpindleDrive::status() const { return impl_->st; }

void SpindleDrive::sdo_read(std::uint16_t index, std::uint8_t sub, ValueDone done) {
  impl_->sdo_upload(index, sub, std::move(done));
}
void SpindleDrive::sdo_write(std::uint16_t index, std::uint8_t sub, std::uint32_t value, std::uint8_t size,
                             Done done) {
  impl_->sdo_download(index, sub, value, size, std::move(done));
}
void SpindleDrive::nmt(NmtCommand command) {
  impl_->ensure_transport();
  impl_->send(nmt_frame(command, impl_->opt.node_id));
}

std::shared_ptr<CanTransport> make_spindle_transport(boost::asio::io_context& io, const config::SpindleSection& s) {
  if (s.transport == "socketcan") {
    const auto node = static_cast<std::uint32_t>(s.node_id);
    return open_socketcan(io, s.interface,
                          {CanFilter{kEmcyBase + node, 0x7FF}, CanFilter{kTpdo1Base + node, 0x7FF},
                           CanFilter{kSdoTxBase + node, 0x7FF}, CanFilter{kHeartbeatBase + node, 0x7FF}});
  }
  if (s.transport == "socketcand") return open_socketcand(io, s.address, s.port, s.interface);
  throw UserError("[spindle] transport = \"" + s.transport +
                  "\": the simulated drive is only reachable in the same process (fettle-sim); to reach "
                  "'fettle-sim spindle --listen ADDRESS:PORT' from another process use transport = \"socketcand\" "
                  "with address and port");
}

}  // namespace fettle::drivers
