// The cycle runner of fettled's runtime (runtime_impl.hpp): one cycle's steps, each with its
// timeout: slide, capture, process (worker pool), validate, upload, spindle, run, verification
// scan, one re-grind; a step that fails raises its fault and ends the cycle.
#include <algorithm>
#include <utility>

#include <fmt/format.h>
#include <fmt/ranges.h>
#include <boost/asio/co_spawn.hpp>
#include <boost/asio/detached.hpp>
#include <boost/asio/post.hpp>

#include "fettle/core/ply.hpp"
#include "runtime_impl.hpp"

namespace fettle::daemon {

asio::awaitable<void> Runtime::Impl::sleep(milliseconds d) {
  asio::steady_timer t(io);
  t.expires_after(d);
  boost::system::error_code ec;
  co_await t.async_wait(asio::redirect_error(asio::use_awaitable, ec));
}

void Runtime::Impl::maybe_start_cycle() {
  if (cycle || shutting_down) return;
  if (dry_requested) {
    dry_requested = false;
    start_cycle(pending_recipe.value_or(cell.cell.recipes.empty() ? 0 : cell.cell.recipes.front().plc_recipe_id), true,
                false);
    return;
  }
  if (machine.state() != State::execute || !pending_recipe) return;
  if (options.max_cycles > 0 && cycles_in_execute >= options.max_cycles) return;
  // The next request is accepted once the PLC acknowledged the last result (cycle_result_ack):
  // a result is never overwritten unread (docs/plc-interface.md; test CycleFaults.*ResultAck*).
  if (plc_link->status().results_waiting > 0) {
    log->debug("cycle request for recipe {} waits for the PLC to acknowledge the last result", *pending_recipe);
    return;
  }
  const int recipe_id = *pending_recipe;
  pending_recipe.reset();
  plc_link->accept_cycle();
  start_cycle(recipe_id, false, true);
}

void Runtime::Impl::start_cycle(int recipe_id, bool dry, bool from_plc) {
  auto c = std::make_shared<Cycle>();
  c->recipe_id = recipe_id;
  c->dry = dry;
  if (auto it = recipes.find(recipe_id); it != recipes.end()) c->recipe = it->second;
  auto begun = records.begin(recipe_id, c->recipe ? c->recipe->recipe.id : "", dry);
  if (!begun) {
    raise(Fault{FaultCode::records_failed, begun.error().message, "begin"});
    if (from_plc) (void)plc_link->report_result(plc::CycleResult::fault);  // the request's one result
    return;
  }
  c->summary = *begun;
  if (!records.warning().empty()) c->warnings.push_back("records: " + records.warning());
  // The PLC's request survives a restart, and the casting on the fixture may be the one the
  // interrupted cycle left half ground: the cycle runs (a fresh scan, excess measured against
  // the template, so nothing already ground is ground again), and says so in its report and the
  // log, so a refusal (E505 on a flash half gone) is read for what it is (docs/daemon.md
  // "Stopping and restarting"; test CycleFaults.TheCycleAfterAnInterruptedOneSaysTheCastingMayBeHalfGround).
  if (from_plc && !interrupted_cycle.empty()) {
    c->warnings.push_back("the casting may be half ground: cycle " + interrupted_cycle +
                          " was interrupted (fettled stopped during it); this cycle scans it afresh");
    log->warn("cycle {}: the casting may be half ground by interrupted cycle {}", c->summary.id, interrupted_cycle);
    interrupted_cycle.clear();
  }
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

bool Runtime::Impl::fail(Cycle& c, Fault f) {
  if (!c.fault) raise(std::move(f));
  return false;
}

bool Runtime::Impl::fail(Cycle& c, const Error& e, ErrorSource source, FaultCode fallback) {
  return fail(c, fault_from_error(e, source, c.step, c.motion, fallback));
}

asio::awaitable<bool> Runtime::Impl::slide_to(Cycle& c, int target) {
  c.begin(target == 0 ? "slide home" : "slide to " + std::to_string(target));
  publish_state();
  if (!plc_up) co_return fail(c, Fault{FaultCode::plc_link_lost, "the PLC link is down", c.step});
  // A slide already in fault sends no new state when commanded: without this the cycle would
  // wait out travel_timeout_ms and report a timeout (test Fettled.B_EveryFaultEndsInItsStateAndTheCellRecovers,
  // "slide faulted before the cycle").
  if (slide.status == plc::SlideStatus::fault)
    co_return fail(
        c, Fault{FaultCode::slide_fault, "the PLC reports a slide fault (before the slide was commanded)", c.step});
  auto p = std::make_shared<Pending<Status>>(io);
  slide_wait = p;
  slide_target = target;
  auto command = plc_link->command_slide(target);
  if (!command) co_return fail(c, command.error(), ErrorSource::plc, FaultCode::slide_fault);
  slide_command = *command;
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
    co_return fail(
        c, Fault{FaultCode::slide_timeout,
                 "the slide did not reach " +
                     (target == 0 ? std::string("home") : "photo position " + std::to_string(target)) + " within " +
                     std::to_string(cell.slide.travel_timeout_ms) + " ms ([slide] travel_timeout_ms)",
                 c.step});
  if (!*p->value) co_return fail(c, Fault{FaultCode::slide_fault, p->value->error().message, c.step});
  c.end();
  co_return true;
}

Transform Runtime::Impl::T_base_camera_at(double slide_mm) const {
  return config::T_base_camera_at(
      calibration && calibration->T_base_camera ? *calibration->T_base_camera : Transform::Identity(), slide_mm);
}

asio::awaitable<bool> Runtime::Impl::capture(Cycle& c, int position, std::vector<View>& out, const std::string& stem) {
  c.begin("capture " + std::to_string(position));
  publish_state();
  const auto timeout =
      milliseconds(cell.camera.frame_timeout_ms * (cell.camera.retries + 1)) + margin() + milliseconds(10000);
  auto r = co_await await_op<Result<drivers::CameraCapture>>(
      &c,
      [this](std::function<void(Result<drivers::CameraCapture>)> done) {
        asio::post(camera_thread, [this, self = shared_from_this(), done] {
          Result<drivers::CameraCapture> result = Error{"camera.unavailable", "not opened"};
          if (camera->lifecycle() == drivers::Lifecycle::active) {
            result = camera->capture();
          } else if (auto st = camera->activate(); !st) {
            result = st.error();
          } else {
            camera_open->store(true);
            result = camera->capture();
          }
          asio::post(io, [done, result = std::move(result)]() mutable { done(std::move(result)); });
        });
      },
      timeout);
  if (c.fault) co_return false;
  if (!r)
    co_return fail(
        c, Fault{FaultCode::camera_timeout, "no capture within " + std::to_string(timeout.count()) + " ms", c.step});
  if (!*r) co_return fail(c, r->error(), ErrorSource::camera, FaultCode::camera_unavailable);
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
      auto st = write_via_temp(file, [&](const fs::path& tmp) { return write_ply(tmp, *cloud); });
      if (!st) log->warn("record {}: {}", file.string(), st.error().message);
    });
    c.files.push_back(file.filename().string());
  }
  out.push_back(std::move(v));
  co_return true;
}

