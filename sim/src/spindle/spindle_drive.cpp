// The simulated CiA 402 spindle drive (see fettle/sim/spindle.hpp).
#include <algorithm>
#include <cmath>
#include <map>
#include <mutex>

#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>

#include "fettle/core/log.hpp"
#include "fettle/sim/spindle.hpp"

namespace fettle::sim {

using namespace fettle::canopen;

Result<SpindleFault> parse_spindle_fault(const std::string& name) {
  if (name == "overcurrent") return SpindleFault::overcurrent;
  if (name == "overtemperature") return SpindleFault::overtemperature;
  if (name == "heartbeat_loss") return SpindleFault::heartbeat_loss;
  return Error{"sim.spindle.bad_fault",
               "unknown spindle fault '" + name + "' (expected overcurrent, overtemperature or heartbeat_loss)"};
}

namespace {

constexpr std::uint32_t key(std::uint16_t index, std::uint8_t sub) {
  return (static_cast<std::uint32_t>(index) << 8U) | sub;
}

struct Entry {
  std::uint32_t value = 0;
  std::uint8_t size = 4;
  bool writable = true;
};

}  // namespace

struct SimulatedSpindleDrive::Impl : std::enable_shared_from_this<Impl> {
  Impl(boost::asio::io_context& io_, std::shared_ptr<CanTransport> t, SpindleSimOptions o)
      : io(io_), transport(std::move(t)), opt(o), tick_timer(io_), hb_timer(io_), consumer_timer(io_),
        log(log::get("sim.spindle")) {}

  boost::asio::io_context& io;
  std::shared_ptr<CanTransport> transport;
  SpindleSimOptions opt;
  boost::asio::steady_timer tick_timer;
  boost::asio::steady_timer hb_timer;
  boost::asio::steady_timer consumer_timer;
  std::shared_ptr<spdlog::logger> log;

  std::map<std::uint32_t, Entry> od;
  NmtState nmt = NmtState::boot_up;
  DriveState state = DriveState::switch_on_disabled;
  std::uint16_t last_controlword = 0;
  double velocity = 0.0;  // rpm
  double current = 0.0;   // A
  bool ramping = false;
  std::atomic<double> removal_mm3_s{0.0};
  std::atomic<bool> heartbeat_enabled{true};
  bool consumer_active = false;
  int since_tpdo_ms = 0;
  std::uint16_t last_tpdo_statusword = 0xFFFF;
  bool powered = false;
  bool closed = false;

  // ---------------------------------------------------------------- object dictionary
  void reset_communication() {
    od[key(od::producer_heartbeat_time, 0)] = {0, 2, true};
    od[key(od::consumer_heartbeat_time, 0)] = {1, 1, false};
    od[key(od::consumer_heartbeat_time, 1)] = {0, 4, true};
    const std::uint32_t cob = kTpdo1Base + opt.node_id;
    od[key(od::tpdo1_communication, 0)] = {5, 1, false};
    od[key(od::tpdo1_communication, 1)] = {0x80000000U | cob, 4, true};
    od[key(od::tpdo1_communication, 2)] = {0xFF, 1, true};
    od[key(od::tpdo1_communication, 3)] = {0, 2, true};
    od[key(od::tpdo1_communication, 5)] = {0, 2, true};
    od[key(od::tpdo1_mapping, 0)] = {0, 1, true};
    for (std::uint8_t s = 1; s <= 8; ++s) od[key(od::tpdo1_mapping, s)] = {0, 4, true};
    consumer_active = false;
    consumer_timer.cancel();
  }

