// The processing pipeline (see fettle/daemon/pipeline.hpp): setup (load_recipe), per cycle
// (process: fuse -> vision -> plan -> validate) and after grinding (verify).
#include "fettle/daemon/pipeline.hpp"

#include <algorithm>
#include <array>
#include <cstdint>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <sstream>
#include <system_error>
#include <unordered_map>

#include "fettle/config/load.hpp"
#include "fettle/config/roi.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/planning/sdf_grid.hpp"
#include "fettle/planning/surface.hpp"
#include "fettle/vision/multiview.hpp"
#include "fettle/vision/preprocess.hpp"

namespace fettle::daemon {

namespace fs = std::filesystem;

namespace {

using Clock = std::chrono::steady_clock;

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

void report(const Progress& progress, std::size_t done, std::size_t total, const std::string& step) {
  if (progress) progress(done, total, step);
}

Error step_error(const std::string& step, const Error& inner) {
  return Error{inner.code.empty() ? "pipeline." + step : inner.code, "step " + step + ": " + inner.message};
}

/// The view without flying pixels when vision.jump_edge_mm is on (the filtered copy is kept in
/// `storage`), else the view itself: the filter copies a whole view, off by default.
const OrganizedCloud& without_jump_edges(const OrganizedCloud& view, double jump_edge_mm, OrganizedCloud& storage) {
  if (!(jump_edge_mm > 0.0)) return view;
  storage = vision::remove_jump_edges(view, jump_edge_mm);
  return storage;
}

Error empty_view(std::size_t i, const View& view) {
  return Error{"pipeline.empty_view", "step fuse: view " + std::to_string(i) + " (slide at " +
                                          std::to_string(view.slide_position_mm) +
                                          " mm) has no valid point: check the camera and its exposure"};
}

/// The views in the base (= fixture) frame, fused into one cloud when there are several.
Result<vision::Cloud> fuse(const std::vector<View>& views, double jump_edge_mm) {
  if (views.empty()) return Error{"pipeline.no_views", "step fuse: no views were captured"};
  std::vector<vision::View> camera_views;
  camera_views.reserve(views.size());
  for (std::size_t i = 0; i < views.size(); ++i) {
    vision::View v;
    OrganizedCloud filtered;
    v.cloud = vision::to_cloud(without_jump_edges(views[i].cloud, jump_edge_mm, filtered));
    if (v.cloud.empty()) return empty_view(i, views[i]);
    v.T_first_view = views.front().T_base_camera.inverse() * views[i].T_base_camera;
    camera_views.push_back(std::move(v));
  }
  if (camera_views.size() == 1) return vision::transformed(camera_views.front().cloud, views.front().T_base_camera);
  vision::FuseSettings fs;
  auto fused = vision::fuse_views(camera_views, fs);
  if (!fused) return step_error("fuse", fused.error());
  return vision::transformed(fused->cloud, views.front().T_base_camera);
}

/// Locates the part and its regions in the views, each view without its flying pixels first
/// when jump_edge_mm > 0. Organized views (the camera's) go to the vision stage as they are:
/// image-space outliers per view, every view's pixels into one voxel grid at its slide pose
/// refined against the previous view (vision::register_views). Unorganized ones are fused
/// first (vision::fuse_views).
Result<vision::Inspection> locate(const LoadedRecipe& loaded, const std::vector<View>& views, double jump_edge_mm,
                                  std::vector<StepTiming>& timings, const Progress& progress, std::size_t total) {
  auto t0 = Clock::now();
  const bool organized =
      !views.empty() && std::all_of(views.begin(), views.end(), [](const View& v) { return v.cloud.height > 1; });
  if (organized) {
    report(progress, 0, total, "fuse");
    std::vector<OrganizedCloud> filtered(views.size());
    std::vector<vision::OrganizedView> organized_views;
    for (std::size_t i = 0; i < views.size(); ++i) {
      if (views[i].cloud.count_valid() == 0) return empty_view(i, views[i]);
      organized_views.push_back(
          {&without_jump_edges(views[i].cloud, jump_edge_mm, filtered[i]), views[i].T_base_camera});
    }
    if (views.size() > 1) {  // the slide's calibrated poses, refined pairwise on the overlaps
      vision::FuseSettings fs;
      // Views already without jumps over jump_edge_mm have none over a larger threshold either
      // (remove_jump_edges drops both pixels of every such pair): no second pass over them.
      if (jump_edge_mm > 0.0 && jump_edge_mm <= fs.jump_edge_mm) fs.jump_edge_mm = 0.0;
      auto refined = vision::register_views(organized_views, fs);
      if (!refined) return step_error("fuse", refined.error());
      organized_views = std::move(*refined);
    }
    timings.push_back({"fuse", ms_since(t0)});
    t0 = Clock::now();
    report(progress, 1, total, "vision");
    auto ins = vision::inspect(loaded.recipe, loaded.templ, organized_views);
    timings.push_back({"vision", ms_since(t0)});
    if (!ins) return step_error("vision", ins.error());
    return ins;
  }
  report(progress, 0, total, "fuse");
  auto scan = fuse(views, jump_edge_mm);
  if (!scan) return scan.error();
  timings.push_back({"fuse", ms_since(t0)});
  t0 = Clock::now();
  report(progress, 1, total, "vision");
  auto ins = vision::inspect(loaded.recipe, loaded.templ, *scan);
  timings.push_back({"vision", ms_since(t0)});
  if (!ins) return step_error("vision", ins.error());
  return ins;
}

/// The transform with its rotation made exactly orthonormal (the nearest rotation): a pose from
/// single-precision registration maps lengths off by up to ~1e-7, and its Isometry inverse (the
/// transpose) then takes a point 100 mm out back to within only ~1e-5 mm of where it was.
Transform orthonormalized(const Transform& T) {
  Transform R = Transform::Identity();
  R.linear() = Quat(T.rotation()).normalized().toRotationMatrix();
  R.translation() = T.translation();
  return R;
}

bool selected(const ProcessOptions& options, const std::string& name) {
  return options.regions.empty() || std::find(options.regions.begin(), options.regions.end(), name) != options.regions.end();
}

/// The planner's signed distance: the exact sample-based one (sdf_from_samples) evaluated once
/// on a banded grid (planning::SdfGrid), read from `<recipe dir>/.<recipe stem>.planning-cache/`
/// when its key (hash of the samples and of every setting) matches, else built in parallel and
/// written there. A stale or corrupt cache is rebuilt with a warning, never trusted.
planning::SignedDistance signed_distance_grid(const config::PartRecipe& recipe, const LoadOptions& options,
                                              const std::vector<Vec3>& pts, const std::vector<Vec3>& nrm,
                                              double search_mm, LoadedRecipe& out) {
  constexpr double kCellMm = 4.0;
  auto exact = planning::sdf_from_samples(pts, nrm, kCellMm, search_mm);
  const planning::SdfGridSettings gs;
  Vec3 lo = Vec3::Constant(std::numeric_limits<double>::infinity()), hi = -lo;
  for (const auto& p : pts) lo = lo.cwiseMin(p), hi = hi.cwiseMax(p);
  std::ostringstream params;
  params.precision(17);
  params << "sdf_from_samples 4 cell " << kCellMm << " search " << search_mm << " grid voxel " << gs.voxel_mm << " band "
         << gs.band_mm << " tol " << gs.exact_tol_mm << " far " << gs.far_voxel_mm << " " << gs.far_band_mm << " "
         << gs.far_tol_mm << " jump " << gs.kink_jump_mm;
  const auto key = planning::sdf_grid_key(pts, nrm, params.str());
  fs::path dir = options.sdf_cache_dir;
  if (dir.empty() && recipe.vision.cache && !recipe.source.empty()) dir = planning_cache_dir(recipe.source);
  const bool cache = !dir.empty();
  const fs::path file = cache ? sdf_grid_file(dir) : fs::path{};
  auto logger = log::get("planning");
  if (cache) {
    std::string why;
    std::error_code ec;
    const bool present = fs::exists(file, ec);
    if (auto grid = planning::SdfGrid::load(file, key, exact, &why)) {
      out.sdf_grid = grid->stats();
      out.sdf_from_cache = true;
      return grid->function();
    }
    if (present) logger->warn("signed-distance grid cache not used, rebuilding it: {}", why);
  }
  logger->info("building the template's signed-distance grid ({} samples, voxel {} mm, band {} mm)", pts.size(),
               gs.voxel_mm, gs.band_mm);
  const auto grid = planning::SdfGrid::build(exact, lo, hi, gs, [&](const char* lattice, std::size_t done, std::size_t total) {
    logger->info("signed-distance grid: {} lattice {}/{} bricks", lattice, done, total);
  });
  const auto& st = grid.stats();
  logger->info("signed-distance grid: {} band bricks of {}, {} far bricks, {:.1f} MiB; {} band and {} far cells answered "
               "exactly; built in {:.1f} s",
               st.bricks, st.brick_slots, st.far_bricks, static_cast<double>(st.memory_bytes) / (1024.0 * 1024.0),
               st.exact_cells, st.far_exact_cells, st.build_ms / 1000.0);
  out.sdf_grid = st;
  if (cache) {
    std::error_code ec;
    fs::create_directories(file.parent_path(), ec);
    if (Status s = grid.save(file, key); !s) logger->warn("signed-distance grid cache not written: {}", s.error().message);
  }
  return grid.function();
}

}  // namespace

const config::Tool& LoadedRecipe::tool_for(const config::Region& region) const {
  for (const auto& t : recipe.tools)
    if (t.name == region.tool) return t;
  throw UserError(recipe.source.string() + ": region '" + region.name + "' names tool '" + region.tool +
                  "', which has no [[tools]] entry");
}

fs::path golden_path(const config::PartRecipe& recipe) {
  if (!recipe.template_source.scan.empty()) return recipe.template_source.scan;
  const fs::path dir = recipe.source.empty() ? fs::current_path() : recipe.source.parent_path();
  const std::string stem = recipe.source.empty() ? recipe.id : recipe.source.stem().string();
  return dir / (stem + ".golden.ply");
}

fs::path planning_cache_dir(const fs::path& recipe_file) {
  return recipe_file.parent_path() / ("." + recipe_file.stem().string() + ".planning-cache");
}

fs::path sdf_grid_file(const fs::path& planning_cache_dir) { return planning_cache_dir / "sdf-grid.bin"; }

LoadedRecipe load_recipe(const config::PartRecipe& recipe, const LoadOptions& options) {
  const auto t0 = Clock::now();
  LoadedRecipe out;
  out.recipe = recipe;
  const std::string where = recipe.source.empty() ? recipe.id : recipe.source.string();
  for (const auto& r : recipe.regions) (void)out.tool_for(r);  // every region has its tool
  vision::Cloud golden;
  if (options.golden) {
    golden = *options.golden;
    out.golden_identity = options.golden_identity.empty() ? "memory:" + recipe.id : options.golden_identity;
  } else {
    out.golden_file = golden_path(recipe);
    std::error_code ec;
    if (!fs::exists(out.golden_file, ec)) {
      const std::string how = recipe.template_source.kind == "simulator"
                                  ? "write it with `fettle-sim golden --part " + where + " --out " +
                                        out.golden_file.string() + "`"
                                  : "check [template] scan";
      throw UserError(where + ": golden template " + out.golden_file.string() + " not found: " + how);
    }
    golden = vision::load_cloud(out.golden_file);
    out.golden_identity = fs::absolute(out.golden_file).string() + " " +
                          std::to_string(fs::file_size(out.golden_file, ec)) + " " +
                          std::to_string(fs::last_write_time(out.golden_file, ec).time_since_epoch().count());
  }
  if (golden.empty()) throw UserError(where + ": the golden template has no points");
  vision::require_millimetres(golden, "golden template of " + where);
  out.templ = vision::PartTemplate::load_or_build(recipe, golden, out.golden_identity, &out.template_from_cache,
                                                  options.template_cache_dir);
  // The planner's signed distance: from the golden samples themselves where they carry normals
  // (the simulator's golden part: exact outward normals), else from the vision template's fine
  // cloud. The template is voxel-averaged, which blends the normals of the two faces at every
  // edge into a diagonal one and puts a false 0.1-0.2 mm gouge just above the edge.
  const auto& fine = golden.has_normals() ? golden : out.templ.whole().fine();
  if (!fine.has_normals()) throw UserError(where + ": the template has no normals (a bug in the vision stage)");
  std::vector<Vec3> pts, nrm;
  pts.reserve(fine.size());
  nrm.reserve(fine.size());
  for (std::size_t i = 0; i < fine.size(); ++i) {
    pts.push_back(fine.points[i].cast<double>());
    nrm.push_back(fine.normals[i].cast<double>());
  }
  double search_mm = 20.0;
  for (const auto& t : recipe.tools) search_mm = std::max(search_mm, 0.5 * t.diameter_mm + 5.0);
  out.template_points = fine.points;
  out.template_sdf = signed_distance_grid(recipe, options, pts, nrm, search_mm, out);
  out.load_ms = ms_since(t0);
  return out;
}

LoadedRecipe load_recipe(const fs::path& part_file, const LoadOptions& options) {
  return load_recipe(config::load_part(part_file), options);
}

Result<ProcessOutput> process(const LoadedRecipe& recipe, const config::CellConfig& cell, const std::vector<View>& views,
                              const Progress& progress) {
  return process(recipe, cell, views, ProcessOptions{}, progress);
}

Result<ProcessOutput> process(const LoadedRecipe& loaded, const config::CellConfig& cell, const std::vector<View>& views,
                              const ProcessOptions& options, const Progress& progress) {
  const auto t_start = Clock::now();
  const auto& recipe = loaded.recipe;
  for (const auto& name : options.regions) {
    const bool known = std::any_of(recipe.regions.begin(), recipe.regions.end(),
                                   [&](const config::Region& r) { return r.name == name; });
    if (!known) return Error{"pipeline.input", "no region named '" + name + "' in recipe " + recipe.id};
  }
  const std::size_t total = 3 + recipe.regions.size();
  ProcessOutput out;
  auto ins = locate(loaded, views, loaded.recipe.vision.jump_edge_mm, out.timings, progress, total);
  if (!ins) return ins.error();
  out.inspection = std::move(ins.value());
  out.T_base_part = out.inspection.whole.T_scene_template;

  // Regions: a region the vision stage could not locate cannot be ground safely.
  std::vector<planning::RegionInput> inputs;
  for (std::size_t i = 0; i < recipe.regions.size(); ++i) {
    const auto& region = recipe.regions[i];
    const auto& rr = out.inspection.regions[i];
    RegionMetrics m;
    m.name = region.name;
    m.type = region.type;
    m.scene_points = rr.scene_points;
    m.fitness = rr.registration.fitness;
    m.rmse_mm = rr.registration.rmse;
    m.excess_points = rr.excess.points.size();
    m.excess_volume_mm3 = rr.excess.volume_mm3;
    m.excess_max_height_mm = rr.excess.max_height_mm;
    out.regions.push_back(m);
    if (!selected(options, region.name)) continue;
    // A region whose own fine fit is weak (below min_fitness: less of its visible template
    // surface found than expected) is planned on the whole part's pose; one below half of
    // min_fitness (0.16 on the mirror-image part) or not registered at all fails the cycle.
    const bool weak = !rr.ok() && rr.error->code == "vision.low_fitness" &&
                      rr.registration.fitness >= 0.5 * recipe.vision.min_fitness;
    if (!rr.ok() && !weak)
      return Error{rr.error->code, "step vision, region '" + region.name + "': " + rr.error->message};
    planning::RegionInput in;
    in.region = &region;
    in.tool = &loaded.tool_for(region);
    // scene = base (= fixture) frame
    // exactly orthonormal: validation maps every pose back into the part frame with its
    // inverse and must read it as the planner placed it
    in.T_base_part = orthonormalized(weak ? out.T_base_part : rr.registration.T_scene_template);
    const Transform T_part_region = in.T_base_part.inverse() * rr.registration.T_scene_template;
    in.excess_points_part.reserve(rr.excess.points.size());
    for (const auto& p : rr.excess.points) in.excess_points_part.push_back(T_part_region * p.cast<double>());
    in.template_sdf = loaded.template_sdf;
    inputs.push_back(std::move(in));
  }

  // Planning: per region (timed), ordering, assembly, validation.
  const auto settings = planning::PlannerSettings::from(cell.safety);
  const auto t_plan = Clock::now();
  std::vector<planning::RegionPlan> plans;
  plans.reserve(inputs.size());
  for (std::size_t k = 0; k < inputs.size(); ++k) {
    const auto& in = inputs[k];
    report(progress, 2 + k, total, "plan " + in.region->name);
    const auto t0 = Clock::now();
    auto plan = planning::plan_region(in, settings);
    const double ms = ms_since(t0);
    if (!plan) return step_error("plan", plan.error());
    if (plan->left_mm > 0.0)
      log::get("planning")->warn("region '{}': {:.2f} mm of excess material at ({:.2f}, {:.2f}, {:.2f}) (part frame){} is "
                                 "left: unreachable, the tool cannot reach it without coming nearer the template than "
                                 "its allowance",
                                 in.region->name, plan->left_mm, plan->left_at.x(), plan->left_at.y(), plan->left_at.z(),
                                 plan->left_length_mm > 0.0 ? fmt::format(", {:.1f} mm of the fin", plan->left_length_mm)
                                                            : std::string{});
    for (auto& m : out.regions)
      if (m.name == in.region->name) {
        m.plan_ms = ms;
        m.trajectory_points = plan->points.size();
        m.segments = plan->segments;
        m.material_left_mm = plan->left_mm;
        m.material_left_at = plan->left_at;
        m.material_left_length_mm = plan->left_length_mm;
      }
    plans.push_back(std::move(plan.value()));
  }
  report(progress, 2 + inputs.size(), total, "validate");
  out.trajectory = planning::assemble(recipe.id, plans, planning::order_regions(plans), settings);
  if (Status st = planning::validate(out.trajectory, inputs, settings); !st) {
    out.trajectory = {};
    return step_error("validate", st.error());
  }
  out.timings.push_back({"plan", ms_since(t_plan)});

  // Preview: the located scan in the base frame, coloured by height above the template.
  const auto& ins_ref = out.inspection;
  out.preview.reserve(ins_ref.scene_part.size());
  for (std::size_t i = 0; i < ins_ref.scene_part.size(); ++i) {
    const float d = i < ins_ref.deviation_mm.size() ? ins_ref.deviation_mm[i] : 0.0f;
    out.preview.push_back({out.T_base_part * ins_ref.scene_part.points[i].cast<double>(),
                           std::isfinite(d) ? std::max(0.0, static_cast<double>(d)) : 0.0});
  }
  report(progress, total, total, "done");
  out.total_ms = ms_since(t_start);
  return out;
}

Status write_outputs(const fs::path& dir, const ProcessOutput& output) {
  return planning::write_outputs(dir, output.trajectory, output.preview);
}

const char* to_string(Verdict verdict) {
  switch (verdict) {
    case Verdict::ok: return "OK";
    case Verdict::regrind: return "REGRIND";
    case Verdict::nok: return "NOK";
  }
  return "?";
}

std::vector<std::string> VerificationResult::regrind_regions() const {
  std::vector<std::string> names;
  for (const auto& r : regions)
    if (r.verdict == Verdict::regrind) names.push_back(r.name);
  return names;
}

namespace {

/// Integer cells of a uniform grid of `cell` mm, packed into one key (21 bits an axis).
struct CellKeys {
  double cell = 1.0;
  [[nodiscard]] std::array<std::int64_t, 3> coords(const Vec3& p) const {
    return {static_cast<std::int64_t>(std::floor(p.x() / cell)), static_cast<std::int64_t>(std::floor(p.y() / cell)),
            static_cast<std::int64_t>(std::floor(p.z() / cell))};
  }
  static std::int64_t pack(std::int64_t x, std::int64_t y, std::int64_t z) {
    return ((x & 0x1FFFFF) << 42) | ((y & 0x1FFFFF) << 21) | (z & 0x1FFFFF);
  }
  [[nodiscard]] std::int64_t key(const Vec3& p) const {
    const auto c = coords(p);
    return pack(c[0], c[1], c[2]);
  }
};

/// Points of a cloud by cells, for the neighbours of a few candidates.
class PointCells {
 public:
  PointCells(const std::vector<Eigen::Vector3f>& pts, double cell) : pts_(pts), keys_{cell} {
    for (std::size_t i = 0; i < pts.size(); ++i) cells_[keys_.key(pts[i].cast<double>())].push_back(i);
  }
  template <class F>
  void within(const Vec3& q, double r, F&& f) const {
    const auto c = keys_.coords(q);
    const int n = static_cast<int>(std::ceil(r / keys_.cell));
    for (int dz = -n; dz <= n; ++dz)
      for (int dy = -n; dy <= n; ++dy)
        for (int dx = -n; dx <= n; ++dx) {
          const auto it = cells_.find(CellKeys::pack(c[0] + dx, c[1] + dy, c[2] + dz));
          if (it == cells_.end()) continue;
          for (auto i : it->second)
            if ((pts_[i].cast<double>() - q).squaredNorm() <= r * r) f(i);
        }
  }

