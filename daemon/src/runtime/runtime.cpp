// The runtime of fettled: event loop, PackML, the cycle, faults, records (runtime.hpp).
#include "fettle/daemon/runtime.hpp"

#include <fcntl.h>
#include <malloc.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <thread>
#include <utility>
#include <vector>

#include <boost/asio/awaitable.hpp>
#include <boost/asio/co_spawn.hpp>
#include <boost/asio/detached.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/redirect_error.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/thread_pool.hpp>
#include <boost/asio/use_awaitable.hpp>

#include "fettle/config/calibration.hpp"
#include "fettle/core/atomic_file.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/daemon/packml_machine.hpp"
#include "fettle/process/pipeline.hpp"
#include "fettle/daemon/records.hpp"
#include "fettle/drivers/camera.hpp"
#include "fettle/drivers/camera_ply.hpp"
#include "fettle/drivers/plc_link.hpp"
#include "fettle/drivers/robot_link.hpp"
#include "fettle/drivers/spindle.hpp"

namespace fettle::daemon {

namespace asio = boost::asio;
namespace fs = std::filesystem;
using process::LoadedRecipe;
using process::ProcessOptions;
using process::ProcessOutput;
using process::StepTiming;
using process::VerificationResult;
using process::Verdict;
using process::View;
namespace plc = drivers::plc;
using nlohmann::json;
using packml::Command;
using packml::State;
using Clock = std::chrono::steady_clock;
using std::chrono::milliseconds;

namespace {

double ms_since(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

/// A value some callback will deliver on the loop thread, awaited with a timeout.
template <class T>
struct Pending {
  explicit Pending(asio::io_context& io) : timer(io) {}
  asio::steady_timer timer;
  std::optional<T> value;
  bool cancelled = false;
  void set(T v) {
    if (value || cancelled) return;
    value.emplace(std::move(v));
    timer.cancel();
  }
  void cancel() {
    cancelled = true;
    timer.cancel();
  }
};

/// Binary little-endian PLY of points with one float property (e.g. a deviation in mm).
Status write_scalar_ply(const fs::path& path, const std::vector<Eigen::Vector3f>& points,
                        const std::vector<float>& values, const std::string& property) {
  std::string out = "ply\nformat binary_little_endian 1.0\ncomment fettle cycle record, mm\nelement vertex " +
                    std::to_string(points.size()) + "\nproperty float x\nproperty float y\nproperty float z\n";
  const bool with_values = values.size() == points.size() && !property.empty();
  if (with_values) out += "property float " + property + "\n";
  out += "end_header\n";
  out.reserve(out.size() + points.size() * 16);
  for (std::size_t i = 0; i < points.size(); ++i) {
    out.append(reinterpret_cast<const char*>(points[i].data()), 3 * sizeof(float));
    if (with_values) out.append(reinterpret_cast<const char*>(&values[i]), sizeof(float));
  }
  return write_file_atomic(path, out);
}

/// Runs `writer(tmp)` then renames tmp onto `path` (after fsync): atomic for writers that write plain files.
Status write_via_temp(const fs::path& path, const std::function<Status(const fs::path&)>& writer) {
  const fs::path tmp = path.parent_path() / ("." + path.filename().string() + ".tmp");
  if (auto st = writer(tmp); !st) return st;
  const int fd = ::open(tmp.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd >= 0) {
    (void)::fsync(fd);
    ::close(fd);
  }
  std::error_code ec;
  fs::rename(tmp, path, ec);
  if (ec) return Error{"records.write", "cannot rename " + tmp.string() + " to " + path.string() + ": " + ec.message()};
  return {};
}

json timings_json(const std::vector<StepTiming>& t) {
  json j = json::array();
  for (const auto& s : t) j.push_back({{"step", s.step}, {"ms", s.ms}});
  return j;
}

std::string safe_name(std::string s) {
  for (auto& c : s)
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_') c = '_';
  return s;
}

}  // namespace

// ---------------------------------------------------------------------------------------------

struct Cycle {
  CycleSummary summary;
  std::shared_ptr<const LoadedRecipe> recipe;
  int recipe_id = 0;
  bool dry = false;
  Clock::time_point t0 = Clock::now();
  std::optional<Fault> fault;
  std::function<void()> cancel;  ///< cancels the current wait
  std::string step;
  Clock::time_point step_t0 = Clock::now();
  json steps = json::array();  ///< [{step, ms}], the step a fault ended also {failed: true}
  bool motion = false;         ///< the robot may move or the spindle turns
  std::vector<View> views;
  std::optional<ProcessOutput> processed;
  std::vector<ProcessOutput> regrinds;
  std::optional<VerificationResult> verification;
  std::optional<VerificationResult> first_verification;
  std::string result;  ///< "OK" / "NOK" when no fault
  json files = json::array();
  std::vector<std::string> warnings;

  void begin(const std::string& name) {
    step = name;
    step_t0 = Clock::now();
  }
  /// Records the step in progress; `failed` marks the one the cycle's fault ended.
  void end(bool failed = false) {
    if (step.empty()) return;
    json record{{"step", step}, {"ms", ms_since(step_t0)}};
    if (failed) record["failed"] = true;
    steps.push_back(std::move(record));
    step.clear();
  }
};

struct Runtime::Impl : std::enable_shared_from_this<Runtime::Impl> {
  Impl(asio::io_context& io_, config::CellConfig cell_, RuntimeOptions options_)
      : io(io_),
        cell(std::move(cell_)),
        options(std::move(options_)),
        workers(static_cast<std::size_t>(cell.cell.workers > 0 ? cell.cell.workers
                                                                : std::max(1U, std::thread::hardware_concurrency()))),
        camera_thread(1),
        record_writer(1),
        records(cell.cell.state_dir, cell.records),
        log(log::get("fettled")) {}

  asio::io_context& io;
  config::CellConfig cell;
  RuntimeOptions options;
  asio::thread_pool workers;
  asio::thread_pool camera_thread;
  asio::thread_pool record_writer;  ///< a cycle's output files (one thread: its memory peak is reached once)
  Records records;
  std::shared_ptr<spdlog::logger> log;

  std::map<int, std::shared_ptr<const LoadedRecipe>> recipes;
  std::optional<config::CalibrationFile> calibration;

  std::unique_ptr<plc::Link> plc_link;
  std::unique_ptr<drivers::RobotLink> robot;
  std::shared_ptr<canopen::CanTransport> can;
  std::unique_ptr<drivers::SpindleDrive> spindle;
  std::shared_ptr<drivers::Camera> camera;  ///< camera thread only
  std::shared_ptr<std::atomic<bool>> camera_open = std::make_shared<std::atomic<bool>>(false);