asio::awaitable<bool> Runtime::Impl::scan(Cycle& c, std::vector<View>& views, const std::string& stem) {
  views.clear();
  const int n = static_cast<int>(cell.slide.photo_positions_mm.size());
  for (int pos = 1; pos <= n; ++pos) {
    if (!co_await slide_to(c, pos)) co_return false;
    if (!co_await capture(c, pos, views, stem)) co_return false;
  }
  co_return co_await slide_to(c, 0);
}

/// A failed process(): a cell fault, or with `part_error` an error about the part itself
/// (anything but an internal one: the part cannot be located or planned) returned there (see
/// process_views).
void Runtime::Impl::report_process_error(Cycle& c, const Error& e, std::string* part_error) {
  if (part_error != nullptr && e.kind != ErrorKind::internal) {
    *part_error = e.message + " [" + e.code + "]";
    c.end();
    return;
  }
  fail(c, e, ErrorSource::process, FaultCode::vision_failed);
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
// Its frame draws GCC 12's -Wmismatched-new-delete false positive too (see run_cycle).
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
#endif
asio::awaitable<std::optional<ProcessOutput>> Runtime::Impl::process_views(Cycle& c, const std::vector<View>& views,
                                                                           const ProcessOptions& process_options,
                                                                           const char* name, std::string* part_error) {
  ProcessOptions po = process_options;
  c.begin(name);
  publish_state();
  auto recipe = c.recipe;
  auto views_copy = std::make_shared<const std::vector<View>>(views);
  // The worker may outlive the cycle (a timeout, an abort): what the options point to (a
  // re-grind's first inspection and plans, in the cycle) is copied and lives as long as it.
  auto before = po.before != nullptr ? std::make_shared<const vision::Inspection>(*po.before) : nullptr;
  auto before_plans =
      po.before_plans != nullptr ? std::make_shared<const std::vector<planning::RegionPlan>>(*po.before_plans) : nullptr;
  po.before = before.get();
  po.before_plans = before_plans.get();
  const std::function<void(std::function<void(Result<ProcessOutput>)>)> start =
      [this, recipe, views_copy, po, before, before_plans](std::function<void(Result<ProcessOutput>)> done) {
        asio::post(workers, [this, self = shared_from_this(), recipe, views_copy, po, before, before_plans, done] {
          Result<ProcessOutput> out = Error{"pipeline.internal", "not run", ErrorKind::internal};
          try {
            out = processing->process(*recipe, cell, *views_copy, po);
          } catch (const std::exception& e) {
            out = Error{"pipeline.internal", e.what(), ErrorKind::internal};
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
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif

asio::awaitable<std::optional<VerificationResult>> Runtime::Impl::verify_views(Cycle& c,
                                                                               const std::vector<View>& views) {
  c.begin("verify");
  publish_state();
  auto recipe = c.recipe;
  auto views_copy = std::make_shared<const std::vector<View>>(views);
  // what the robot ran in this cycle: the verification looks for gouges wherever it went
  auto ground = std::make_shared<std::vector<Trajectory>>();
  if (c.processed) ground->push_back(c.processed->trajectory);
  for (const auto& r : c.regrinds) ground->push_back(r.trajectory);
  // Every verification of the cycle judges the casting against its own faces as the first scan
  // found them (process::VerifyOptions); with [compensation] the first one also measures where
  // the tool cut against where it was told (the first inspection says where material was). The
  // worker may outlive the cycle (a timeout, an abort): it gets its own copy of that inspection.
  auto first = c.processed ? std::make_shared<const vision::Inspection>(c.processed->inspection) : nullptr;
  process::VerifyOptions vo;
  vo.before = first.get();
  const vision::Inspection* before = cell.compensation.enabled && c.regrinds.empty() ? vo.before : nullptr;
  auto offset = std::make_shared<std::optional<Result<process::CutOffset>>>();
  auto removed = std::make_shared<std::map<std::string, double>>();
  const bool seen = cell.compensation.enabled && vo.before != nullptr;
  const auto wear = c.tool_wear_mm;
  // named, not a temporary in the co_await expression (see process_views)
  const std::function<void(std::function<void(Result<VerificationResult>)>)> start =
      [this, recipe, views_copy, ground, first, before, vo, offset, wear, removed, seen](
          std::function<void(Result<VerificationResult>)> done) {
        asio::post(workers, [this, self = shared_from_this(), recipe, views_copy, ground, first, before, vo, offset, wear,
                             removed, seen, done] {
          Result<VerificationResult> out = Error{"pipeline.internal", "not run", ErrorKind::internal};
          try {
            out = processing->verify(*recipe, cell, *views_copy, *ground, vo);
            if (out && before != nullptr) {
              process::CutOffsetSettings cs;
              cs.min_points = static_cast<std::size_t>(cell.compensation.min_points);
              *offset = process::measure_cut_offset(*recipe, *before, *ground, *out, wear, cs);
            }
            if (out && seen) *removed = process::measure_removed_cm3(*recipe, *vo.before, *out);
          } catch (const std::exception& e) {
            out = Error{"pipeline.internal", e.what(), ErrorKind::internal};
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
    fail(c, r->error(), ErrorSource::process, FaultCode::vision_failed);
    co_return std::nullopt;
  }
  if (*offset) c.cut_offset = std::move(*offset);
  if (seen) c.removed_seen_cm3 = *removed;
  c.end();
  co_return std::move(r->value());
}

/// validate -> upload -> spindle up -> run -> spindle down.
asio::awaitable<bool> Runtime::Impl::grind(Cycle& c, const Trajectory& trajectory, const std::string& suffix) {
  c.begin("validate" + suffix);
  if (trajectory.points.empty()) {
    c.end();
    co_return true;
  }
  // The planner validated it (gouges included); this is the last check before the robot,
  // against the cell's [safety] limits, whatever produced the trajectory.
  if (const auto limits = planning::validate_limits(trajectory, planning::PlannerSettings::from(cell.safety)); !limits)
    co_return fail(c, limits.error(), ErrorSource::process, FaultCode::plan_failed);
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
  if (!*up) co_return fail(c, up->error(), ErrorSource::robot, FaultCode::robot_unavailable);
  c.end();

  c.begin("spindle up" + suffix);
  publish_state();
  auto sp = co_await await_op<Status>(
      &c, [this, rpm](std::function<void(Status)> d) { spindle->spin_up(rpm, d); },
      milliseconds(cell.spindle.spin_up_timeout_ms) + margin());
  if (c.fault) co_return false;
  if (!sp) co_return fail(c, Fault{FaultCode::spindle_timeout, "spin-up timed out", c.step});
  if (!*sp) co_return fail(c, sp->error(), ErrorSource::spindle, FaultCode::spindle_fault);
  c.end();

  c.begin("run" + suffix);
  publish_state();
  auto run = co_await await_op<Status>(
      &c, [this](std::function<void(Status)> d) { robot->run(d); }, milliseconds(cell.robot.run_timeout_ms) + margin());
  if (c.fault) co_return false;
  if (!run) co_return fail(c, Fault{FaultCode::robot_timeout, "no DONE within the run timeout", c.step});
  if (!*run) co_return fail(c, run->error(), ErrorSource::robot, FaultCode::robot_fault);
  c.end();

  c.begin("spindle down" + suffix);
  publish_state();
  auto down = co_await await_op<Status>(
      &c, [this](std::function<void(Status)> d) { spindle->spin_down(d); },
      milliseconds(cell.spindle.spin_up_timeout_ms) + margin());
  if (c.fault) co_return false;
  if (!down) co_return fail(c, Fault{FaultCode::spindle_timeout, "spindle stop timed out", c.step});
  if (!*down) co_return fail(c, down->error(), ErrorSource::spindle, FaultCode::spindle_fault);
  c.motion = false;
  c.end();
  co_return true;
}

// GCC 12 reports this coroutine's frame (Boost.Asio's awaitable_frame_base: its own operator new
// and sized operator delete) as -Wmismatched-new-delete: a known false positive (gcc PR
// middle-end/109224, also silenced in the sanitizer builds: cmake/FettleOptions.cmake).
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
#endif
asio::awaitable<void> Runtime::Impl::run_cycle(Cycle& c) {
  if (!c.recipe) {
    fail(c, Fault{FaultCode::unknown_recipe,
                  "recipe id " + std::to_string(c.recipe_id) + " is not in [[cell.recipes]] of " + cell.source.string(),
                  "recipe"});
    co_return;
  }
  if (auto worn = worn_wheels(c)) {
    fail(c, *worn);
    co_return;
  }
  if (!co_await scan(c, c.views, "capture")) co_return;
  ProcessOptions all_regions;
  if (cell.compensation.enabled) c.cell_bias_mm = cell_bias.bias_mm;
  c.placement = placement_uncertainty(cell.safety, c.recipe->recipe,
                                      cell.compensation.enabled ? cell_bias : process::CellBias{}, cell.compensation);
  all_regions.cell_bias_mm = c.cell_bias_mm;
  if (cell.compensation.enabled) {
    c.tool_wear_mm = cell_bias.tool_wear_mm(c.recipe->recipe);
    c.tool_wear_most_mm = cell_bias.tool_wear_most_mm(c.recipe->recipe);
  }
  all_regions.tool_wear_mm = c.tool_wear_mm;
  all_regions.tool_wear_most_mm = c.tool_wear_most_mm;
  all_regions.placement_bound_mm2 = c.placement.bound_mm2;
  if (cell.compensation.enabled) c.region_placement = cell_bias.region_placement(c.placement.bound_mm2);
  all_regions.region_placement = c.region_placement;
  if (!c.placement.bound_mm2.isZero())
    log->info("cycle {}: every path keeps {} from the template (the stated accuracies less what the cell has learned)",
              c.summary.id, c.placement.describe());
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
    count_removal(c, &*c.processed, true);
    c.result = "OK";
    co_return;
  }
  std::vector<View> rescan;
  if (!co_await scan(c, rescan, "rescan")) co_return;
  auto v = co_await verify_views(c, rescan);
  if (!v) co_return;
  log_verification(c, *v, "verification");
  count_removal(c, nullptr, true);
  learn_bias(c);
  if (v->verdict == Verdict::regrind) {
    ProcessOptions po;
    po.regions = v->regrind_regions();
    po.cell_bias_mm = c.cell_bias_mm;
    po.placement_bound_mm2 = c.placement.bound_mm2;
    po.region_placement = c.region_placement;
    // the wheels as worn after this cycle's grind (learn_bias counted it)
    if (cell.compensation.enabled) {
      po.tool_wear_mm = cell_bias.tool_wear_mm(c.recipe->recipe);
      po.tool_wear_most_mm = cell_bias.tool_wear_most_mm(c.recipe->recipe);
    }
    if (cell.compensation.enabled && c.cut_offset && *c.cut_offset) {
      // what this cycle's grind measured (process::regrind_compensation)
      const auto rc = process::regrind_compensation(cell.safety, c.recipe->recipe, cell_bias, c.cut_offset->value(),
                                                      cell.compensation);
      po.cell_bias_mm = rc.bias_mm;
      po.placement_bound_mm2 = rc.placement.bound_mm2;
      po.region_placement = rc.regions;
      po.tool_wear_mm = process::regrind_tool_wear(po.tool_wear_mm, c.cut_offset->value(), c.tool_wear_mm);
      for (const auto& [name, w] : po.tool_wear_mm)
        if (const auto before = c.tool_wear_mm.find(name); before != c.tool_wear_mm.end() && w > before->second + 1e-9)
          log->info("cycle {}: wheel '{}' is re-ground as worn at least {:.3f} mm (its cut showed it)", c.summary.id, name, w);
      for (const auto& [name, r] : rc.regions)
        log->info("cycle {}: region '{}' is re-ground with its own offset ({:.3f}, {:.3f}, {:.3f}) mm", c.summary.id, name,
                  r.bias_mm.x(), r.bias_mm.y(), r.bias_mm.z());
      log->info("cycle {}: the re-grind keeps {} from the template (what this cycle's grind measured)", c.summary.id,
                rc.placement.describe());
    }
    po.before = c.processed ? &c.processed->inspection : nullptr;  // the casting's faces as first seen
    po.before_plans = c.processed ? &c.processed->plans : nullptr;  // a ring's fit on the whole fin
    log->info("cycle {}: re-grind of {} region(s): {}", c.summary.id, po.regions.size(), fmt::join(po.regions, ", "));
    c.first_verification = std::move(v);
    po.leftover = &*c.first_verification;  // the fin the first grind left shows where the wheel stood
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
    count_removal(c, nullptr, false);
    log_verification(c, *v, "verification after the re-grind");
  }
  c.verification = std::move(v);
  c.result = c.verification->verdict == Verdict::ok ? "OK" : "NOK";
}
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif

/// One line per region: what the maintenance engineer needs to see why a part is NOK.
void Runtime::Impl::log_verification(const Cycle& c, const VerificationResult& v, const char* what) {
  for (const auto& r : v.regions) {
    const auto line = fmt::format(
        "cycle {}: {} of '{}': {} ({} ROI points, {:.2f} % > 0.3 mm, {:.2f} % > 0.5 mm, "
        "max {:.2f} mm above / {:.2f} mm below the {}){}{}",
        c.summary.id, what, r.name, to_string(r.verdict), r.roi_points, r.share_over_0_3_pct, r.share_over_0_5_pct,
        r.max_above_mm, r.max_below_mm,
        r.against_casting ? fmt::format("casting's own face, {:+.2f} mm over the template", r.form_offset_mm) : "template",
        r.reason.empty() ? "" : ": ", r.reason);
    if (r.verdict == Verdict::ok)
      log->info("{}", line);
    else
      log->warn("{}", line);
  }
  if (v.worst_gouge) log->warn("cycle {}: {}: NOK: {}", c.summary.id, what, v.worst_gouge->describe());
}

}  // namespace fettle::daemon