 private:
  const std::vector<Eigen::Vector3f>& pts_;
  CellKeys keys_;
  std::unordered_map<std::int64_t, std::vector<std::size_t>> cells_;
};

/// The median signed distance of the points within `radius` of point k (k included): a gouge's
/// depth as its neighbourhood confirms it. nullopt with fewer than 3 points there (an isolated
/// point confirms nothing).
std::optional<double> neighbourhood_median(const PointCells& cells, const std::vector<Eigen::Vector3f>& pts,
                                           const std::vector<float>& residual, std::size_t k, double radius,
                                           std::vector<float>& scratch) {
  scratch.clear();
  cells.within(pts[k].cast<double>(), radius, [&](std::size_t i) { scratch.push_back(residual[i]); });
  if (scratch.size() < 3) return std::nullopt;
  auto mid = scratch.begin() + static_cast<std::ptrdiff_t>(scratch.size() / 2);
  std::nth_element(scratch.begin(), mid, scratch.end());
  return static_cast<double>(*mid);
}

RegionVerification judge_region(const config::Region& region, const config::VerificationSettings& vs,
                                std::size_t min_points, std::vector<Eigen::Vector3f> points_part,
                                std::vector<float> residual_mm) {
  RegionVerification v;
  v.name = region.name;
  v.type = region.type;
  v.roi_points = points_part.size();
  std::size_t gouged = 0, too_high = 0;
  for (const float r : residual_mm) {
    const double a = std::abs(r);
    v.over_0_3 += a > 0.3 ? 1 : 0;
    v.over_0_4 += a > 0.4 ? 1 : 0;
    v.over_0_5 += a > 0.5 ? 1 : 0;
    v.max_residual_mm = std::max(v.max_residual_mm, a);
    v.max_above_mm = std::max(v.max_above_mm, static_cast<double>(r));
    v.max_below_mm = std::max(v.max_below_mm, static_cast<double>(-r));
    too_high += r > vs.max_regrind_height_mm ? 1 : 0;
  }
  // Gouged points: more than gouge_depth_mm below the template, and so is the median of their
  // neighbourhood (a single deep point is noise or a mixed pixel at a wall, not a cut).
  if (std::any_of(residual_mm.begin(), residual_mm.end(), [&](float r) { return -r > vs.gouge_depth_mm; })) {
    const PointCells cells(points_part, std::max(0.25, vs.gouge_confirm_radius_mm));
    std::vector<float> scratch;
    for (std::size_t k = 0; k < residual_mm.size(); ++k) {
      if (!(-residual_mm[k] > vs.gouge_depth_mm)) continue;
      const auto m = neighbourhood_median(cells, points_part, residual_mm, k, vs.gouge_confirm_radius_mm, scratch);
      gouged += m && -*m > vs.gouge_depth_mm ? 1 : 0;
    }
  }
  const double n = static_cast<double>(std::max<std::size_t>(1, v.roi_points));
  auto pct = [&](std::size_t k) { return 100.0 * static_cast<double>(k) / n; };
  v.share_over_0_3_pct = pct(v.over_0_3);
  v.share_over_0_4_pct = pct(v.over_0_4);
  v.share_over_0_5_pct = pct(v.over_0_5);
  auto num = [](double x) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.3g", x);
    return std::string(buf);
  };
  if (v.roi_points < min_points) {
    // Nothing to judge is not a pass: a region the verification scan does not see (a wall
    // seen edge-on from above, a ROI that misses the part) must not be reported as ground.
    v.verdict = Verdict::nok;
    v.reason = "cannot be verified: " + std::to_string(v.roi_points) +
               " points of the verification scan in its ROI (at least " + std::to_string(min_points) +
               ", vision.min_region_points); check the region's roi_center_mm and roi_size_mm against what the "
               "camera sees from the slide's photo positions";
  } else if (pct(gouged) > vs.nok_max_share_gouged_pct) {
    v.verdict = Verdict::nok;
    v.reason = num(pct(gouged)) + " % of the ROI points are more than gouge_depth_mm = " + num(vs.gouge_depth_mm) +
               " mm below the template with their neighbourhood (allowed " + num(vs.nok_max_share_gouged_pct) +
               " %): gouged";
  } else if (pct(too_high) > vs.ok_max_share_over_0_5_pct) {
    v.verdict = Verdict::nok;
    v.reason = num(pct(too_high)) + " % of the ROI points stand more than max_regrind_height_mm = " +
               num(vs.max_regrind_height_mm) + " mm above the template: not a grinding leftover";
  } else if (v.share_over_0_3_pct > vs.ok_max_share_over_0_3_pct || v.share_over_0_5_pct > vs.ok_max_share_over_0_5_pct) {
    v.verdict = Verdict::regrind;
    v.reason = num(v.share_over_0_3_pct) + " % of the ROI points > 0.3 mm (allowed " + num(vs.ok_max_share_over_0_3_pct) +
               " %), " + num(v.share_over_0_5_pct) + " % > 0.5 mm (allowed " + num(vs.ok_max_share_over_0_5_pct) + " %)";
  }
  v.roi_points_part = std::move(points_part);
  v.residual_mm = std::move(residual_mm);
  return v;
}

}  // namespace