  void reset_application() {
    od[key(od::error_register, 0)] = {0, 1, false};
    od[key(od::identity, 0)] = {4, 1, false};
    od[key(od::identity, 1)] = {opt.vendor_id, 4, false};
    od[key(od::identity, 2)] = {0x00000402, 4, false};
    od[key(od::identity, 3)] = {0x00010000, 4, false};
    od[key(od::identity, 4)] = {1, 4, false};
    od[key(od::controlword, 0)] = {0, 2, true};
    od[key(od::statusword, 0)] = {0, 2, false};
    od[key(od::error_code, 0)] = {0, 2, false};
    od[key(od::vl_target_velocity, 0)] = {0, 2, true};
    od[key(od::vl_velocity_actual, 0)] = {0, 2, false};
    od[key(od::modes_of_operation, 0)] = {static_cast<std::uint8_t>(OperationMode::profile_velocity), 1, true};
    od[key(od::modes_of_operation_display, 0)] = {static_cast<std::uint8_t>(OperationMode::profile_velocity), 1, false};
    od[key(od::velocity_actual, 0)] = {0, 4, false};
    od[key(od::motor_rated_current, 0)] = {static_cast<std::uint32_t>(std::lround(opt.rated_current_a * 1000.0)), 4, true};
    od[key(od::current_actual, 0)] = {0, 2, false};
    od[key(od::target_velocity, 0)] = {0, 4, true};
    state = DriveState::switch_on_disabled;
    velocity = 0.0;
    current = 0.0;
    last_controlword = 0;
  }

  std::uint16_t statusword() const {
    std::uint16_t sw = statusword_of(state) | kStatusRemote;
    if (state == DriveState::switch_on_disabled || state == DriveState::not_ready_to_switch_on) sw &= ~0x0010U;
    if (state == DriveState::operation_enabled || state == DriveState::switched_on ||
        state == DriveState::ready_to_switch_on)
      sw |= 0x0010U;  // voltage enabled
    if (std::abs(velocity - target_rpm()) < 1.0) sw |= kStatusTargetReached;
    return static_cast<std::uint16_t>(sw);
  }

  double target_rpm() const {
    if (state != DriveState::operation_enabled) return 0.0;
    double t = 0.0;
    if (mode() == static_cast<std::int8_t>(OperationMode::velocity))
      t = static_cast<std::int16_t>(od.at(key(od::vl_target_velocity, 0)).value & 0xFFFFU);
    else
      t = static_cast<std::int32_t>(od.at(key(od::target_velocity, 0)).value);
    return std::clamp(t, -opt.max_rpm, opt.max_rpm);
  }

  std::int8_t mode() const {
    return static_cast<std::int8_t>(od.at(key(od::modes_of_operation, 0)).value & 0xFFU);
  }

  std::uint32_t live_value(std::uint16_t index, std::uint8_t sub) const {
    if (sub == 0) {
      switch (index) {
        case od::statusword: return statusword();
        case od::velocity_actual: return static_cast<std::uint32_t>(static_cast<std::int32_t>(std::lround(velocity)));
        case od::vl_velocity_actual:
          return static_cast<std::uint16_t>(static_cast<std::int16_t>(std::clamp(std::lround(velocity), -32768L, 32767L)));
        case od::current_actual: {
          const long permille = std::lround(current / opt.rated_current_a * 1000.0);
          return static_cast<std::uint16_t>(static_cast<std::int16_t>(std::clamp(permille, -32768L, 32767L)));
        }
        case od::modes_of_operation_display: return od.at(key(od::modes_of_operation, 0)).value;
        default: break;
      }
    }
    return od.at(key(index, sub)).value;
  }

  // ---------------------------------------------------------------- lifecycle
  void power_on() {
    if (powered) return;
    powered = true;
    std::weak_ptr<Impl> weak = shared_from_this();
    transport->start(
        [weak](const CanFrame& f) {
          if (auto self = weak.lock()) self->on_frame(f);
        },
        [weak](const Error& e) {
          if (auto self = weak.lock()) self->log->warn("{}", e.message);
        });
    reset_application();
    boot();
    tick();
  }

  void boot() {
    reset_communication();
    nmt = NmtState::boot_up;
    send(heartbeat_frame(opt.node_id, NmtState::boot_up));
    nmt = NmtState::pre_operational;
    schedule_heartbeat();
  }

  void send(const CanFrame& f) {
    if (!closed) transport->send(f);
  }

