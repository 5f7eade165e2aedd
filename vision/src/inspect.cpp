// Templates per recipe (cached) and the per-cycle vision stage.
#include "fettle/vision/inspect.hpp"

#include <chrono>
#include <fstream>
#include <sstream>

#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/vision/plane.hpp"
#include "fettle/vision/preprocess.hpp"

namespace fettle::vision {

namespace {

PrepareSettings whole_settings(const config::PartRecipe& recipe) {
  PrepareSettings ps;
  ps.coarse_voxel = recipe.vision.coarse_voxel_mm;
  ps.feature_radius = recipe.vision.feature_radius_mm;
  return ps;
}

Eigen::Vector3d box_min(const config::Region& r, double margin) {
  return Eigen::Vector3d(r.roi_center_mm[0] - r.roi_size_mm[0] / 2, r.roi_center_mm[1] - r.roi_size_mm[1] / 2,
                         r.roi_center_mm[2] - r.roi_size_mm[2] / 2) -
         Eigen::Vector3d::Constant(margin);
}
Eigen::Vector3d box_max(const config::Region& r, double margin) {
  return Eigen::Vector3d(r.roi_center_mm[0] + r.roi_size_mm[0] / 2, r.roi_center_mm[1] + r.roi_size_mm[1] / 2,
                         r.roi_center_mm[2] + r.roi_size_mm[2] / 2) +
         Eigen::Vector3d::Constant(margin);
}

std::string cache_key(const config::PartRecipe& recipe, const std::string& golden_identity, std::size_t golden_points) {
  std::ostringstream k;
  k << "fettle-vision-cache 1\n" << golden_identity << "\n" << golden_points << "\n";
  k << recipe.template_source.voxel_mm << " " << recipe.vision.coarse_voxel_mm << " " << recipe.vision.feature_radius_mm << "\n";
  for (const auto& r : recipe.regions)
    k << r.name << " " << r.roi_center_mm[0] << " " << r.roi_center_mm[1] << " " << r.roi_center_mm[2] << " "
      << r.roi_size_mm[0] << " " << r.roi_size_mm[1] << " " << r.roi_size_mm[2] << "\n";
  return k.str();
}

}  // namespace

PartTemplate PartTemplate::build(const config::PartRecipe& recipe, const Cloud& golden_part, const Eigen::Vector3f& viewpoint) {
  require_millimetres(golden_part, "golden template of " + recipe.id);
  Cloud golden = golden_part;
  if (!golden.has_normals()) estimate_normals(golden, 12, viewpoint);
  golden = voxel_downsample(golden, recipe.template_source.voxel_mm);
  PartTemplate t;
  t.whole_ = PreparedCloud::prepare(golden, whole_settings(recipe));
  for (const auto& region : recipe.regions) {
    // A little beyond the ROI so that ICP sees the surface the region sits on.
    const Cloud roi = crop_box(golden, Transform::Identity(), box_min(region, 2.0), box_max(region, 2.0));
    if (roi.size() < 20)
      throw UserError("recipe " + recipe.source.string() + ": region '" + region.name + "' has only " +
                      std::to_string(roi.size()) + " golden template points inside its ROI; check roi_center_mm and roi_size_mm");
    PrepareSettings ps;
    ps.features = false;
    ps.coarse_voxel = recipe.vision.coarse_voxel_mm;
    t.regions_.push_back(RegionTemplate{region, PreparedCloud::prepare(roi, ps)});
  }
  return t;
}

PartTemplate PartTemplate::load_or_build(const config::PartRecipe& recipe, const Cloud& golden_part,
                                         const std::string& golden_identity, bool* from_cache) {
  if (from_cache != nullptr) *from_cache = false;
  if (!recipe.vision.cache || recipe.source.empty()) return build(recipe, golden_part);
  const auto dir = recipe.source.parent_path() / ("." + recipe.source.stem().string() + ".vision-cache");
  const std::string key = cache_key(recipe, golden_identity, golden_part.size());
  std::error_code ec;
  {
    std::ifstream in(dir / "key.txt");
    std::string stored((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    if (stored == key) {
      PartTemplate t;
      auto whole = PreparedCloud::load(dir / "whole.bin");
      bool ok = whole.has_value();
      if (ok) t.whole_ = *whole;
      for (std::size_t i = 0; ok && i < recipe.regions.size(); ++i) {
        auto r = PreparedCloud::load(dir / ("region-" + std::to_string(i) + ".bin"));
        ok = r.has_value();
        if (ok) t.regions_.push_back(RegionTemplate{recipe.regions[i], *r});
      }
      if (ok) {
        if (from_cache != nullptr) *from_cache = true;
        return t;
      }
    }
  }
  PartTemplate t = build(recipe, golden_part);
  std::filesystem::create_directories(dir, ec);
  if (ec) {
    log::get("vision")->warn("cannot create template cache {}: {}", dir.string(), ec.message());
    return t;
  }
  try {
    t.whole_.save(dir / "whole.bin");
    for (std::size_t i = 0; i < t.regions_.size(); ++i) t.regions_[i].cloud.save(dir / ("region-" + std::to_string(i) + ".bin"));
    std::ofstream(dir / "key.txt") << key;
  } catch (const UserError& e) {
    log::get("vision")->warn("template cache not written: {}", e.what());
  }
  return t;
}

Transform nominal_T_fixture_part(const config::PartRecipe& recipe) {
  const auto& f = recipe.fixture;
  Transform T = Transform::Identity();
  T.linear() = (Eigen::AngleAxisd(deg_to_rad(f.rotation_deg[2]), Vec3::UnitZ()) *
                Eigen::AngleAxisd(deg_to_rad(f.rotation_deg[1]), Vec3::UnitY()) *
                Eigen::AngleAxisd(deg_to_rad(f.rotation_deg[0]), Vec3::UnitX()))
                   .toRotationMatrix();
  T.translation() = Vec3(f.position_mm[0], f.position_mm[1], f.position_mm[2]);
  return T;
}

Result<Inspection> inspect(const config::PartRecipe& recipe, const PartTemplate& templ, const Cloud& scan,
                           const Transform& T_fixture_scan) {
  const auto t0 = std::chrono::steady_clock::now();
  const auto& vs = recipe.vision;
  if (scan.empty()) return Error{"vision.empty_scan", "the scan has no valid points"};
  const double extent = bounds(scan).diagonal();
  if (extent < 5.0)
    return Error{"vision.units", "the scan spans only " + std::to_string(extent) +
                                     " units: it looks like metres, Fettle expects millimetres (scale it by 1000)"};
  // 1. Preprocessing in the fixture frame: pass-through box, outliers.
  Cloud scene = transformed(scan, T_fixture_scan);
  scene.normals.clear();
  scene = crop_box(scene, Transform::Identity(), Eigen::Vector3d(vs.crop_min_mm[0], vs.crop_min_mm[1], vs.crop_min_mm[2]),
                   Eigen::Vector3d(vs.crop_max_mm[0], vs.crop_max_mm[1], vs.crop_max_mm[2]));
  if (scene.size() < static_cast<std::size_t>(vs.min_region_points))
    return Error{"vision.no_part", "only " + std::to_string(scene.size()) +
                                       " scan points inside the [vision] crop box: is the part on the fixture and the scan in the fixture frame?"};
  // Voxel first (cheap, centroid per voxel) so that the neighbour searches run on fewer points.
  const double spacing_voxel = std::max(0.5 * templ.whole().fine_spacing(), 0.05);
  scene = voxel_downsample(scene, spacing_voxel);
  scene = remove_statistical_outliers(scene, vs.outlier_neighbours, vs.outlier_std_ratio);
  // 2. Environment: the fixture plane (horizontal, at or below the part's bottom).
  if (vs.remove_plane) {
    PlaneSettings ps;
    ps.distance = vs.plane_distance_mm;
    ps.probability = vs.plane_probability;
    if (auto plane = fit_plane(scene, ps)) {
      const double nz = std::abs(plane->coefficients[2]);
      const double z0 = -plane->coefficients[3] / plane->coefficients[2];
      const double part_bottom = nominal_T_fixture_part(recipe).translation().z() + bounds(templ.whole().fine()).min.z();
      if (nz > 0.95 && z0 < part_bottom + 2.0 * vs.plane_distance_mm) scene = remove_indices(scene, plane->inliers);
    }
  }
  // 3. Coarse: FPFH + RANSAC bounded by the fixture prior; the prior itself is a candidate too.
  PrepareSettings ps = whole_settings(recipe);
  ps.fine_normal_neighbours = 8;
  Cloud scene_view = scene;
  estimate_normals(scene_view, 8, Eigen::Vector3f(0.0f, 0.0f, 2000.0f));  // camera above the fixture
  const auto prepared = PreparedCloud::prepare(scene_view, ps);
  const Transform prior_T = nominal_T_fixture_part(recipe);
  CoarseSettings cs;
  cs.max_iterations = vs.ransac_max_iterations;
  cs.prior = PosePrior{prior_T, recipe.fixture.position_tolerance_mm, deg_to_rad(recipe.fixture.rotation_tolerance_deg)};
  std::vector<Transform> candidates{prior_T};
  if (auto coarse = coarse_align(templ.whole(), prepared, cs)) candidates.insert(candidates.begin(), coarse->T_scene_template);
  FineSettings fs;
  fs.max_iterations = vs.icp_max_iterations;
  std::optional<Registration> best;
  // The whole-part ICP runs on the scene at the template's resolution; regions use all points.
  const Cloud scene_whole = voxel_downsample(scene, recipe.template_source.voxel_mm);
  for (const auto& c : candidates) {
    auto r = refine(templ.whole(), scene_whole, c, fs);
    if (r && (!best || r->fitness > best->fitness)) best = *r;
  }
  if (!best || best->fitness < 0.5 * vs.min_fitness)
    return Error{"vision.no_part", "the part was not found in the scan (best fitness " +
                                       std::to_string(best ? best->fitness : 0.0) +
                                       "): is it on the fixture, within the placement tolerance of the recipe?"};
  Inspection out;
  out.whole = *best;
  // 4. Per region: fine ICP on the region's own template, then excess material.
  for (const auto& rt : templ.regions()) {
    RegionResult rr;
    rr.name = rt.region.name;
    const Transform T_part_scene = out.whole.T_scene_template.inverse();
    const Cloud local = crop_box(scene, T_part_scene, box_min(rt.region, 2.0), box_max(rt.region, 2.0));
    rr.scene_points = local.size();
    if (local.size() < static_cast<std::size_t>(vs.min_region_points)) {
      rr.error = Error{"vision.too_few_points", "region '" + rr.name + "': only " + std::to_string(local.size()) +
                                                    " scan points in its ROI (needs " + std::to_string(vs.min_region_points) + ")"};
      out.regions.push_back(std::move(rr));
      continue;
    }
    FineSettings rfs = fs;
    rfs.max_distance = 2.0;
    auto r = refine(rt.cloud, local, out.whole.T_scene_template, rfs);
    if (!r) {
      rr.error = Error{r.error().code, "region '" + rr.name + "': " + r.error().message};
    } else {
      rr.registration = *r;
      if (r->fitness < vs.min_fitness)
        rr.error = Error{"vision.low_fitness", "region '" + rr.name + "': fitness " + std::to_string(r->fitness) +
                                                   " below min_fitness " + std::to_string(vs.min_fitness)};
      ExcessSettings es;
      es.threshold_mm = rt.region.excess_threshold_mm;
      es.min_cluster_points = vs.excess_min_cluster_points;
      const Cloud local_part = transformed(local, r->T_scene_template.inverse());
      const Cloud inside = crop_box(local_part, Transform::Identity(), box_min(rt.region, 0.0), box_max(rt.region, 0.0));
      rr.excess = measure_excess(rt.cloud, inside, es);
    }
    out.regions.push_back(std::move(rr));
  }
  out.scene_part = transformed(scene, out.whole.T_scene_template.inverse());
  out.deviation_mm = signed_distances(templ.whole(), out.scene_part.points);
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return out;
}

}  // namespace fettle::vision
