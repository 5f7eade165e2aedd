#pragma once
// Runtime::Impl: what fettled's event loop owns, and the cycle it runs (runtime.hpp). Its
// member functions live in three files, one per seam of the runtime:
//   cell_supervisor.cpp  setup, the PackML machine, faults, device events, shutdown
//   cycle_runner.cpp     one cycle's steps: slide, capture, process, validate, upload, grind,
//                        verification scan, re-grind
//   cycle_record.cpp     the cycle's record: output files, report.json, the journal's end line
// runtime.cpp holds Runtime's public functions. Every member runs on the loop thread unless
// its comment names another (the camera thread, the worker pool, the record writer).
#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include <boost/asio/awaitable.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/redirect_error.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/thread_pool.hpp>
#include <boost/asio/use_awaitable.hpp>

#include "fettle/config/calibration.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/daemon/packml_machine.hpp"
#include "fettle/daemon/processing.hpp"
#include "fettle/daemon/records.hpp"
#include "fettle/daemon/runtime.hpp"
#include "fettle/drivers/camera.hpp"
#include "fettle/drivers/plc_link.hpp"
#include "fettle/drivers/robot_link.hpp"
#include "fettle/drivers/spindle.hpp"
#include "fettle/process/compensation.hpp"
#include "fettle/process/pipeline.hpp"

namespace fettle::daemon {

namespace asio = boost::asio;
namespace fs = std::filesystem;
using process::LoadedRecipe;
using process::ProcessOptions;
using process::ProcessOutput;
using process::StepTiming;
using process::Verdict;
using process::VerificationResult;
using process::View;
namespace plc = drivers::plc;
using nlohmann::json;
using packml::Command;
using packml::State;
using Clock = std::chrono::steady_clock;
using std::chrono::milliseconds;

inline double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

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

/// Runs `writer(tmp)` then renames tmp onto `path` (after fsync): atomic for writers that
/// write plain files (cycle_record.cpp).
Status write_via_temp(const fs::path& path, const std::function<Status(const fs::path&)>& writer);

/// One cycle as it runs, and what its record is made of.
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
  /// [compensation]: the bias this cycle's paths were commanded with, and what its first
  /// verification measured of where the tool cut (report.json "compensation").
  Vec3 cell_bias_mm = Vec3::Zero();
  /// The regions commanded with an offset of their own (process::CellBias::region_placement).
  std::map<std::string, process::RegionPlacement> region_placement;
  /// What every path of the cycle keeps from the template: the cell's stated accuracies less
  /// what it has learned (process::placement_uncertainty; report.json "placement_bound_mm").
  process::PlacementUncertainty placement;
  std::optional<Result<process::CutOffset>> cut_offset;
  /// [compensation]: each wheel's wear as predicted when the cycle was planned (its paths were
  /// planned with the wheels that much smaller; report.json "compensation" "tool_wear_mm").
  process::ToolWearMm tool_wear_mm;
  process::ToolWearMm tool_wear_most_mm;
  /// [compensation]: the iron each wheel removed in this cycle as the latest verification shows
  /// it (process::measure_removed_cm3), and what of it the wheels' wear has counted.
  std::map<std::string, double> removed_seen_cm3;
  std::map<std::string, double> removed_counted_cm3;
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
        processing(options.processing ? options.processing : std::make_shared<const Processing>(Processing::pipeline())),
        log(log::get("fettled")) {}

  asio::io_context& io;
  config::CellConfig cell;
  RuntimeOptions options;
  asio::thread_pool workers;
  asio::thread_pool camera_thread;
  asio::thread_pool record_writer;  ///< a cycle's output files (one thread: its memory peak is reached once)
  Records records;
  std::shared_ptr<const Processing> processing;
  std::shared_ptr<spdlog::logger> log;

  std::map<int, std::shared_ptr<const LoadedRecipe>> recipes;
  std::optional<config::CalibrationFile> calibration;
  process::CellBias cell_bias;  ///< [compensation]: the cell's learned bias (docs/compensation.md)

  // The devices, only through their interfaces (device.hpp), made by RuntimeOptions' makers
  // or as the cell file says.
  std::unique_ptr<drivers::PlcDevice> plc_link;
  std::unique_ptr<drivers::RobotDevice> robot;
  std::unique_ptr<drivers::SpindleDevice> spindle;
  std::unique_ptr<drivers::CameraDevice> camera;  ///< configured at setup; then the camera thread's only
  std::shared_ptr<std::atomic<bool>> camera_open = std::make_shared<std::atomic<bool>>(false);

  PackmlMachine machine;
  std::uint64_t generation = 0;
  std::optional<Fault> fault;  ///< latched until a Reset
  std::shared_ptr<Cycle> cycle;
  std::optional<int> pending_recipe;
  /// The cycle fettled found interrupted at start (the last, if several): the casting on the
  /// fixture may be the one it left half ground. The next PLC cycle says so in its report.
  std::string interrupted_cycle;
  bool dry_requested = false;
  long long cycles_total = 0;
  long long cycles_in_execute = 0;
  std::string last_result;
  bool plc_up = false;
  plc::SlideState slide{};
  std::shared_ptr<Pending<Status>> slide_wait;
  int slide_target = -1;
  std::uint64_t slide_command = 0;  ///< the number of the slide command slide_wait waits for
  bool shutting_down = false;
  bool maintenance = false;
  Clock::time_point started = Clock::now();
  asio::steady_timer loop_timer{io};