  void schedule_heartbeat() {
    hb_timer.cancel();
    const auto period = od[key(od::producer_heartbeat_time, 0)].value;
    if (period == 0) return;
    hb_timer.expires_after(std::chrono::milliseconds(period));
    hb_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (ec) return;
      if (self->heartbeat_enabled) self->send(heartbeat_frame(self->opt.node_id, self->nmt));
      self->schedule_heartbeat();
    });
  }

  void tick() {
    if (closed) return;
    tick_timer.expires_after(std::chrono::milliseconds(opt.tick_ms));
    tick_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (ec) return;
      self->step(self->opt.tick_ms / 1000.0);
      self->tick();
    });
  }

  void step(double dt_s) {
    const double target = target_rpm();
    const double dv = opt.ramp_rpm_s * dt_s;
    const double before = velocity;
    if (std::abs(target - velocity) <= dv)
      velocity = target;
    else
      velocity += target > velocity ? dv : -dv;
    ramping = velocity != before;
    const bool powered_stage = state == DriveState::operation_enabled;
    current = 0.0;
    if (powered_stage || ramping) {
      if (std::abs(velocity) > 1.0) current += opt.idle_current_a + opt.current_per_removal_a * removal_mm3_s.load();
      if (ramping && powered_stage) current += opt.accel_current_a;
    }
    if (current > opt.trip_current_a && state == DriveState::operation_enabled) fault(SpindleFault::overcurrent);
    if (state == DriveState::quick_stop_active && velocity == 0.0) state = DriveState::switch_on_disabled;
    send_tpdo(opt.tick_ms);
  }

  void send_tpdo(int elapsed_ms) {
    since_tpdo_ms += elapsed_ms;
    if (nmt != NmtState::operational) return;
    const auto cob = od[key(od::tpdo1_communication, 1)].value;
    if (cob & 0x80000000U) return;
    const auto event_ms = static_cast<int>(od[key(od::tpdo1_communication, 5)].value);
    const std::uint16_t sw = statusword();
    const bool changed = sw != last_tpdo_statusword;
    if (!changed && (event_ms == 0 || since_tpdo_ms < event_ms)) return;
    CanFrame f;
    f.id = cob & 0x7FFU;
    const auto count = od[key(od::tpdo1_mapping, 0)].value;
    std::size_t at = 0;
    for (std::uint8_t i = 1; i <= count; ++i) {
      const auto m = od[key(od::tpdo1_mapping, i)].value;
      const auto v = live_value(static_cast<std::uint16_t>(m >> 16U), static_cast<std::uint8_t>((m >> 8U) & 0xFFU));
      for (std::size_t b = 0; b < (m & 0xFFU) / 8U && at < 8; ++b) f.data[at++] = static_cast<std::uint8_t>(v >> (8 * b));
    }
    f.len = static_cast<std::uint8_t>(at);
    send(f);
    since_tpdo_ms = 0;
    last_tpdo_statusword = sw;
  }

  void fault(SpindleFault which) {
    if (state == DriveState::fault) return;
    Emergency e;
    switch (which) {
      case SpindleFault::overcurrent:
        e.error_code = 0x2310;
        e.error_register = 0x03;
        break;
      case SpindleFault::overtemperature:
        e.error_code = 0x4310;
        e.error_register = 0x09;
        break;
      case SpindleFault::heartbeat_loss:
        e.error_code = 0x8130;
        e.error_register = 0x11;
        break;
    }
    log->warn("drive fault: {}", describe(e));
    od[key(od::error_register, 0)].value = e.error_register;
    od[key(od::error_code, 0)].value = e.error_code;
    state = DriveState::fault;  // the power stage is off: the spindle coasts down on the ramp
    if (nmt != NmtState::stopped) send(emcy_frame(opt.node_id, e));
  }

  // ---------------------------------------------------------------- receive
  void on_frame(const CanFrame& f) {
    if (f.extended || f.rtr) return;
    if (f.id == kNmtId) return on_nmt(f);
    if (f.id == kSdoRxBase + opt.node_id) return on_sdo(f);
    const auto consumer = od[key(od::consumer_heartbeat_time, 1)].value;
    const auto watched = (consumer >> 16U) & 0x7FU;
    if (watched != 0 && f.id == kHeartbeatBase + watched) on_master_heartbeat(consumer & 0xFFFFU);
  }

  void on_nmt(const CanFrame& f) {
    if (f.len < 2 || (f.data[1] != 0 && f.data[1] != opt.node_id)) return;
    switch (static_cast<NmtCommand>(f.data[0])) {
      case NmtCommand::start: nmt = NmtState::operational; last_tpdo_statusword = 0xFFFF; break;
      case NmtCommand::stop: nmt = NmtState::stopped; break;
      case NmtCommand::enter_pre_operational: nmt = NmtState::pre_operational; break;
      case NmtCommand::reset_node: reset_application(); boot(); break;
      case NmtCommand::reset_communication: boot(); break;
    }
  }

  void on_master_heartbeat(std::uint32_t time_ms) {
    if (time_ms == 0) return;
    consumer_active = true;
    consumer_timer.expires_after(std::chrono::milliseconds(time_ms));
    consumer_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (ec || !self->consumer_active) return;
      self->consumer_active = false;
      self->log->warn("master heartbeat lost");
      self->fault(SpindleFault::heartbeat_loss);
    });
  }

  void on_sdo(const CanFrame& f) {
    if (nmt == NmtState::stopped) return;
    auto m = decode_sdo(f, true);
    if (!m) return;
    const std::uint8_t node = opt.node_id;
    auto abort = [&](std::uint32_t code) { send(sdo_abort(node, false, m->index, m->subindex, code)); };
    switch (m->kind) {
      case SdoMessage::Kind::upload_request: {
        auto it = od.find(key(m->index, m->subindex));
        if (it == od.end()) return abort(od.lower_bound(key(m->index, 0)) != od.end() &&
                                                 (od.lower_bound(key(m->index, 0))->first >> 8U) == m->index
                                             ? abort_code::no_subindex
                                             : abort_code::no_object);
        return send(sdo_upload_response(node, m->index, m->subindex, live_value(m->index, m->subindex), it->second.size));
      }
      case SdoMessage::Kind::download_request: {
        auto it = od.find(key(m->index, m->subindex));
        if (it == od.end()) return abort(od.lower_bound(key(m->index, 0)) != od.end() &&
                                                 (od.lower_bound(key(m->index, 0))->first >> 8U) == m->index
                                             ? abort_code::no_subindex
                                             : abort_code::no_object);
        if (!it->second.writable) return abort(abort_code::read_only);
        if (m->size != 0 && m->size != it->second.size) return abort(abort_code::length_mismatch);
        const std::uint32_t mask = it->second.size >= 4 ? 0xFFFFFFFFU : ((1U << (8U * it->second.size)) - 1U);
        if (auto code = write(m->index, m->subindex, m->value & mask); code != 0) return abort(code);
        return send(sdo_download_response(node, m->index, m->subindex));
      }
      case SdoMessage::Kind::abort: return;
      default: return abort(abort_code::bad_command);
    }
  }

  /// Applies a write; returns an abort code or 0.
  std::uint32_t write(std::uint16_t index, std::uint8_t sub, std::uint32_t v) {
    auto& e = od[key(index, sub)];
    switch (index) {
      case od::modes_of_operation:
        if (v != 2 && v != 3) return abort_code::value_range;
        if (state == DriveState::operation_enabled && v != e.value) return abort_code::device_state;
        break;
      case od::controlword:
        e.value = v;
        on_controlword(static_cast<std::uint16_t>(v));
        return 0;
      case od::target_velocity: {
        const auto t = static_cast<std::int32_t>(v);
        if (std::abs(t) > static_cast<std::int32_t>(opt.max_rpm)) return abort_code::value_range;
        break;
      }
      case od::vl_target_velocity: {
        const auto t = static_cast<std::int16_t>(v);
        if (std::abs(t) > static_cast<std::int32_t>(opt.max_rpm)) return abort_code::value_range;
        break;
      }
      case od::tpdo1_mapping: {
        const bool valid = (od[key(od::tpdo1_communication, 1)].value & 0x80000000U) == 0;
        if (valid) return abort_code::device_state;  // mapping changes need the PDO disabled first
        if (sub == 0) {
          if (v > 8) return abort_code::value_range;
          unsigned bits = 0;
          for (std::uint8_t i = 1; i <= v; ++i) {
            const auto m = od[key(od::tpdo1_mapping, i)].value;
            const auto k = key(static_cast<std::uint16_t>(m >> 16U), static_cast<std::uint8_t>((m >> 8U) & 0xFFU));
            if (od.find(k) == od.end()) return abort_code::not_mappable;
            if ((m & 0xFFU) != 8U * od[k].size) return abort_code::not_mappable;
            bits += m & 0xFFU;
          }
          if (bits > 64) return abort_code::pdo_too_long;
        } else if (od[key(od::tpdo1_mapping, 0)].value != 0) {
          return abort_code::device_state;
        }
        break;
      }
      default: break;
    }
    e.value = v;
    if (index == od::producer_heartbeat_time) schedule_heartbeat();
    if (index == od::consumer_heartbeat_time) {
      consumer_active = false;
      consumer_timer.cancel();
    }
    return 0;
  }

  void on_controlword(std::uint16_t cw) {
    const bool reset_edge = (cw & 0x80U) != 0 && (last_controlword & 0x80U) == 0;
    last_controlword = cw;
    if (state == DriveState::fault) {
      if (reset_edge) {
        state = DriveState::switch_on_disabled;
        od[key(od::error_register, 0)].value = 0;
        od[key(od::error_code, 0)].value = 0;
        send(emcy_frame(opt.node_id, Emergency{}));  // error reset
        log->info("fault reset");
      }
      return;
    }
    if (cw & 0x80U) return;
    const bool ev = (cw & 0x02U) != 0, qs = (cw & 0x04U) != 0, so = (cw & 0x01U) != 0, eo = (cw & 0x08U) != 0;
    if (!ev) {  // disable voltage
      if (state != DriveState::not_ready_to_switch_on) state = DriveState::switch_on_disabled;
      return;
    }
    if (!qs) {  // quick stop
      if (state == DriveState::operation_enabled) state = DriveState::quick_stop_active;
      else if (state == DriveState::ready_to_switch_on || state == DriveState::switched_on)
        state = DriveState::switch_on_disabled;
      return;
    }
    if (!so) {  // shutdown
      if (state == DriveState::switch_on_disabled || state == DriveState::switched_on ||
          state == DriveState::operation_enabled)
        state = DriveState::ready_to_switch_on;
      return;
    }
    if (!eo) {  // switch on / disable operation
      if (state == DriveState::ready_to_switch_on || state == DriveState::operation_enabled)
        state = DriveState::switched_on;
      return;
    }
    // enable operation
    if (state == DriveState::switched_on || state == DriveState::quick_stop_active)
      state = DriveState::operation_enabled;
  }

  void close() {
    closed = true;
    tick_timer.cancel();
    hb_timer.cancel();
    consumer_timer.cancel();
    transport->close();
  }
};

