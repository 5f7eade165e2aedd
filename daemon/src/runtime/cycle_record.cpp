// The cycle record of fettled's runtime (runtime_impl.hpp): the files a cycle's processing made,
// report.json and the journal's end line (records.hpp keeps the store).
#include <fcntl.h>
#include <malloc.h>
#include <unistd.h>

#include <cctype>
#include <utility>

#include <boost/asio/post.hpp>

#include "fettle/core/atomic_file.hpp"
#include "fettle/core/ply.hpp"
#include "runtime_impl.hpp"

namespace fettle::daemon {

namespace {

/// Points with their deviation from the template (mm) as the property deviation_mm; the points
/// alone when the deviations do not match them.
Status write_deviation_ply(const fs::path& path, const std::vector<Eigen::Vector3f>& points,
                           const std::vector<float>& deviation_mm) {
  const bool with = deviation_mm.size() == points.size();
  return write_ply(path, points, with ? std::vector<std::string>{"deviation_mm"} : std::vector<std::string>{},
                   with ? std::span<const float>(deviation_mm) : std::span<const float>(), "fettle cycle record, mm");
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

/// A verification for report.json; writes each region's deviation cloud into the record.
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
                       {"against", r.against_casting ? "casting" : "template"},
                       {"form_offset_mm", r.form_offset_mm},
                       {"verdict", to_string(r.verdict)},
                       {"reason", r.reason}});
    const auto name = prefix + "deviation_" + safe_name(r.name) + ".ply";
    if (write_deviation_ply(c.summary.dir / name, r.roi_points_part, r.residual_mm))
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
    regions.push_back(
        {{"name", r.name},
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

}  // namespace

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

/// The files a cycle's processing made for its record (trajectory, preview, fused cloud),
/// written on a thread of their own: rendering and writing them takes 0.1-0.2 s under ASan on
/// an idle machine, and the event loop, which serves every device link's heartbeat, must not
/// wait for a busy disk. One thread, not the worker pool: each worker's malloc arena would
/// take the files' memory peak once, and fettled's RSS would step up 50 MB over a soak.
/// The writer gets its own copy of what it writes: nothing of the cycle is shared.
asio::awaitable<void> Runtime::Impl::write_process_outputs(Cycle& c, const ProcessOutput& out,
                                                           const char* prefix_text) {
  struct Written {
    std::vector<std::string> files, warnings;
  };
  const std::string prefix = prefix_text;
  const fs::path dir = c.summary.dir;
  auto copy = std::make_shared<const ProcessOutput>(out);
  const std::function<void(std::function<void(Written)>)> start = [this, dir, prefix,
                                                                   copy](std::function<void(Written)> done) {
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
      if (auto st = write_deviation_ply(dir / name, insp.scene_part.points, insp.deviation_mm); st)
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

void Runtime::Impl::record_cycle(Cycle& c) {
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
  if (cell.compensation.enabled) {
    const auto v3 = [](const Vec3& v) { return json::array({v.x(), v.y(), v.z()}); };
    json comp{{"frame", "base"}, {"bias_commanded_mm", v3(c.cell_bias_mm)}, {"bias_now_mm", v3(cell_bias.bias_mm)},
              {"updates", cell_bias.updates}};
    // the regions commanded with an offset of their own, and each one's now
    json own = json::object(), own_now = json::object();
    for (const auto& [name, r] : c.region_placement) own[name] = v3(r.bias_mm);
    for (const auto& [name, r] : cell_bias.regions) own_now[name] = v3(cell_bias.region_bias_mm(name));
    comp["region_bias_commanded_mm"] = own;
    comp["region_bias_now_mm"] = own_now;
    // each wheel's radius lost to wear: as the paths were planned, and as predicted now
    comp["tool_wear_planned_mm"] = c.tool_wear_mm;
    if (c.recipe) {
      json now = json::object();
      for (const auto& [name, w] : cell_bias.tool_wear(c.recipe->recipe))
        now[name] = {{"least", w.least_mm}, {"expected", w.expected_mm}, {"most", w.most_mm}};
      comp["tool_wear_now_mm"] = now;
    }
    comp["removed_cm3"] = c.removed_seen_cm3;
    if (c.cut_offset && *c.cut_offset) {
      comp["measured"] = {{"offset_mm", v3((*c.cut_offset)->offset_mm)},
                          {"std_mm", v3((*c.cut_offset)->std_mm)},
                          {"points", (*c.cut_offset)->points},
                          {"directions_observed", (*c.cut_offset)->observed_directions()}};
      json wear = json::object();
      for (const auto& [name, w] : (*c.cut_offset)->tools)
        wear[name] = {{"wear_mm", w.wear_mm}, {"std_mm", w.std_mm}, {"points", w.points}};
      comp["measured"]["tool_wear_beyond_planned_mm"] = wear;
    }
    else if (c.cut_offset)
      comp["not_measured"] = c.cut_offset->error().message;
    report["compensation"] = comp;
  }
  if (!c.placement.bound_mm2.isZero())
    report["placement_bound_mm"] = {{"sideways_and_vertical", c.placement.describe()},
                                    {"x", c.placement.along_mm(Vec3::UnitX())},
                                    {"y", c.placement.along_mm(Vec3::UnitY())},
                                    {"z", c.placement.along_mm(Vec3::UnitZ())}};
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
}

}  // namespace fettle::daemon