  /// The event loop serves every device link (PLC polling and heartbeat, robot pings, the
  /// spindle's heartbeats both ways): a handler that holds it for a second makes those links
  /// time out although every device is fine. A timer due every 200 ms says when it came late.
  static constexpr milliseconds kLoopPeriod{200};
  static constexpr double kLoopLateWarnMs = 300.0;

  // --- cell_supervisor.cpp ------------------------------------------------------------------
  void setup();
  void watch_loop(Clock::time_point due);
  void start_spindle();
  void open_camera();
  void publish_state();
  void enter(State s);
  /// The acting state's work; then its SC if nothing else happened meanwhile.
  asio::awaitable<void> act(State s, std::uint64_t gen);
  Status command(Command c, const std::string& source);
  /// A fault: latch it, tell the PLC, end the cycle, Hold or Abort.
  void raise(Fault f);
  void interrupt(const Fault& f);
  /// Sends STOP at once when the robot may move (the first thing on any abort).
  void quick_robot_stop();
  asio::awaitable<void> stop_robot();
  asio::awaitable<void> stop_robot_if_moving();
  asio::awaitable<void> stop_spindle();
  asio::awaitable<void> release_spindle();
  asio::awaitable<void> wait_cycle_gone();
  asio::awaitable<void> slide_home_best_effort();
  asio::awaitable<void> clear_devices();
  asio::awaitable<void> reset_devices();
  void on_plc(const plc::Event& e);
  void on_robot_state(drivers::RobotState s, const Error& cause);
  void on_spindle(const drivers::SpindleEvent& e);
  /// After the cycle's record: the result to the PLC, then the next cycle or Execute's end.
  void finish_cycle(const std::shared_ptr<Cycle>& cp);
  RuntimeStatus snapshot() const;
  void shutdown(std::function<void()> done);

  // --- cycle_runner.cpp ---------------------------------------------------------------------
  void maybe_start_cycle();
  void start_cycle(int recipe_id, bool dry, bool from_plc);
  asio::awaitable<void> run_cycle(Cycle& c);
  bool fail(Cycle& c, Fault f);
  /// The fault for `e` of `source` (faults.hpp), `fallback` when its kind says nothing more.
  bool fail(Cycle& c, const Error& e, ErrorSource source, FaultCode fallback);
  milliseconds margin() const { return options.step_margin; }
  asio::awaitable<bool> slide_to(Cycle& c, int target);
  Transform T_base_camera_at(double slide_mm) const;
  asio::awaitable<bool> capture(Cycle& c, int position, std::vector<View>& out, const std::string& stem);
  asio::awaitable<bool> scan(Cycle& c, std::vector<View>& views, const std::string& stem);
  void report_process_error(Cycle& c, const Error& e, std::string* part_error);
  /// Vision + planning in the worker pool (see the definition for `part_error` and `name`).
  asio::awaitable<std::optional<ProcessOutput>> process_views(Cycle& c, const std::vector<View>& views,
                                                              const ProcessOptions& process_options, const char* name,
                                                              std::string* part_error = nullptr);
  asio::awaitable<std::optional<VerificationResult>> verify_views(Cycle& c, const std::vector<View>& views);
  /// validate -> upload -> spindle up -> run -> spindle down.
  asio::awaitable<bool> grind(Cycle& c, const Trajectory& trajectory, const std::string& suffix);
  /// One line per region: what the maintenance engineer needs to see why a part is NOK.
  void log_verification(const Cycle& c, const VerificationResult& v, const char* what);
  /// [compensation] (compensation.cpp): the learned bias at start (reset when the calibration
  /// or the tools changed), and its update from a cycle's measured cut offset.
  void load_cell_bias();
  void learn_bias(Cycle& c);
  /// Counts what the cycle removed beyond what was counted (c.removed_seen_cm3, or without a
  /// verification scan what `planned` was to remove) into each wheel's wear ([compensation]),
  /// and saves it.
  void count_removal(Cycle& c, const ProcessOutput* planned, bool first_grind);
  /// The wheels a cycle like the last one would wear past their max_wear_mm: tool.worn.
  [[nodiscard]] std::optional<Fault> worn_wheels(const Cycle& c) const;
  /// Each recipe's first grind's removal in its last cycle (cm3 by tool name), for worn_wheels().
  std::map<int, std::map<std::string, double>> last_removed_cm3;
  /// A new wheel is fitted (control socket "tool_changed"): its predicted wear starts from zero.
  Result<json> tool_changed(const std::string& name);
  [[nodiscard]] std::string bias_identity_calibration() const;
  [[nodiscard]] std::string bias_identity_tools() const;
  asio::awaitable<void> sleep(milliseconds d);

  // --- cycle_record.cpp ---------------------------------------------------------------------
  /// The files a cycle's processing made for its record, written on the record writer's thread.
  asio::awaitable<void> write_process_outputs(Cycle& c, const ProcessOutput& out, const char* prefix_text);
  /// Ends the cycle's record: its summary, report.json and the journal's end line.
  void record_cycle(Cycle& c);

  /// Awaits `start`'s callback on the loop thread, at most `timeout`; a fault of `c` cancels
  /// the wait. `start` by reference: see process_views on GCC 12 and temporaries in co_await
  /// expressions.
  template <class T>
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
};

}  // namespace fettle::daemon