  PackmlMachine machine;
  std::uint64_t generation = 0;
  std::optional<Fault> fault;  ///< latched until a Reset
  std::shared_ptr<Cycle> cycle;
  std::optional<int> pending_recipe;
  bool dry_requested = false;
  long long cycles_total = 0;
  long long cycles_in_execute = 0;
  std::string last_result;
  bool plc_up = false;
  plc::SlideState slide{};
  std::shared_ptr<Pending<Status>> slide_wait;
  int slide_target = -1;
  bool shutting_down = false;
  bool maintenance = false;
  Clock::time_point started = Clock::now();
  asio::steady_timer loop_timer{io};

  /// The event loop serves every device link (PLC polling and heartbeat, robot pings, the
  /// spindle's heartbeats both ways): a handler that holds it for a second makes those links
  /// time out although every device is fine. A timer due every 200 ms says when it came late.
  static constexpr milliseconds kLoopPeriod{200};
  static constexpr double kLoopLateWarnMs = 300.0;
  void watch_loop(Clock::time_point due) {
    loop_timer.expires_at(due);
    loop_timer.async_wait([weak = weak_from_this(), due](const boost::system::error_code& ec) {
      auto self = weak.lock();
      if (ec || !self || self->shutting_down) return;
      if (const double late_ms = ms_since(due); late_ms >= kLoopLateWarnMs)
        self->log->warn("the event loop was blocked for {:.0f} ms{}: PLC, robot and spindle links were not served "
                        "meanwhile (a heartbeat timeout shorter than that faults them)",
                        late_ms, self->cycle ? " (cycle " + self->cycle->summary.id + ", step " + self->cycle->step + ")" : "");
      self->watch_loop(Clock::now() + kLoopPeriod);
    });
  }

  // ------------------------------------------------------------------------------------------
  // Setup

  void setup() {
    for (const auto& r : cell.cell.recipes) {
      log->info("loading recipe {} ({})", r.plc_recipe_id, r.file.string());
      recipes[r.plc_recipe_id] = std::make_shared<const LoadedRecipe>(process::load_recipe(r.file));
    }
    if (!cell.calibration.file.empty()) calibration = config::load_calibration(cell.calibration.file);
    auto interrupted = records.open();
    if (!interrupted) throw UserError(interrupted.error().message);
    for (const auto& id : *interrupted) log->warn("cycle {} shows as INTERRUPTED (the daemon stopped during it)", id);

    auto weak = weak_from_this();
    plc_link = std::make_unique<plc::Link>(io.get_executor(), plc::LinkOptions::from_config(cell),
                                           [weak](const plc::Event& e) {
                                             if (auto self = weak.lock()) self->on_plc(e);
                                           });
    robot = std::make_unique<drivers::RobotLink>(io, drivers::RobotLinkOptions::from_config(cell.robot));
    robot->on_state([weak](drivers::RobotState s, const Error& cause) {
      if (auto self = weak.lock()) self->on_robot_state(s, cause);
    });
    can = drivers::make_spindle_transport(io, cell.spindle);
    spindle = std::make_unique<drivers::SpindleDrive>(io, can, drivers::SpindleOptions::from_config(cell.spindle));
    spindle->on_event([weak](const drivers::SpindleEvent& e) {
      if (auto self = weak.lock()) self->on_spindle(e);
    });
    (void)plc_link->set_state(machine.state());
    plc_link->start();
    robot->start();
    start_spindle();
    open_camera();
    publish_state();
    watch_loop(Clock::now() + kLoopPeriod);
  }

  void start_spindle() {
    if (spindle->status().configured) return;
    spindle->start([this, self = shared_from_this()](Status st) {
      if (!st) log->warn("spindle drive not ready: {} ({}); retried at the next Reset", st.error().message, st.error().code);
      else log->info("spindle drive configured");
    });
  }

  void open_camera() {
    if (camera_open->load()) return;
    asio::post(camera_thread, [this, self = shared_from_this()] {
      if (camera) return;
      try {
        auto o = drivers::camera_options(cell.camera);
        camera = std::make_shared<drivers::Camera>(o);
        camera_open->store(true);
        log->info("camera open: {}", camera->info().to_string());
      } catch (const std::exception& e) {
        log->warn("camera {} not available yet: {}", cell.camera.address, e.what());
      }
    });
  }

  // ------------------------------------------------------------------------------------------
  // PackML

  void publish_state() {
    const State s = machine.state();
    if (plc_link) (void)plc_link->set_state(s);
    std::string line = std::string(packml::name(s));
    if (cycle) line += ": cycle " + cycle->summary.id + (cycle->step.empty() ? "" : " (" + cycle->step + ")");
    if (fault) line += " - fault " + fault->describe();
    if (options.on_state) options.on_state(s, line);
  }