namespace {

std::string fmt_mm(double v, int precision) {
  char buf[48];
  std::snprintf(buf, sizeof buf, "%.*f", precision, v);
  return buf;
}

/// A tool's volume at one pose, for the swept footprint: a ball (centre, radius) or a cylinder
/// (axis from `a` to `b`, radius), both grown by the margin.
struct ToolVolume {
  Vec3 a, b;
  double radius = 0.0;
  std::size_t region = 0;  ///< index into the recipe's regions
  [[nodiscard]] bool contains(const Vec3& q) const {
    const Vec3 ab = b - a;
    const double len2 = ab.squaredNorm();
    const double f = len2 > 0.0 ? std::clamp((q - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
    return (q - (a + f * ab)).squaredNorm() <= radius * radius;
  }
};

/// Every pose of the trajectories and every 1 mm of the moves between them (validate()'s
/// sampling), as tool volumes in the part frame.
std::vector<ToolVolume> swept_volumes(const LoadedRecipe& loaded, const std::vector<Trajectory>& ground,
                                      const Transform& T_part_base) {
  const auto& recipe = loaded.recipe;
  std::vector<ToolVolume> out;
  for (const auto& traj : ground) {
    for (std::size_t i = 0; i < traj.points.size(); ++i) {
      const std::string name = traj.region_of(traj.points[i]);
      const auto it = std::find_if(recipe.regions.begin(), recipe.regions.end(),
                                   [&](const config::Region& r) { return r.name == name; });
      if (it == recipe.regions.end()) continue;
      const auto& tool = loaded.tool_for(*it);
      const double R = 0.5 * tool.diameter_mm;
      const bool ball = tool.shape == config::ToolShape::ball;
      const double grow = recipe.verification.footprint_margin_mm;
      auto add = [&](const Pose& m) {
        const Transform T = T_part_base * m.to_transform();
        const Vec3 tip = T.translation(), z = T.linear().col(2);
        ToolVolume v;
        v.region = static_cast<std::size_t>(it - recipe.regions.begin());
        v.a = ball ? Vec3(tip + R * z) : tip;
        v.b = ball ? v.a : Vec3(tip + std::max(0.0, tool.length_mm) * z);
        v.radius = R + grow;
        out.push_back(v);
      };
      if (i > 0)
        planning::for_each_move_sample(traj.points[i - 1].T_base_tool, traj.points[i].T_base_tool, [&](const Pose& m) {
          add(m);
          return true;
        });
      add(traj.points[i].T_base_tool);
    }
  }
  return out;
}

/// The swept volumes by the grid cells their bounding boxes overlap: a point tests only the
/// volumes of its cell, in their order (the scan's 10^5 points against the trajectories' 10^4
/// poses one by one made the verification seconds slower).
class VolumeIndex {
 public:
  VolumeIndex(const std::vector<ToolVolume>& volumes, double cell) : volumes_(volumes), keys_{cell} {
    for (std::size_t i = 0; i < volumes.size(); ++i) {
      const auto& v = volumes[i];
      const auto lo = keys_.coords(v.a.cwiseMin(v.b) - Vec3::Constant(v.radius));
      const auto hi = keys_.coords(v.a.cwiseMax(v.b) + Vec3::Constant(v.radius));
      for (auto z = lo[2]; z <= hi[2]; ++z)
        for (auto y = lo[1]; y <= hi[1]; ++y)
          for (auto x = lo[0]; x <= hi[0]; ++x) cells_[CellKeys::pack(x, y, z)].push_back(i);
    }
  }
  /// The first volume holding q, or nullptr.
  [[nodiscard]] const ToolVolume* containing(const Vec3& q) const {
    const auto it = cells_.find(keys_.key(q));
    if (it == cells_.end()) return nullptr;
    for (auto i : it->second)
      if (volumes_[i].contains(q)) return &volumes_[i];
    return nullptr;
  }

 private:
  const std::vector<ToolVolume>& volumes_;
  CellKeys keys_;
  std::unordered_map<std::int64_t, std::vector<std::size_t>> cells_;
};

}  // namespace

std::string GougeFinding::describe() const {
  return std::string("gouged ") + (in_roi ? "in" : "outside") + " region " + region + " at (" + fmt_mm(at_part.x(), 2) +
         ", " + fmt_mm(at_part.y(), 2) + ", " + fmt_mm(at_part.z(), 2) + ") mm (part frame), depth " +
         fmt_mm(depth_mm, 3) + " mm";
}

Result<VerificationResult> verify(const LoadedRecipe& loaded, const config::CellConfig& cell, const std::vector<View>& rescan,
                                  const Progress& progress) {
  return verify(loaded, cell, rescan, {}, progress);
}

Result<VerificationResult> verify(const LoadedRecipe& loaded, const config::CellConfig&, const std::vector<View>& rescan,
                                  const std::vector<Trajectory>& ground, const Progress& progress) {
  const auto& recipe = loaded.recipe;
  const auto& vs = recipe.verification;
  VerificationResult out;
  const std::size_t total = 3;
  // the re-scan without flying pixels: beside a wall they stand in the air and read as material
  auto ins = locate(loaded, rescan, vs.jump_edge_mm, out.timings, progress, total);
  if (!ins) return ins.error();
  const auto t0 = Clock::now();
  report(progress, 2, total, "verify");
  out.T_base_part = ins->whole.T_scene_template;
  for (std::size_t i = 0; i < recipe.regions.size(); ++i) {
    const auto& region = recipe.regions[i];
    const auto& rr = ins->regions[i];
    // The region's own fine pose where it could be found, else the whole part's (after
    // grinding a region may have too few features of its own).
    const Transform T_region_part = rr.ok() ? rr.registration.T_scene_template.inverse() * out.T_base_part
                                            : Transform::Identity();
    const Eigen::Isometry3f T = T_region_part.cast<float>();
    std::vector<Eigen::Vector3f> pts;
    for (const auto& p : ins->scene_part.points) {
      const Eigen::Vector3f q = T * p;
      if (config::roi_contains(region, q)) pts.push_back(q);
    }
    // Residuals on the planner's signed distance (golden samples with their normals, edges
    // handled): the voxel-averaged vision template blends the two normals at every edge and
    // read exactly ground edges as 0.5 mm off.
    std::vector<float> residual;
    residual.reserve(pts.size());
    for (const auto& q : pts) residual.push_back(static_cast<float>(loaded.template_sdf(q.cast<double>())));
    out.regions.push_back(judge_region(region, recipe.verification,
                                       static_cast<std::size_t>(recipe.vision.min_region_points), std::move(pts),
                                       std::move(residual)));
  }

  // Gouges wherever the tool went: the whole part's re-scan (part frame, the whole part's pose)
  // in every ROI and in the swept footprint of every uploaded pose and move. A place counts
  // when the median of the points within gouge_confirm_radius_mm lies more than gouge_depth_mm
  // below the template (tests Pipeline.VerifyFindsAGougeOutsideEveryRoiWhereTheToolWent,
  // Pipeline.VerifyFindsNoGougeWhereAnExactlyGroundCastingWasGround).
  {
    const auto& scene = ins->scene_part.points;
    const auto volumes = swept_volumes(loaded, ground, out.T_base_part.inverse());
    const VolumeIndex footprint(volumes, 8.0);
    std::vector<float> residual(scene.size());
    for (std::size_t k = 0; k < scene.size(); ++k)
      residual[k] = static_cast<float>(loaded.template_sdf(scene[k].cast<double>()));
    // where a point is: the ROI holding it, else the footprint of a region's tool, else nowhere
    auto place = [&](const Vec3& q, std::string& region, bool& in_roi) {
      for (const auto& r : recipe.regions)
        if (config::roi_contains(r, q.cast<float>())) {
          region = r.name, in_roi = true;
          return true;
        }
      if (const ToolVolume* v = footprint.containing(q)) {
        region = recipe.regions[v->region].name, in_roi = false;
        return true;
      }
      return false;
    };
    for (const auto& p : scene) {
      std::string region;
      bool in_roi = false;
      if (place(p.cast<double>(), region, in_roi) && !in_roi) ++out.footprint_points;
    }
    // candidates from half the gouge depth: the deepest confirmed place is reported even when it
    // is no gouge
    std::vector<std::size_t> candidates;
    for (std::size_t k = 0; k < scene.size(); ++k)
      if (-residual[k] > 0.5 * vs.gouge_depth_mm) candidates.push_back(k);
    if (!candidates.empty()) {
      const PointCells cells(scene, std::max(0.25, vs.gouge_confirm_radius_mm));
      std::vector<float> near;
      for (auto k : candidates) {
        const Vec3 q = scene[k].cast<double>();
        GougeFinding g;
        if (!place(q, g.region, g.in_roi)) continue;
        const auto median = neighbourhood_median(cells, scene, residual, k, vs.gouge_confirm_radius_mm, near);
        if (!median) continue;
        const double depth = -*median;
        out.deepest_below_mm = std::max(out.deepest_below_mm, depth);
        if (depth <= vs.gouge_depth_mm) continue;
        if (out.worst_gouge && out.worst_gouge->depth_mm >= depth) continue;
        g.depth_mm = depth;
        g.at_part = q;
        g.points = near.size();  // the neighbourhood's points
        out.worst_gouge = g;
      }
    }
  }

  for (const auto& r : out.regions) {
    if (r.verdict == Verdict::nok) out.verdict = Verdict::nok;
    else if (r.verdict == Verdict::regrind && out.verdict == Verdict::ok) out.verdict = Verdict::regrind;
  }
  if (out.worst_gouge) out.verdict = Verdict::nok;
  out.timings.push_back({"verify", ms_since(t0)});
  report(progress, total, total, "done");
  return out;
}

}  // namespace fettle::daemon
