// The cell supervisor of fettled's runtime (runtime_impl.hpp): setup, the PackML state machine,
// faults and their reactions, device events, the end of a cycle, shutdown.
#include <algorithm>
#include <cmath>
#include <type_traits>
#include <utility>
#include <variant>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/detached.hpp>
#include <boost/asio/post.hpp>

#include "runtime_impl.hpp"

namespace fettle::daemon {

void Runtime::Impl::watch_loop(Clock::time_point due) {
  loop_timer.expires_at(due);
  loop_timer.async_wait([weak = weak_from_this(), due](const boost::system::error_code& ec) {
    auto self = weak.lock();
    if (ec || !self || self->shutting_down) return;
    if (const double late_ms = ms_since(due); late_ms >= kLoopLateWarnMs)
      self->log->warn(
          "the event loop was blocked for {:.0f} ms{}: PLC, robot and spindle links were not served "
          "meanwhile (a heartbeat timeout shorter than that faults them)",
          late_ms, self->cycle ? " (cycle " + self->cycle->summary.id + ", step " + self->cycle->step + ")" : "");
    self->watch_loop(Clock::now() + kLoopPeriod);
  });
}

void Runtime::Impl::setup() {
  for (const auto& r : cell.cell.recipes) {
    log->info("loading recipe {} ({})", r.plc_recipe_id, r.file.string());
    recipes[r.plc_recipe_id] = processing->load_recipe(r.file);
  }
  if (!cell.calibration.file.empty()) calibration = config::load_calibration(cell.calibration.file);
  load_cell_bias();
  auto interrupted = records.open();
  if (!interrupted) throw UserError(interrupted.error().message);
  for (const auto& id : *interrupted) log->warn("cycle {} shows as INTERRUPTED (the daemon stopped during it)", id);
  if (!interrupted->empty()) interrupted_cycle = interrupted->back();

  auto weak = weak_from_this();
  auto on_plc_event = [weak](const plc::Event& e) {
    if (auto self = weak.lock()) self->on_plc(e);
  };
  plc_link = options.make_plc
                 ? options.make_plc(io, cell, on_plc_event)
                 : std::make_unique<plc::Link>(io.get_executor(), plc::LinkOptions::from_config(cell), on_plc_event);
  if (auto st = plc_link->configure(); !st) throw UserError(st.error().message);
  robot = options.make_robot ? options.make_robot(io, cell)
                             : std::make_unique<drivers::RobotLink>(io, drivers::RobotLinkOptions::from_config(cell.robot));
  if (auto st = robot->configure(); !st) throw UserError(st.error().message);
  robot->on_state([weak](drivers::RobotState s, const Error& cause) {
    if (auto self = weak.lock()) self->on_robot_state(s, cause);
  });
  camera = options.make_camera ? options.make_camera(cell)
                               : std::make_unique<drivers::GigECamera>(drivers::camera_options(cell.camera));
  if (auto st = camera->configure(); !st) throw UserError(st.error().message);
  spindle = options.make_spindle
                ? options.make_spindle(io, cell)
                : std::make_unique<drivers::SpindleDrive>(io, drivers::make_spindle_transport(io, cell.spindle),
                                                          drivers::SpindleOptions::from_config(cell.spindle));
  if (auto st = spindle->configure(); !st) throw UserError(st.error().message);
  spindle->on_event([weak](const drivers::SpindleEvent& e) {
    if (auto self = weak.lock()) self->on_spindle(e);
  });
  (void)plc_link->set_state(machine.state());
  if (auto st = plc_link->activate(); !st) throw UserError(st.error().message);
  if (auto st = robot->activate(); !st) throw UserError(st.error().message);
  start_spindle();
  open_camera();
  publish_state();
  watch_loop(Clock::now() + kLoopPeriod);
}

void Runtime::Impl::start_spindle() {
  if (spindle->status().configured) return;
  spindle->activate_async([this, self = shared_from_this()](Status st) {
    if (!st)
      log->warn("spindle drive not ready: {} ({}); retried at the next Reset", st.error().message, st.error().code);
    else
      log->info("spindle drive configured");
  });
}

void Runtime::Impl::open_camera() {
  if (camera_open->load()) return;
  asio::post(camera_thread, [this, self = shared_from_this()] {
    if (camera->lifecycle() == drivers::Lifecycle::active) return;
    if (auto st = camera->activate(); !st) {
      log->warn("camera {} not available yet: {}", cell.camera.address, st.error().message);
      return;
    }
    camera_open->store(true);
    log->info("camera open: {}", camera->info().to_string());
  });
}

void Runtime::Impl::publish_state() {
  const State s = machine.state();
  if (plc_link) (void)plc_link->set_state(s);
  std::string line = std::string(packml::name(s));
  if (cycle) line += ": cycle " + cycle->summary.id + (cycle->step.empty() ? "" : " (" + cycle->step + ")");
  if (fault) line += " - fault " + fault->describe();
  if (options.on_state) options.on_state(s, line);
}

void Runtime::Impl::enter(State s) {
  ++generation;
  log->info("PackML state {} ({})", packml::name(s), packml::code(s));
  publish_state();
  const auto gen = generation;
  auto self = shared_from_this();
  if (s == State::execute) {
    asio::post(io, [self] { self->maybe_start_cycle(); });
  } else if (PackmlMachine::is_acting(s)) {  // the other acting states do their work, then SC
    asio::co_spawn(io, act(s, gen), asio::detached);
  }
}

/// The acting state's work; then its SC if nothing else happened meanwhile.
asio::awaitable<void> Runtime::Impl::act(State s, std::uint64_t gen) {
  auto self = shared_from_this();
  try {
    switch (s) {
      case State::aborting:
        co_await stop_robot();
        co_await stop_spindle();
        co_await wait_cycle_gone();
        break;
      case State::stopping:
      case State::holding:
        co_await stop_robot_if_moving();
        co_await stop_spindle();
        co_await wait_cycle_gone();
        if (plc_up) co_await slide_home_best_effort();
        break;
      case State::suspending:
        co_await wait_cycle_gone();  // a running cycle finishes first
        break;
      case State::clearing:
        co_await clear_devices();
        break;
      case State::resetting:
        co_await reset_devices();
        break;
      default:
        break;
    }
  } catch (const std::exception& e) {
    log->error("PackML {}: {}", packml::name(s), e.what());
  }
  if (gen != generation || machine.state() != s) co_return;
  if (auto next = machine.state_complete(); next) enter(*next);
}

Status Runtime::Impl::command(Command c, const std::string& source) {
  // A Reset clears the latched fault in any state (docs/faults.md: in Held it clears the latch
  // and Held stays Held): one log line says what the command did.
  std::optional<Fault> cleared;
  if (c == Command::reset && fault) cleared = std::exchange(fault, std::nullopt);
  auto next = machine.command(c);
  if (!next) {
    if (cleared) {
      log->info("Reset from {} clears fault {}; the cell stays {}", source, cleared->describe(),
                packml::name(machine.state()));
      publish_state();
      return {};
    }
    log->warn("{} from {} ignored: {}", packml::name(c), source, next.error().message);
    publish_state();
    return next.error();
  }
  if (cleared) log->info("Reset from {} clears fault {}", source, cleared->describe());
  log->info("PackML command {} from {}", packml::name(c), source);
  if ((c == Command::abort || c == Command::stop || c == Command::hold) && cycle && !cycle->fault)
    interrupt(Fault{c == Command::abort ? FaultCode::operator_abort : FaultCode::operator_abort,
                    std::string(packml::name(c)) + " commanded by " + source, cycle->step});
  if (c == Command::abort) quick_robot_stop();
  enter(*next);
  return {};
}

/// A fault: latch it, tell the PLC, end the cycle, Hold or Abort.
void Runtime::Impl::raise(Fault f) {
  log->error("fault {}", f.describe());
  if (!fault) fault = f;
  if (plc_link) (void)plc_link->raise_fault(static_cast<std::uint16_t>(f.number()));
  interrupt(f);
  const State s = machine.state();
  if (f.reaction() == FaultReaction::abort) {
    quick_robot_stop();
    if (auto next = machine.command(Command::abort); next) enter(*next);
  } else if (auto next = machine.command(Command::hold); next) {
    enter(*next);
  } else {
    log->warn("fault {} in state {}: latched (Hold is not possible here)", f.id(), packml::name(s));
    publish_state();
  }
}

void Runtime::Impl::interrupt(const Fault& f) {
  if (!cycle || cycle->fault) return;
  cycle->fault = f;
  if (cycle->fault->step.empty()) cycle->fault->step = cycle->step;
  if (cycle->cancel) cycle->cancel();
}

/// Sends STOP at once when the robot may move (the first thing on any abort).
void Runtime::Impl::quick_robot_stop() {
  if (!robot) return;
  const auto rs = robot->state();
  if (rs == drivers::RobotState::running || rs == drivers::RobotState::uploading ||
      rs == drivers::RobotState::uploaded) {
    log->warn("stopping the robot");
    robot->stop([this, self = shared_from_this()](Status st) {
      if (!st) log->warn("robot STOP: {}", st.error().message);
    });
  }
}

asio::awaitable<void> Runtime::Impl::stop_robot() {
  if (!robot) co_return;
  const auto rs = robot->state();
  if (rs == drivers::RobotState::disconnected || rs == drivers::RobotState::connecting ||
      rs == drivers::RobotState::faulted || rs == drivers::RobotState::ready)
    co_return;
  // In state stopping (the quick STOP of an abort) this waits for that STOP's ACK.
  auto st = co_await await_op<Status>(
      nullptr, [this](std::function<void(Status)> done) { robot->stop(done); },
      milliseconds(cell.robot.reply_timeout_ms + 500));
  if (!st || !*st) log->warn("robot STOP not acknowledged: {}", st ? st->error().message : "timeout");
}

asio::awaitable<void> Runtime::Impl::stop_robot_if_moving() {
  if (robot && (robot->state() == drivers::RobotState::running || robot->state() == drivers::RobotState::uploading))
    co_await stop_robot();
}

asio::awaitable<void> Runtime::Impl::stop_spindle() {
  if (!spindle || !spindle->status().configured) co_return;
  if (spindle->status().fault) co_return;  // a faulted drive has no torque; never re-enabled here
  if (spindle->status().target_rpm == 0.0 && std::abs(spindle->status().velocity_rpm) < 1.0) co_return;
  auto st = co_await await_op<Status>(
      nullptr, [this](std::function<void(Status)> done) { spindle->spin_down(done); },
      milliseconds(cell.spindle.spin_up_timeout_ms + 1000));
  if (!st || !*st) log->warn("spindle stop: {}", st ? st->error().message : "timeout");
}

/// The last thing before fettled exits: the drive stops watching our heartbeat, so a clean stop
/// leaves it without a heartbeat fault (only SIGKILL may; docs/daemon.md).
asio::awaitable<void> Runtime::Impl::release_spindle() {
  if (!spindle->status().heartbeat_ok) {  // the bus or the drive is gone: nothing to tell it
    log->info("spindle not released: the drive's heartbeat is missing");
    spindle->deactivate();
    co_return;
  }
  auto st = co_await await_op<Status>(
      nullptr, [this](std::function<void(Status)> d) { spindle->deactivate_async(d); }, milliseconds(1000));
  if (!st || !*st) log->warn("spindle release: {}", st ? st->error().message : "timeout");
}

asio::awaitable<void> Runtime::Impl::wait_cycle_gone() {
  for (int i = 0; i < 200 && cycle; ++i) co_await sleep(milliseconds(50));
}

/// Sends the slide home and waits for it, at most travel_timeout_ms; a faulted slide cannot
/// move (it stays where it is until the PLC clears its fault), so that is not waited out.
asio::awaitable<void> Runtime::Impl::slide_home_best_effort() {
  if (slide.status == plc::SlideStatus::at_home) co_return;
  if (slide.status == plc::SlideStatus::fault) {
    log->warn("the slide is in fault at position {}: not sent home (the PLC must clear its fault)", slide.position);
    co_return;
  }
  const auto command = plc_link->command_slide(0);
  if (!command) co_return;
  for (int i = 0; i < cell.slide.travel_timeout_ms / 50 && plc_up &&
                  !slide.reached(*command, 0) &&
                  slide.status != plc::SlideStatus::fault;
       ++i)
    co_await sleep(milliseconds(50));
}

asio::awaitable<void> Runtime::Impl::clear_devices() {
  if (robot && robot->state() == drivers::RobotState::faulted) {
    auto st = co_await await_op<Status>(
        nullptr, [this](std::function<void(Status)> d) { robot->reset(d); },
        milliseconds(cell.robot.reply_timeout_ms + 500));
    if (!st || !*st) log->warn("robot RESET: {}", st ? st->error().message : "timeout");
  }
  if (spindle && spindle->status().fault) {
    auto st = co_await await_op<Status>(
        nullptr, [this](std::function<void(Status)> d) { spindle->fault_reset(d); }, milliseconds(3000));
    if (!st || !*st)
      log->warn("spindle fault reset: {}", st ? st->error().message : "timeout");
    else
      log->info("spindle fault reset");
  }
}

asio::awaitable<void> Runtime::Impl::reset_devices() {
  co_await clear_devices();
  if (spindle && !spindle->status().configured) {
    auto st = co_await await_op<Status>(
        nullptr, [this](std::function<void(Status)> d) { spindle->activate_async(d); }, milliseconds(5000));
    if (!st || !*st) log->warn("spindle not ready: {}", st ? st->error().message : "timeout");
  }
  open_camera();
}

void Runtime::Impl::on_plc(const plc::Event& e) {
  std::visit(
      [this](const auto& ev) {
        using E = std::decay_t<decltype(ev)>;
        if constexpr (std::is_same_v<E, plc::LinkUp>) {
          plc_up = true;
          log->info("PLC link up ({})", ev.peer);
          publish_state();
        } else if constexpr (std::is_same_v<E, plc::LinkDown>) {
          const bool was_up = plc_up;
          plc_up = false;
          log->warn("PLC link down: {} ({})", plc::name(ev.reason), ev.detail);
          if (was_up && (cycle || machine.state() == State::execute)) {
            const bool motion = cycle && cycle->motion;
            raise(Fault{motion ? FaultCode::plc_link_lost_moving : FaultCode::plc_link_lost,
                        std::string(plc::name(ev.reason)) + ": " + ev.detail, cycle ? cycle->step : ""});
          }
        } else if constexpr (std::is_same_v<E, plc::Reconnecting>) {
          log->debug("PLC reconnect attempt {} in {} ms", ev.attempt, ev.delay_ms);
        } else if constexpr (std::is_same_v<E, plc::CycleRequest>) {
          log->info("cycle request for recipe {}", ev.recipe_id);
          pending_recipe = ev.recipe_id;
          maybe_start_cycle();
        } else if constexpr (std::is_same_v<E, plc::SlideState>) {
          slide = ev;
          if (slide_wait) {
            if (ev.status == plc::SlideStatus::fault) {
              slide_wait->set(Error{"slide.fault", "the PLC reports a slide fault"});
            } else if (ev.reached(slide_command, slide_target)) {
              slide_wait->set(Status{});
            }
          }
        } else if constexpr (std::is_same_v<E, plc::ResultAcknowledged>) {
          log->debug("the PLC acknowledged result {}", plc::name(ev.result));
          maybe_start_cycle();
        } else if constexpr (std::is_same_v<E, plc::PackMLCommand>) {
          (void)command(ev.command, "PLC");
        } else if constexpr (std::is_same_v<E, plc::ValueOutOfRange>) {
          const std::string what = "register " + std::to_string(ev.address) + " holds " + std::to_string(ev.value) +
                                   "; allowed " + ev.allowed;
          if (cycle || machine.state() == State::execute)
            raise(Fault{FaultCode::plc_value_out_of_range, what, cycle ? cycle->step : ""});
          else
            log->warn("PLC: {}", what);
        }
      },
      e);
}

void Runtime::Impl::on_robot_state(drivers::RobotState s, const Error& cause) {
  log->info("robot {}{}", drivers::to_string(s),
            cause.code.empty() ? "" : " (" + cause.code + ": " + cause.message + ")");
  if (!cycle || !cycle->motion) return;
  if (s == drivers::RobotState::disconnected)
    raise(Fault{FaultCode::robot_link_lost_moving, cause.code + ": " + cause.message, cycle->step});
  else if (s == drivers::RobotState::faulted)
    raise(Fault{FaultCode::robot_fault, cause.code + ": " + cause.message, cycle->step});
}

void Runtime::Impl::on_spindle(const drivers::SpindleEvent& e) {
  if (e.kind == drivers::SpindleEvent::Kind::fault) {
    log->error("spindle fault: {}", e.message);
    if (cycle || machine.state() == State::execute)
      raise(Fault{FaultCode::spindle_fault, e.message, cycle ? cycle->step : ""});
  } else if (e.kind != drivers::SpindleEvent::Kind::state_changed) {
    log->info("spindle {}: {}", drivers::to_string(e.kind), e.message);
  }
}

void Runtime::Impl::finish_cycle(const std::shared_ptr<Cycle>& cp) {
  Cycle& c = *cp;
  record_cycle(c);
  const CycleSummary& s = c.summary;
  last_result = s.result;
  log->info("cycle {} ended: {} in {:.1f} s{}", s.id, s.result, s.duration_s,
            c.fault ? " - " + c.fault->describe() : "");
  // Every cycle the PLC requested ends in exactly one result, a faulted one in FAULT (its code
  // is in fault_code when it latched): the PLC can tell "still running" from "failed"
  // (docs/plc-interface.md; test CycleFaults.*).
  if (!c.dry && plc_link)
    (void)plc_link->report_result(c.fault           ? plc::CycleResult::fault
                                  : s.result == "OK" ? plc::CycleResult::ok
                                                     : plc::CycleResult::nok);
  if (cycle == cp) cycle.reset();
  publish_state();
  if (machine.state() == State::execute && options.max_cycles > 0 && cycles_in_execute >= options.max_cycles) {
    log->info("{} cycle(s) done: Execute completes", cycles_in_execute);
    if (auto next = machine.state_complete(); next) enter(*next);
    return;
  }
  asio::post(io, [self = shared_from_this()] { self->maybe_start_cycle(); });
}

RuntimeStatus Runtime::Impl::snapshot() const {
  RuntimeStatus s;
  s.state = machine.state();
  s.fault = fault;
  if (cycle) {
    s.cycle_id = cycle->summary.id;
    s.step = cycle->step;
  }
  s.cycles_total = cycles_total;
  s.last_result = last_result;
  s.plc_up = plc_up;
  s.robot_state = robot ? std::string(drivers::to_string(robot->state())) : "";
  s.spindle_configured = spindle && spindle->status().configured;
  return s;
}

void Runtime::Impl::shutdown(std::function<void()> done) {
  shutting_down = true;
  loop_timer.cancel();
  interrupt(Fault{FaultCode::operator_abort, "fettled is shutting down", cycle ? cycle->step : ""});
  quick_robot_stop();
  asio::co_spawn(
      io,
      [self = shared_from_this(), done]() -> asio::awaitable<void> {
        co_await self->stop_robot();
        co_await self->stop_spindle();
        co_await self->wait_cycle_gone();
        self->log->info("shutdown: robot {}, spindle at {:.0f} rpm",
                        self->robot ? drivers::to_string(self->robot->state()) : "not configured",
                        self->spindle ? self->spindle->status().velocity_rpm : 0.0);
        if (self->spindle) co_await self->release_spindle();
        // two polls: the interrupted cycle's FAULT result reaches the PLC before the link closes
        co_await self->sleep(milliseconds(2 * std::max(1, self->cell.plc.poll_period_ms)));
        if (self->plc_link) self->plc_link->deactivate();
        if (self->robot) self->robot->deactivate();
        self->workers.stop();
        self->camera_thread.stop();
        self->record_writer.stop();
        if (done) done();
      },
      asio::detached);
}

}  // namespace fettle::daemon