  void enter(State s) {
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
  asio::awaitable<void> act(State s, std::uint64_t gen) {
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

  Status command(Command c, const std::string& source) {
    if (c == Command::reset && fault) {
      log->info("Reset from {} clears fault {}", source, fault->describe());
      fault.reset();
    }
    auto next = machine.command(c);
    if (!next) {
      log->warn("{} from {} ignored: {}", packml::name(c), source, next.error().message);
      publish_state();
      return next.error();
    }
    log->info("PackML command {} from {}", packml::name(c), source);
    if ((c == Command::abort || c == Command::stop || c == Command::hold) && cycle && !cycle->fault)
      interrupt(Fault{c == Command::abort ? FaultCode::operator_abort : FaultCode::operator_abort,
                      std::string(packml::name(c)) + " commanded by " + source, cycle->step});
    if (c == Command::abort) quick_robot_stop();
    enter(*next);
    return {};
  }

  /// A fault: latch it, tell the PLC, end the cycle, Hold or Abort.
  void raise(Fault f) {
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

  void interrupt(const Fault& f) {
    if (!cycle || cycle->fault) return;
    cycle->fault = f;
    if (cycle->fault->step.empty()) cycle->fault->step = cycle->step;
    if (cycle->cancel) cycle->cancel();
  }

  /// Sends STOP at once when the robot may move (the first thing on any abort).
  void quick_robot_stop() {
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

  // ------------------------------------------------------------------------------------------
  // Awaiting callbacks with timeouts

  template <class T>
  // `start` by reference: see process_views on GCC 12 and temporaries in co_await expressions.
  asio::awaitable<std::optional<T>> await_op(Cycle* c, const std::function<void(std::function<void(T)>)>& start,
                                              milliseconds timeout) {
    auto p = std::make_shared<Pending<T>>(io);
    if (c != nullptr) c->cancel = [p] { p->cancel(); };
    start([p](T v) { p->set(std::move(v)); });
    if (!p->value && !(c != nullptr && c->fault)) {
      p->timer.expires_after(timeout);
      boost::system::error_code ec;
      co_await p->timer.async_wait(asio::redirect_error(asio::use_awaitable, ec));
    }
    if (c != nullptr) c->cancel = nullptr;
    co_return std::move(p->value);
  }

  asio::awaitable<void> sleep(milliseconds d) {
    asio::steady_timer t(io);
    t.expires_after(d);
    boost::system::error_code ec;
    co_await t.async_wait(asio::redirect_error(asio::use_awaitable, ec));
  }

  asio::awaitable<void> stop_robot() {
    if (!robot) co_return;
    const auto rs = robot->state();
    if (rs == drivers::RobotState::disconnected || rs == drivers::RobotState::connecting ||
        rs == drivers::RobotState::faulted || rs == drivers::RobotState::ready)
      co_return;
    // In state stopping (the quick STOP of an abort) this waits for that STOP's ACK.
    auto st = co_await await_op<Status>(nullptr, [this](std::function<void(Status)> done) { robot->stop(done); },
                                        milliseconds(cell.robot.reply_timeout_ms + 500));
    if (!st || !*st) log->warn("robot STOP not acknowledged: {}", st ? st->error().message : "timeout");
  }

  asio::awaitable<void> stop_robot_if_moving() {
    if (robot && (robot->state() == drivers::RobotState::running || robot->state() == drivers::RobotState::uploading))
      co_await stop_robot();
  }

  asio::awaitable<void> stop_spindle() {
    if (!spindle || !spindle->status().configured) co_return;
    if (spindle->status().fault) co_return;  // a faulted drive has no torque; never re-enabled here
    if (spindle->status().target_rpm == 0.0 && std::abs(spindle->status().velocity_rpm) < 1.0) co_return;
    auto st = co_await await_op<Status>(nullptr, [this](std::function<void(Status)> done) { spindle->stop(done); },
                                        milliseconds(cell.spindle.spin_up_timeout_ms + 1000));
    if (!st || !*st) log->warn("spindle stop: {}", st ? st->error().message : "timeout");
  }

  asio::awaitable<void> wait_cycle_gone() {
    for (int i = 0; i < 200 && cycle; ++i) co_await sleep(milliseconds(50));
  }

  /// Sends the slide home and waits for it, at most travel_timeout_ms; a faulted slide cannot
  /// move (it stays where it is until the PLC clears its fault), so that is not waited out.
  asio::awaitable<void> slide_home_best_effort() {
    if (slide.status == plc::SlideStatus::at_home) co_return;
    if (slide.status == plc::SlideStatus::fault) {
      log->warn("the slide is in fault at position {}: not sent home (the PLC must clear its fault)", slide.position);
      co_return;
    }
    (void)plc_link->command_slide(0);
    for (int i = 0; i < cell.slide.travel_timeout_ms / 50 && plc_up && slide.status != plc::SlideStatus::at_home &&
                    slide.status != plc::SlideStatus::fault;
         ++i)
      co_await sleep(milliseconds(50));
  }

  asio::awaitable<void> clear_devices() {
    if (robot && robot->state() == drivers::RobotState::faulted) {
      auto st = co_await await_op<Status>(nullptr, [this](std::function<void(Status)> d) { robot->reset(d); },
                                          milliseconds(cell.robot.reply_timeout_ms + 500));
      if (!st || !*st) log->warn("robot RESET: {}", st ? st->error().message : "timeout");
    }
    if (spindle && spindle->status().fault) {
      auto st = co_await await_op<Status>(nullptr, [this](std::function<void(Status)> d) { spindle->fault_reset(d); },
                                          milliseconds(3000));
      if (!st || !*st) log->warn("spindle fault reset: {}", st ? st->error().message : "timeout");
      else log->info("spindle fault reset");
    }
  }

  asio::awaitable<void> reset_devices() {
    co_await clear_devices();
    if (spindle && !spindle->status().configured) {
      auto st = co_await await_op<Status>(nullptr, [this](std::function<void(Status)> d) { spindle->start(d); },
                                          milliseconds(5000));
      if (!st || !*st) log->warn("spindle not ready: {}", st ? st->error().message : "timeout");
    }
    open_camera();
  }

  // ------------------------------------------------------------------------------------------
  // Device events

  void on_plc(const plc::Event& e) {
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
              } else if ((slide_target == 0 && ev.status == plc::SlideStatus::at_home) ||
                         (slide_target > 0 && ev.status == plc::SlideStatus::at_position &&
                          ev.position == slide_target)) {
                slide_wait->set(Status{});
              }
            }
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

  void on_robot_state(drivers::RobotState s, const Error& cause) {
    log->info("robot {}{}", drivers::to_string(s), cause.code.empty() ? "" : " (" + cause.code + ": " + cause.message + ")");
    if (!cycle || !cycle->motion) return;
    if (s == drivers::RobotState::disconnected)
      raise(Fault{FaultCode::robot_link_lost_moving, cause.code + ": " + cause.message, cycle->step});
    else if (s == drivers::RobotState::faulted)
      raise(Fault{FaultCode::robot_fault, cause.code + ": " + cause.message, cycle->step});
  }

  void on_spindle(const drivers::SpindleEvent& e) {
    if (e.kind == drivers::SpindleEvent::Kind::fault) {
      log->error("spindle fault: {}", e.message);
      if (cycle || machine.state() == State::execute)
        raise(Fault{FaultCode::spindle_fault, e.message, cycle ? cycle->step : ""});
    } else if (e.kind != drivers::SpindleEvent::Kind::state_changed) {
      log->info("spindle {}: {}", drivers::to_string(e.kind), e.message);
    }
  }

  // ------------------------------------------------------------------------------------------
  // The cycle

  void maybe_start_cycle() {
    if (cycle || shutting_down) return;
    if (dry_requested) {
      dry_requested = false;
      start_cycle(pending_recipe.value_or(cell.cell.recipes.empty() ? 0 : cell.cell.recipes.front().plc_recipe_id),
                  true, false);
      return;
    }
    if (machine.state() != State::execute || !pending_recipe) return;
    if (options.max_cycles > 0 && cycles_in_execute >= options.max_cycles) return;
    const int recipe_id = *pending_recipe;
    pending_recipe.reset();
    plc_link->accept_cycle();
    start_cycle(recipe_id, false, true);
  }

  void start_cycle(int recipe_id, bool dry, bool from_plc) {
    auto c = std::make_shared<Cycle>();
    c->recipe_id = recipe_id;
    c->dry = dry;
    if (auto it = recipes.find(recipe_id); it != recipes.end()) c->recipe = it->second;
    auto begun = records.begin(recipe_id, c->recipe ? c->recipe->recipe.id : "", dry);
    if (!begun) {
      raise(Fault{FaultCode::records_failed, begun.error().message, "begin"});
      return;
    }
    c->summary = *begun;
    if (!records.warning().empty()) c->warnings.push_back("records: " + records.warning());
    cycle = c;
    ++cycles_total;
    if (from_plc) ++cycles_in_execute;
    log->info("cycle {} started (recipe {}{})", c->summary.id, recipe_id, dry ? ", dry" : "");
    publish_state();
    asio::co_spawn(
        io,
        [self = shared_from_this(), c]() -> asio::awaitable<void> {
          try {
            co_await self->run_cycle(*c);
          } catch (const std::exception& e) {
            if (!c->fault) self->raise(Fault{FaultCode::internal, e.what(), c->step});
          }
          try {
            self->finish_cycle(c);
          } catch (const std::exception& e) {
            self->log->error("cycle {}: ending its record failed: {}", c->summary.id, e.what());
            if (self->cycle == c) self->cycle.reset();
          }
        },
        asio::detached);
  }

  bool fail(Cycle& c, Fault f) {
    if (!c.fault) raise(std::move(f));
    return false;
  }

  bool fail(Cycle& c, const Error& e, FaultCode fallback) {
    return fail(c, fault_from_error(e, c.step, c.motion, fallback));
  }

  milliseconds margin() const { return options.step_margin; }

  asio::awaitable<bool> slide_to(Cycle& c, int target) {
    c.begin(target == 0 ? "slide home" : "slide to " + std::to_string(target));
    publish_state();
    if (!plc_up) co_return fail(c, Fault{FaultCode::plc_link_lost, "the PLC link is down", c.step});
    // A slide already in fault sends no new state when commanded: without this the cycle would
    // wait out travel_timeout_ms and report a timeout (test Fettled.B_EveryFaultEndsInItsStateAndTheCellRecovers,
    // "slide faulted before the cycle").
    if (slide.status == plc::SlideStatus::fault)
      co_return fail(c, Fault{FaultCode::slide_fault, "the PLC reports a slide fault (before the slide was commanded)", c.step});
    auto p = std::make_shared<Pending<Status>>(io);
    slide_wait = p;
    slide_target = target;
    if (auto st = plc_link->command_slide(target); !st) co_return fail(c, st.error(), FaultCode::slide_fault);
    c.cancel = [p] { p->cancel(); };
    if (!c.fault) {
      p->timer.expires_after(milliseconds(cell.slide.travel_timeout_ms));
      boost::system::error_code ec;
      co_await p->timer.async_wait(asio::redirect_error(asio::use_awaitable, ec));
    }
    c.cancel = nullptr;
    slide_wait.reset();
    if (c.fault) co_return false;
    if (!p->value)
      co_return fail(c, Fault{FaultCode::slide_timeout,
                              "the slide did not reach " + (target == 0 ? std::string("home") : "photo position " + std::to_string(target)) +
                                  " within " + std::to_string(cell.slide.travel_timeout_ms) + " ms ([slide] travel_timeout_ms)",
                              c.step});
    if (!*p->value) co_return fail(c, Fault{FaultCode::slide_fault, p->value->error().message, c.step});
    c.end();
    co_return true;
  }

  Transform T_base_camera_at(double slide_mm) const {
    Transform T = calibration && calibration->T_base_camera ? *calibration->T_base_camera : Transform::Identity();
    // The calibration holds the camera pose with the slide at 0 mm; the slide moves along base +x.
    T.pretranslate(Vec3(slide_mm, 0.0, 0.0));
    return T;
  }

  asio::awaitable<bool> capture(Cycle& c, int position, std::vector<View>& out, const std::string& stem) {
    c.begin("capture " + std::to_string(position));
    publish_state();
    const auto timeout =
        milliseconds(cell.camera.frame_timeout_ms * (cell.camera.retries + 1)) + margin() + milliseconds(10000);
    auto r = co_await await_op<Result<drivers::CameraCapture>>(
        &c,
        [this](std::function<void(Result<drivers::CameraCapture>)> done) {
          asio::post(camera_thread, [this, self = shared_from_this(), done] {
            Result<drivers::CameraCapture> result = Error{"camera.unavailable", "not opened"};
            try {
              if (!camera) {
                camera = std::make_shared<drivers::Camera>(drivers::camera_options(cell.camera));
                camera_open->store(true);
              }
              result = camera->capture();
            } catch (const std::exception& e) {
              result = Error{"camera.unavailable", "camera " + cell.camera.address + ": " + e.what()};
            }
            asio::post(io, [done, result = std::move(result)]() mutable { done(std::move(result)); });
          });
        },
        timeout);
    if (c.fault) co_return false;
    if (!r) co_return fail(c, Fault{FaultCode::camera_timeout, "no capture within " + std::to_string(timeout.count()) + " ms", c.step});
    if (!*r) co_return fail(c, r->error(), FaultCode::camera_unavailable);
    const double slide_mm = cell.slide.photo_positions_mm.at(static_cast<std::size_t>(position - 1));
    View v;
    v.cloud = std::move((*r)->cloud);
    v.slide_position_mm = slide_mm;
    v.T_base_camera = T_base_camera_at(slide_mm);
    log->info("capture {}: {} valid points, {} attempt(s), {:.0f} ms wait", position, v.cloud.count_valid(),
              (*r)->stats.attempts, (*r)->stats.wait_ms);
    c.end();
    if (options.keep_captures) {
      const auto file = c.summary.dir / (stem + "_" + std::to_string(position) + ".ply");
      auto cloud = std::make_shared<OrganizedCloud>(v.cloud);
      asio::post(workers, [file, cloud, this, self = shared_from_this()] {
        auto st = write_via_temp(file, [&](const fs::path& tmp) { return drivers::write_ply(tmp, *cloud); });
        if (!st) log->warn("record {}: {}", file.string(), st.error().message);
      });
      c.files.push_back(file.filename().string());
    }
    out.push_back(std::move(v));
    co_return true;
  }

  asio::awaitable<bool> scan(Cycle& c, std::vector<View>& views, const std::string& stem) {
    views.clear();
    const int n = static_cast<int>(cell.slide.photo_positions_mm.size());
    for (int pos = 1; pos <= n; ++pos) {
      if (!co_await slide_to(c, pos)) co_return false;
      if (!co_await capture(c, pos, views, stem)) co_return false;
    }
    co_return co_await slide_to(c, 0);
  }

  /// A failed process(): a cell fault, or with `part_error` an error about the part itself
  /// (vision.* or planning.*) returned there (see process_views).
  void report_process_error(Cycle& c, const Error& e, std::string* part_error) {
    const bool planning = e.code.rfind("planning", 0) == 0;
    if (part_error != nullptr && (planning || e.code.rfind("vision", 0) == 0)) {
      *part_error = e.message + " [" + e.code + "]";
      c.end();
      return;
    }
    fail(c, e, planning ? FaultCode::plan_failed : FaultCode::vision_failed);
  }

  // GCC 12 destroys a temporary with a non-trivial destructor in a co_await expression twice:
  // a lambda capturing shared_ptrs and ProcessOptions by value, passed straight into
  // await_op, double-frees the region names at the first re-grind and can drop the views'
  // refcount early.
  // Everything non-trivial handed to await_op is therefore a named local of this frame.
  /// Vision + planning in the worker pool. With `part_error`, an error about the part itself
  /// (vision.* or planning.*: it cannot be located or planned) is returned there instead of
  /// faulting the cell: a re-grind that cannot be planned makes the part NOK, not the cell Held.
  /// `name` is a literal: no temporary with a destructor in the callers' co_await expressions
  /// (GCC 12 destroys those twice, see above).
  asio::awaitable<std::optional<ProcessOutput>> process_views(Cycle& c, const std::vector<View>& views,
                                                              const ProcessOptions& process_options, const char* name,
                                                              std::string* part_error = nullptr) {
    const ProcessOptions po = process_options;
    c.begin(name);
    publish_state();
    auto recipe = c.recipe;
    auto views_copy = std::make_shared<const std::vector<View>>(views);
    const std::function<void(std::function<void(Result<ProcessOutput>)>)> start =
        [this, recipe, views_copy, po](std::function<void(Result<ProcessOutput>)> done) {
          asio::post(workers, [this, self = shared_from_this(), recipe, views_copy, po, done] {
            Result<ProcessOutput> out = Error{"pipeline.internal", "not run"};
            try {
              out = process::process(*recipe, cell, *views_copy, po);
            } catch (const std::exception& e) {
              out = Error{"pipeline.internal", e.what()};
            }
            asio::post(io, [done, out = std::move(out)]() mutable { done(std::move(out)); });
          });
        };
    auto r = co_await await_op<Result<ProcessOutput>>(&c, start, milliseconds(180000));
    if (c.fault) co_return std::nullopt;
    if (!r) {
      fail(c, Fault{FaultCode::step_timeout, "processing took longer than 180 s", c.step});
      co_return std::nullopt;
    }
    if (!*r) {
      report_process_error(c, r->error(), part_error);
      co_return std::nullopt;
    }
    c.end();
    co_return std::move(r->value());
  }

  asio::awaitable<std::optional<VerificationResult>> verify_views(Cycle& c, const std::vector<View>& views) {
    c.begin("verify");
    publish_state();
    auto recipe = c.recipe;
    auto views_copy = std::make_shared<const std::vector<View>>(views);
    // what the robot ran in this cycle: the verification looks for gouges wherever it went
    auto ground = std::make_shared<std::vector<Trajectory>>();
    if (c.processed) ground->push_back(c.processed->trajectory);
    for (const auto& r : c.regrinds) ground->push_back(r.trajectory);
    // named, not a temporary in the co_await expression (see process_views)
    const std::function<void(std::function<void(Result<VerificationResult>)>)> start =
        [this, recipe, views_copy, ground](std::function<void(Result<VerificationResult>)> done) {
          asio::post(workers, [this, self = shared_from_this(), recipe, views_copy, ground, done] {
            Result<VerificationResult> out = Error{"pipeline.internal", "not run"};
            try {
              out = process::verify(*recipe, cell, *views_copy, *ground);
            } catch (const std::exception& e) {
              out = Error{"pipeline.internal", e.what()};
            }
            asio::post(io, [done, out = std::move(out)]() mutable { done(std::move(out)); });
          });
        };
    auto r = co_await await_op<Result<VerificationResult>>(&c, start, milliseconds(180000));
    if (c.fault) co_return std::nullopt;
    if (!r) {
      fail(c, Fault{FaultCode::step_timeout, "verification took longer than 180 s", c.step});
      co_return std::nullopt;
    }
    if (!*r) {
      fail(c, r->error(), FaultCode::vision_failed);
      co_return std::nullopt;
    }
    c.end();
    co_return std::move(r->value());
  }

  /// validate -> upload -> spindle up -> run -> spindle down.
  asio::awaitable<bool> grind(Cycle& c, const Trajectory& trajectory, const std::string& suffix) {
    c.begin("validate" + suffix);
    if (trajectory.points.empty()) {
      c.end();
      co_return true;
    }
    // The planner validated it (gouges included); this is the last check before the robot,
    // against the cell's [safety] limits, whatever produced the trajectory.
    if (const auto limits = planning::validate_limits(trajectory, planning::PlannerSettings::from(cell.safety)); !limits)
      co_return fail(c, limits.error(), FaultCode::plan_failed);
    c.end();
    double rpm = 0.0;  // the spindle runs at the highest speed the trajectory asks for
    for (const auto& p : trajectory.points) rpm = std::max(rpm, p.spindle_rpm);

    if (robot->state() != drivers::RobotState::ready && robot->state() != drivers::RobotState::uploaded)
      co_return fail(c, Fault{FaultCode::robot_unavailable,
                              "robot " + std::string(drivers::to_string(robot->state())) + " at " + cell.robot.address +
                                  ":" + std::to_string(cell.robot.port),
                              "upload" + suffix});
    c.begin("upload" + suffix);
    publish_state();
    c.motion = true;  // an upload can be followed by motion; a link loss from here on is safety-relevant
    const auto chunks = static_cast<int>(trajectory.points.size()) / std::max(1, cell.robot.chunk_points) + 3;
    auto up = co_await await_op<Status>(
        &c, [this, &trajectory](std::function<void(Status)> d) { robot->upload(trajectory, d); },
        milliseconds(cell.robot.reply_timeout_ms) * chunks + margin());
    if (c.fault) co_return false;
    if (!up) co_return fail(c, Fault{FaultCode::step_timeout, "trajectory upload timed out", c.step});
    if (!*up) co_return fail(c, up->error(), FaultCode::robot_unavailable);
    c.end();

    c.begin("spindle up" + suffix);
    publish_state();
    auto sp = co_await await_op<Status>(
        &c, [this, rpm](std::function<void(Status)> d) { spindle->spin_up(rpm, d); },
        milliseconds(cell.spindle.spin_up_timeout_ms) + margin());
    if (c.fault) co_return false;
    if (!sp) co_return fail(c, Fault{FaultCode::spindle_timeout, "spin-up timed out", c.step});
    if (!*sp) co_return fail(c, sp->error(), FaultCode::spindle_fault);
    c.end();

    c.begin("run" + suffix);
    publish_state();
    auto run = co_await await_op<Status>(
        &c, [this](std::function<void(Status)> d) { robot->run(d); },
        milliseconds(cell.robot.run_timeout_ms) + margin());
    if (c.fault) co_return false;
    if (!run) co_return fail(c, Fault{FaultCode::robot_timeout, "no DONE within the run timeout", c.step});
    if (!*run) co_return fail(c, run->error(), FaultCode::robot_fault);
    c.end();

    c.begin("spindle down" + suffix);
    publish_state();
    auto down = co_await await_op<Status>(
        &c, [this](std::function<void(Status)> d) { spindle->stop(d); },
        milliseconds(cell.spindle.spin_up_timeout_ms) + margin());
    if (c.fault) co_return false;
    if (!down) co_return fail(c, Fault{FaultCode::spindle_timeout, "spindle stop timed out", c.step});
    if (!*down) co_return fail(c, down->error(), FaultCode::spindle_fault);
    c.motion = false;
    c.end();
    co_return true;
  }

  asio::awaitable<void> run_cycle(Cycle& c) {
    if (!c.recipe) {
      fail(c, Fault{FaultCode::unknown_recipe,
                    "recipe id " + std::to_string(c.recipe_id) + " is not in [[cell.recipes]] of " + cell.source.string(),
                    "recipe"});
      co_return;
    }
    if (!co_await scan(c, c.views, "capture")) co_return;
    const ProcessOptions all_regions;
    auto processed = co_await process_views(c, c.views, all_regions, "process");
    if (!processed) co_return;
    c.processed = std::move(processed);
    co_await write_process_outputs(c, *c.processed, "");
    if (c.dry) {
      c.result = "OK";
      co_return;
    }
    if (!co_await grind(c, c.processed->trajectory, "")) co_return;
    if (!cell.cell.verification_scan) {
      c.result = "OK";
      co_return;
    }
    std::vector<View> rescan;
    if (!co_await scan(c, rescan, "rescan")) co_return;
    auto v = co_await verify_views(c, rescan);
    if (!v) co_return;
    log_verification(c, *v, "verification");
    if (v->verdict == Verdict::regrind) {
      ProcessOptions po;
      po.regions = v->regrind_regions();
      log->info("cycle {}: re-grind of {} region(s): {}", c.summary.id, po.regions.size(), fmt::join(po.regions, ", "));
      c.first_verification = std::move(v);
      std::string not_planned;
      auto again = co_await process_views(c, rescan, po, "process regrind", &not_planned);
      // The part stays NOK on its first verification (the cell carries on with the next part)
      // when the re-grind cannot be planned, or leaves nothing to plan: what is left lies below
      // the planner's excess threshold or the camera barely sees it, so a second pass would
      // grind air and a second re-scan would say the same.
      std::string skipped;
      if (!again && !not_planned.empty())
        skipped = "re-grind not possible: " + not_planned;
      else if (again && again->trajectory.points.empty())
        skipped = fmt::format("re-grind skipped: the re-scan leaves nothing above the excess threshold to plan in {}",
                              fmt::join(po.regions, ", "));
      if (!again && skipped.empty()) co_return;  // a cell fault
      if (again) co_await write_process_outputs(c, *again, "regrind_");
      if (!skipped.empty()) {
        skipped += "; the part is NOK on its first verification";
        log->warn("cycle {}: {}", c.summary.id, skipped);
        c.warnings.push_back(skipped);
        if (again) c.regrinds.push_back(std::move(*again));
        c.verification = std::move(c.first_verification);
        c.first_verification.reset();
        c.verification->verdict = Verdict::nok;
        c.result = "NOK";
        co_return;
      }
      if (!co_await grind(c, again->trajectory, " regrind")) co_return;
      c.regrinds.push_back(std::move(*again));
      if (!co_await scan(c, rescan, "rescan2")) co_return;
      v = co_await verify_views(c, rescan);
      if (!v) co_return;
      log_verification(c, *v, "verification after the re-grind");
    }
    c.verification = std::move(v);
    c.result = c.verification->verdict == Verdict::ok ? "OK" : "NOK";
  }

  /// One line per region: what the maintenance engineer needs to see why a part is NOK.
  void log_verification(const Cycle& c, const VerificationResult& v, const char* what) {
    for (const auto& r : v.regions) {
      const auto line = fmt::format("cycle {}: {} of '{}': {} ({} ROI points, {:.2f} % > 0.3 mm, {:.2f} % > 0.5 mm, "
                                    "max {:.2f} mm above / {:.2f} mm below the template){}{}",
                                    c.summary.id, what, r.name, to_string(r.verdict), r.roi_points, r.share_over_0_3_pct,
                                    r.share_over_0_5_pct, r.max_above_mm, r.max_below_mm, r.reason.empty() ? "" : ": ",
                                    r.reason);
      if (r.verdict == Verdict::ok) log->info("{}", line);
      else log->warn("{}", line);
    }
    if (v.worst_gouge) log->warn("cycle {}: {}: NOK: {}", c.summary.id, what, v.worst_gouge->describe());
  }

  /// The files a cycle's processing made for its record (trajectory, preview, fused cloud),
  /// written on a thread of their own: rendering and writing them takes 0.1-0.2 s under ASan on
  /// an idle machine, and the event loop, which serves every device link's heartbeat, must not
  /// wait for a busy disk. One thread, not the worker pool: each worker's malloc arena would
  /// take the files' memory peak once, and fettled's RSS would step up 50 MB over a soak.
  /// The writer gets its own copy of what it writes: nothing of the cycle is shared.
  asio::awaitable<void> write_process_outputs(Cycle& c, const ProcessOutput& out, const char* prefix_text) {
    struct Written {
      std::vector<std::string> files, warnings;
    };
    const std::string prefix = prefix_text;
    const fs::path dir = c.summary.dir;
    auto copy = std::make_shared<const ProcessOutput>(out);
    const std::function<void(std::function<void(Written)>)> start = [this, dir, prefix, copy](std::function<void(Written)> done) {
      asio::post(record_writer, [this, self = shared_from_this(), dir, prefix, copy, done]() mutable {
        Written w;
        const fs::path tmp = dir / ("." + prefix + "outputs.tmp");
        std::error_code ec;
        fs::create_directories(tmp, ec);
        if (auto st = process::write_outputs(tmp, *copy); !st) w.warnings.push_back("outputs: " + st.error().message);
        for (fs::directory_iterator it(tmp, ec), end; !ec && it != end; it.increment(ec)) {
          const auto name = prefix + it->path().filename().string();
          fs::rename(it->path(), dir / name, ec);
          if (!ec) w.files.push_back(name);
        }
        fs::remove_all(tmp, ec);
        const auto& insp = copy->inspection;
        const auto name = prefix + "fused_part.ply";
        if (auto st = write_scalar_ply(dir / name, insp.scene_part.points, insp.deviation_mm, "deviation_mm"); st)
          w.files.push_back(name);
        copy.reset();
        ::malloc_trim(0);  // the copy and the encoders' buffers (about 55 MB) back to the system, not kept in an arena
        asio::post(io, [done, w = std::move(w)]() mutable { done(std::move(w)); });
      });
    };
    // Not cancelled by a fault: the files are short work, and the record lists what was written.
    auto w = co_await await_op<Written>(nullptr, start, milliseconds(60000));
    if (!w) {
      c.warnings.push_back("outputs: not written within 60 s");
      co_return;
    }
    for (auto& f : w->files) c.files.push_back(std::move(f));
    for (auto& m : w->warnings) c.warnings.push_back(std::move(m));
  }

  json verification_json(const VerificationResult& v, Cycle& c, const std::string& prefix) {
    json regions = json::array();
    for (const auto& r : v.regions) {
      regions.push_back({{"name", r.name},
                         {"roi_points", r.roi_points},
                         {"over_0_3", r.over_0_3},
                         {"over_0_4", r.over_0_4},
                         {"over_0_5", r.over_0_5},
                         {"share_over_0_3_pct", r.share_over_0_3_pct},
                         {"share_over_0_4_pct", r.share_over_0_4_pct},
                         {"share_over_0_5_pct", r.share_over_0_5_pct},
                         {"max_residual_mm", r.max_residual_mm},
                         {"max_above_mm", r.max_above_mm},
                         {"max_below_mm", r.max_below_mm},
                         {"verdict", to_string(r.verdict)},
                         {"reason", r.reason}});
      const auto name = prefix + "deviation_" + safe_name(r.name) + ".ply";
      if (write_scalar_ply(c.summary.dir / name, r.roi_points_part, r.residual_mm, "deviation_mm"))
        c.files.push_back(name);
    }
    json gouge = nullptr;
    if (v.worst_gouge)
      gouge = {{"depth_mm", v.worst_gouge->depth_mm},
               {"at_part_mm", {v.worst_gouge->at_part.x(), v.worst_gouge->at_part.y(), v.worst_gouge->at_part.z()}},
               {"region", v.worst_gouge->region},
               {"in_roi", v.worst_gouge->in_roi},
               {"points", v.worst_gouge->points},
               {"reason", v.worst_gouge->describe()}};
    return {{"verdict", to_string(v.verdict)},
            {"regions", regions},
            {"worst_gouge", gouge},
            {"deepest_below_template_mm", v.deepest_below_mm},
            {"footprint_points", v.footprint_points},
            {"timings", timings_json(v.timings)}};
  }

  json process_json(const ProcessOutput& p) {
    json regions = json::array();
    for (const auto& r : p.regions)
      regions.push_back({{"name", r.name},
                         {"scene_points", r.scene_points},
                         {"fitness", r.fitness},
                         {"rmse_mm", r.rmse_mm},
                         {"excess_points", r.excess_points},
                         {"excess_volume_mm3", r.excess_volume_mm3},
                         {"excess_max_height_mm", r.excess_max_height_mm},
                         {"trajectory_points", r.trajectory_points},
                         {"segments", r.segments},
                         {"plan_ms", r.plan_ms},
                         // left: unreachable (the tool cannot get there without coming nearer
                         // the template than its allowance): its height, where, the fin's length
                         {"material_left_mm", r.material_left_mm},
                         {"material_left_at_mm", {r.material_left_at.x(), r.material_left_at.y(), r.material_left_at.z()}},
                         {"material_left_length_mm", r.material_left_length_mm}});
    const auto& t = p.T_base_part.translation();
    return {{"regions", regions},
            {"trajectory_points", p.trajectory.points.size()},
            {"T_base_part_position_mm", {t.x(), t.y(), t.z()}},
            {"timings", timings_json(p.timings)},
            {"total_ms", p.total_ms}};
  }

  void finish_cycle(const std::shared_ptr<Cycle>& cp) {
    Cycle& c = *cp;
    c.end(c.fault.has_value());
    auto& s = c.summary;
    s.duration_s = ms_since(c.t0) / 1000.0;
    if (c.fault) {
      s.result = c.fault->reaction() == FaultReaction::abort ? "ABORTED" : "FAULT";
      s.fault_code = c.fault->number();
      s.fault = c.fault->describe();
    } else {
      s.result = c.result.empty() ? "NOK" : c.result;
    }
    if (c.verification) {
      // `fettle cycles` shows them as columns: the worst gouge (0: none; `gouge` says where)
      // and the deepest confirmed place below the template wherever the tool went
      const auto& g = c.verification->worst_gouge;
      s.worst_gouge_mm = g ? g->depth_mm : 0.0;
      if (g) s.gouge = g->describe();
      s.deepest_below_template_mm = c.verification->deepest_below_mm;
    }
    json report{{"cycle", s.to_json()},
                {"result", s.result},
                {"dry", c.dry},
                {"steps", c.steps},
                {"duration_s", s.duration_s},
                {"cell", cell.cell.name},
                {"config", cell.source.string()},
                {"verification_scan", cell.cell.verification_scan},
                {"views", c.views.size()},
                {"warnings", c.warnings}};
    if (c.fault)
      report["fault"] = {{"code", c.fault->number()},
                         {"id", c.fault->id()},
                         {"reaction", to_string(c.fault->reaction())},
                         {"step", c.fault->step},
                         {"message", c.fault->message}};
    else
      report["fault"] = nullptr;
    if (c.recipe)
      report["recipe"] = {{"plc_recipe_id", c.recipe_id},
                          {"part_id", c.recipe->recipe.id},
                          {"file", c.recipe->recipe.source.string()},
                          {"golden", c.recipe->golden_identity}};
    if (calibration) {
      const auto cal_id = config::calibration_identity(*calibration);
      report["calibration"] = {
          {"id", cal_id.id}, {"date", cal_id.date}, {"sha256", cal_id.sha256}, {"file", cal_id.file.string()}};
    }
    if (c.processed) report["process"] = process_json(*c.processed);
    if (!c.regrinds.empty()) report["regrind_process"] = process_json(c.regrinds.front());
    report["regrinds"] = c.regrinds.size();
    if (c.first_verification) report["first_verification"] = verification_json(*c.first_verification, c, "first_");
    if (c.verification) report["verification"] = verification_json(*c.verification, c, "");
    report["files"] = c.files;
    if (auto st = Records::write_file(s, "report.json", report.dump(2)); !st)
      log->error("cycle {}: report.json: {}", s.id, st.error().message);
    json extra{{"steps", c.steps}};
    if (c.verification) {
      json shares = json::array();
      for (const auto& r : c.verification->regions)
        shares.push_back({{"name", r.name},
                          {"share_over_0_3_pct", r.share_over_0_3_pct},
                          {"share_over_0_5_pct", r.share_over_0_5_pct},
                          {"verdict", to_string(r.verdict)}});
      extra["regions"] = shares;
    }
    if (auto st = records.end(s, extra); !st) log->error("cycle {}: journal: {}", s.id, st.error().message);
    last_result = s.result;
    log->info("cycle {} ended: {} in {:.1f} s{}", s.id, s.result, s.duration_s, c.fault ? " - " + c.fault->describe() : "");
    if (!c.fault && !c.dry && plc_link)
      (void)plc_link->report_result(s.result == "OK" ? plc::CycleResult::ok : plc::CycleResult::nok);
    if (cycle == cp) cycle.reset();
    publish_state();
    if (machine.state() == State::execute && options.max_cycles > 0 && cycles_in_execute >= options.max_cycles) {
      log->info("{} cycle(s) done: Execute completes", cycles_in_execute);
      if (auto next = machine.state_complete(); next) enter(*next);
      return;
    }
    asio::post(io, [self = shared_from_this()] { self->maybe_start_cycle(); });
  }

  // ------------------------------------------------------------------------------------------

  RuntimeStatus snapshot() const {
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

  void shutdown(std::function<void()> done) {
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
          self->log->info("shutdown: robot {}, spindle at {:.0f} rpm", self->robot ? drivers::to_string(self->robot->state()) : "not configured",
                          self->spindle ? self->spindle->status().velocity_rpm : 0.0);
          if (self->plc_link) self->plc_link->stop();
          if (self->robot) self->robot->shutdown();
          self->workers.stop();
          self->camera_thread.stop();
          self->record_writer.stop();
          if (done) done();
        },
        asio::detached);
  }
};

// ---------------------------------------------------------------------------------------------

Runtime::Runtime(asio::io_context& io, config::CellConfig cell, RuntimeOptions options)
    : impl_(std::make_shared<Impl>(io, std::move(cell), std::move(options))) {}

Runtime::~Runtime() {
  if (impl_->plc_link) impl_->plc_link->stop();
  impl_->workers.join();
  impl_->camera_thread.join();
  impl_->record_writer.join();
}

void Runtime::start() { impl_->setup(); }
void Runtime::shutdown(std::function<void()> done) { impl_->shutdown(std::move(done)); }
Status Runtime::command(Command c, const std::string& source) { return impl_->command(c, source); }
RuntimeStatus Runtime::status_snapshot() const { return impl_->snapshot(); }
State Runtime::state() const { return impl_->machine.state(); }

json Runtime::status() {
  const auto s = impl_->snapshot();
  json j{{"state", packml::name(s.state)},
         {"state_code", packml::code(s.state)},
         {"cycle_id", s.cycle_id.empty() ? json(nullptr) : json(s.cycle_id)},
         {"step", s.step},
         {"cycles_total", s.cycles_total},
         {"last_result", s.last_result},
         {"uptime_s", ms_since(impl_->started) / 1000.0},
         {"plc_up", s.plc_up},
         {"robot", s.robot_state},
         {"spindle_configured", s.spindle_configured},
         {"records", impl_->records.state_dir().string()},
         {"records_warning", impl_->records.warning().empty() ? json(nullptr) : json(impl_->records.warning())}};
#ifdef FETTLE_VERSION
  j["version"] = FETTLE_VERSION;
#endif
  if (s.fault)
    j["fault"] = {{"code", s.fault->number()}, {"id", s.fault->id()}, {"message", s.fault->describe()}};
  else
    j["fault"] = nullptr;
  return j;
}

Result<json> Runtime::last_cycle() {
  auto l = impl_->records.last();
  if (!l) return json(nullptr);
  return l->to_json();
}

Result<json> Runtime::cycles(std::size_t limit) {
  json a = json::array();
  for (const auto& c : impl_->records.cycles(limit)) a.push_back(c.to_json());
  return a;
}

namespace {
Result<json> command_reply(Runtime& rt, Command c) {
  if (auto st = rt.command(c, "control socket"); !st) return st.error();
  return json{{"state", packml::name(rt.state())}};
}
}  // namespace

Result<json> Runtime::reset() { return command_reply(*this, Command::reset); }
Result<json> Runtime::hold() { return command_reply(*this, Command::hold); }
Result<json> Runtime::unhold() { return command_reply(*this, Command::unhold); }

Result<json> Runtime::dry_cycle() {
  auto& i = *impl_;
  if (i.cycle) return Error{"fettled.busy", "cycle " + i.cycle->summary.id + " is running; try again when it ends"};
  const State s = i.machine.state();
  if (s != State::idle && s != State::stopped && s != State::execute && s != State::held)
    return Error{"fettled.state", "a dry cycle needs Idle, Stopped, Held or Execute without a cycle; the cell is " +
                                      std::string(packml::name(s))};
  i.dry_requested = true;
  i.maybe_start_cycle();
  return json{{"cycle_id", i.cycle ? json(i.cycle->summary.id) : json(nullptr)}};
}

Status Runtime::maintenance_changing(bool on) {
  if (on && impl_->cycle && !impl_->cycle->dry)
    return Error{"fettled.busy", "a production cycle is running; enter maintenance mode when it ended"};
  impl_->maintenance = on;
  return {};
}

}  // namespace fettle::daemon