SimulatedSpindleDrive::SimulatedSpindleDrive(boost::asio::io_context& io, std::shared_ptr<CanTransport> transport,
                                             SpindleSimOptions options)
    : impl_(std::make_shared<Impl>(io, std::move(transport), options)) {}

SimulatedSpindleDrive::~SimulatedSpindleDrive() { impl_->close(); }

void SimulatedSpindleDrive::power_on() { impl_->power_on(); }

void SimulatedSpindleDrive::inject_fault(SpindleFault fault) {
  boost::asio::post(impl_->io, [weak = std::weak_ptr<Impl>(impl_), fault] {
    if (auto self = weak.lock(); self && !self->closed) self->fault(fault);
  });
}

void SimulatedSpindleDrive::set_material_removal_rate(double mm3_s) { impl_->removal_mm3_s = std::max(0.0, mm3_s); }
void SimulatedSpindleDrive::set_heartbeat_enabled(bool enabled) { impl_->heartbeat_enabled = enabled; }
DriveState SimulatedSpindleDrive::state() const { return impl_->state; }
NmtState SimulatedSpindleDrive::nmt_state() const { return impl_->nmt; }
double SimulatedSpindleDrive::velocity_rpm() const { return impl_->velocity; }
double SimulatedSpindleDrive::current_a() const { return impl_->current; }
std::int8_t SimulatedSpindleDrive::mode() const { return impl_->mode(); }
std::uint16_t SimulatedSpindleDrive::heartbeat_producer_ms() const {
  return static_cast<std::uint16_t>(impl_->od.at(key(od::producer_heartbeat_time, 0)).value);
}

}  // namespace fettle::sim
