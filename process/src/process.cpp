// One cycle of the processing pipeline (fettle/process/pipeline.hpp): fuse -> vision -> plan
// -> validate.
#include "fettle/process/pipeline.hpp"

#include <algorithm>
#include <cmath>
#include <deque>
#include <string>

#include "fettle/core/log.hpp"
#include "fettle/vision/multiview.hpp"
#include "fettle/vision/preprocess.hpp"
#include "internal.hpp"

namespace fettle::process {

namespace fs = std::filesystem;

namespace {

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

}  // namespace

Result<vision::Cloud> fuse_in_base(const std::vector<View>& views, double jump_edge_mm) {
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
  auto scan = fuse_in_base(views, jump_edge_mm);
  if (!scan) return scan.error();
  timings.push_back({"fuse", ms_since(t0)});
  t0 = Clock::now();
  report(progress, 1, total, "vision");
  auto ins = vision::inspect(loaded.recipe, loaded.templ, *scan);
  timings.push_back({"vision", ms_since(t0)});
  if (!ins) return step_error("vision", ins.error());
  return ins;
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
    if (loaded.region(name) == nullptr) return Error{"pipeline.input", "no region named '" + name + "' in recipe " + recipe.id};
  }
  const std::size_t total = 3 + recipe.regions.size();
  ProcessOutput out;
  auto ins = locate(loaded, views, loaded.recipe.vision.jump_edge_mm, out.timings, progress, total);
  if (!ins) return ins.error();
  out.inspection = std::move(ins.value());
  out.T_base_part = out.inspection.whole.T_scene_template;
  if (options.before != nullptr && options.before->regions.size() == recipe.regions.size())
    for (std::size_t i = 0; i < recipe.regions.size(); ++i) {
      auto& rr = out.inspection.regions[i];
      const auto& face = options.before->regions[i].excess.form;
      if (!rr.ok() || !face.fitted || !selected(options, recipe.regions[i].name)) continue;
      rr.excess = vision::measure_region_excess(recipe, loaded.templ.regions()[i], out.inspection.scene_part,
                                                out.T_base_part.inverse() * rr.registration.T_scene_template, &face);
    }

  // Regions: a region the vision stage could not locate cannot be ground safely.
  std::vector<planning::RegionInput> inputs;
  std::deque<config::Tool> worn_tools;  // the regions' tools as worn (stable addresses for the inputs)
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
      return Error{rr.error->code, "step vision, region '" + region.name + "': " + rr.error->message, rr.error->kind};
    planning::RegionInput in;
    in.region = &region;
    in.tool = &worn_tools.emplace_back(worn_tool(loaded.tool_for(region), options.tool_wear_mm));
    if (const auto most = options.tool_wear_most_mm.find(region.tool); most != options.tool_wear_most_mm.end()) {
      const auto least = options.tool_wear_mm.find(region.tool);
      in.tool_worn_more_mm = std::max(0.0, most->second - (least == options.tool_wear_mm.end() ? 0.0 : least->second));
    }
    // scene = base (= fixture) frame
    // exactly orthonormal: validation maps every pose back into the part frame with its
    // inverse and must read it as the planner placed it
    const Transform T_base_located = orthonormalized(weak ? out.T_base_part : rr.registration.T_scene_template);
    const Transform T_part_region = T_base_located.inverse() * rr.registration.T_scene_template;
    // commanded where the cell's tool, with its learned bias, cuts where the plan says
    const auto own = options.region_placement.find(region.name);
    const bool placed = own != options.region_placement.end();
    in.T_base_part = T_base_located;
    in.T_base_part.translation() -= placed ? own->second.bias_mm : options.cell_bias_mm;
    in.excess_points_part.reserve(rr.excess.points.size());
    for (const auto& p : rr.excess.points) in.excess_points_part.push_back(T_part_region * p.cast<double>());
    in.template_sdf = loaded.template_sdf;
    const Eigen::Matrix3d R_base_part = T_base_located.linear();
    in.placement_bound_mm2 =
        R_base_part.transpose() * (placed ? own->second.bound_mm2 : options.placement_bound_mm2) * R_base_part;
    in.form_deviation_mm = recipe.vision.form_deviation_mm;
    if (rr.excess.form.fitted) {
      const auto form = rr.excess.form;  // region template frame ~ part frame (within the region's fit)
      in.form_offset_mm = [form](const Vec3& p) { return form.at(p.x(), p.y()); };
    }
    if (options.before_plans != nullptr)
      for (const auto& first : *options.before_plans)
        if (first.region == region.name) in.first = &first;
    if (options.leftover != nullptr)
      for (const auto& v : options.leftover->regions) {
        if (v.name != region.name) continue;
        const Transform T_located_region = T_base_located.inverse() * v.T_base_region;
        for (std::size_t k = 0; k < v.roi_points_part.size() && k < v.residual_mm.size(); ++k)
          if (v.residual_mm[k] > config::VerificationSettings::kShareLevelMm) {
            in.leftover_part.push_back(T_located_region * v.roi_points_part[k].cast<double>());
            in.leftover_mm.push_back(v.residual_mm[k]);
          }
      }
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
  out.plans = std::move(plans);

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

}  // namespace fettle::process
