// Templates per recipe (cached) and the per-cycle vision stage.
#include "fettle/vision/inspect.hpp"

#include <chrono>
#include <cmath>
#include <fstream>
#include <limits>
#include <sstream>

#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/vision/plane.hpp"
#include "fettle/vision/preprocess.hpp"
#include "detail.hpp"
#include "prepared_impl.hpp"
#include "spatial.hpp"

namespace fettle::vision {

namespace {

/// Context around a region's ROI for its ICP template and scene crop (mm): a region's own
/// surface is often seen at grazing angles only (the flange wall from a camera above), the
/// surfaces next to it (the flange top, the plate around it) pin its pose. The excess is
/// still measured inside the ROI itself.
constexpr double kRegionContextMm = 10.0;
/// The whole part's last ICP, on the full-resolution scene: correspondences within this.
constexpr double kFullResolutionIcpMm = 1.0;
/// ICP (whole part and regions) gives no weight to scene points this far outside the template
/// (material) at its final distance...
constexpr double kTrimOutsideMm = 0.3;
/// ...nor to scene points this near such a point (a fin's root).
constexpr double kMaterialNeighbourhoodMm = 1.5;
/// A region's own ICP takes no step along directions its surfaces do not fix
/// (FineSettings::degenerate_ratio). The boss, a cylinder on an 8-degree face: turning about
/// the face's normal has 5e-5 or less of the largest curvature, its sideways slides 1.8e-4 or
/// more (simulator, 50 seeds); free to turn about it, its own fit is pulled 0.09 deg (median,
/// worst 0.25) by its flash; kept at the whole part's turn, 0.019 deg (worst 0.081; test
/// VisionSimAccuracy.TheBossKeepsThePartsTurnAboutItsAxis).
constexpr double kDegenerateRatio = 1e-4;
/// The whole part's ICP takes only heights from faces flatter than this
/// (FineSettings::heights_only_slope_deg). Simulator, 16 seeds, with the castings' form
/// deviation (test VisionSimAccuracy, FETTLE_ACCURACY_FORM=1): 4 degrees (below the pump
/// body's 8-degree face) turns the part 0.12 degrees about z (median); 10-40 degrees
/// 0.05-0.06; 60 lets the worst region slide 0.18 mm without form deviation against 0.15-0.17.
constexpr double kHeightsOnlySlopeDeg = 40.0;
/// The last ICP uses every 8th scene point on those faces after its first iteration: the
/// vision stage takes about half the time (bench_vision: 0.92 s with all of them, 0.49 s so)
/// and the errors are the same or smaller (test VisionSimAccuracy; FineSettings::flat_sample).
constexpr int kFlatSample = 8;

/// Occluding edges (organized views only): where a face's pixels end at a range jump of more
/// than this, a point halfway between the last ray on the face and the first one past it is
/// on the face's edge within half a pixel (FineSettings::occluding_edges). A camera above the
/// part sees its tops and hardly a wall: the edges are what fix it sideways. The whole part's
/// last ICP with them, 50 simulator seeds (one view, form deviation off): worst region error
/// 0.042 mm / 0.018 deg, medians 0.020-0.027 mm / 0.003 deg; without them 0.166 mm / 0.055 deg,
/// 0.034-0.039 mm / 0.008 deg (docs/vision.md, "Occluding edges").
constexpr double kEdgeJumpMm = 2.0;
/// A pixel beside such a jump that no straight line through two pixels on one side of it
/// predicts within this (or a tenth of its jump) is mixed (mixed_pixels): on no surface.
constexpr double kMixedToleranceMm = 0.3;
/// Weight of an occluding-edge point against a scene point's. 50 seeds, worst region median
/// and worst (walls within 45 degrees of level): weight 0.5: 0.029 / 0.044 mm; 1: 0.036 /
/// 0.051 mm; 2: 0.040 / 0.056 mm; 4: 0.043 / 0.059 mm. An edge point is off by up to half a
/// pixel (0.13 mm at 600 mm), a scan point by sigma 0.05 mm.
constexpr double kOccludingEdgeWeight = 0.5;

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

/// What a cached template was built from. It names the inputs, not the code: bump the version
/// when build() or PreparedCloud::prepare() computes something else from the same inputs.
std::string cache_key(const config::PartRecipe& recipe, const std::string& golden_identity, std::size_t golden_points) {
  std::ostringstream k;
  k << "fettle-vision-cache 3\n" << golden_identity << "\n" << golden_points << "\n";
  k << recipe.template_source.voxel_mm << " " << recipe.vision.coarse_voxel_mm << " " << recipe.vision.feature_radius_mm << "\n";
  for (const auto& r : recipe.regions)
    k << r.name << " " << r.roi_center_mm[0] << " " << r.roi_center_mm[1] << " " << r.roi_center_mm[2] << " "
      << r.roi_size_mm[0] << " " << r.roi_size_mm[1] << " " << r.roi_size_mm[2] << "\n";
  return k.str();
}

}  // namespace

PartTemplate PartTemplate::build(const config::PartRecipe& recipe, const Cloud& golden_part, const Eigen::Vector3f& viewpoint) {
  const auto t0 = std::chrono::steady_clock::now();
  auto log = log::get("vision");
  require_millimetres(golden_part, "golden template of " + recipe.id);
  // Invalid points out first: non-finite ones, and (0, 0, 0) where a scan stores its invalid
  // pixels that way (more than one there: a single point at the part frame's origin is real).
  Cloud golden;
  {
    std::size_t zeros = 0;
    for (const auto& p : golden_part.points) zeros += p.isZero() ? 1 : 0;
    const bool drop_zeros = zeros > 1;
    const bool normals = golden_part.has_normals();
    for (std::size_t i = 0; i < golden_part.size(); ++i) {
      const auto& p = golden_part.points[i];
      if (!p.allFinite() || (drop_zeros && p.isZero())) continue;
      golden.points.push_back(p);
      if (normals) golden.normals.push_back(golden_part.normals[i]);
    }
    if (golden.size() != golden_part.size())
      log->info("golden template of {}: {} of {} points dropped as invalid (non-finite, or (0, 0, 0) x {})", recipe.id,
                golden_part.size() - golden.size(), golden_part.size(), drop_zeros ? zeros : 0);
  }
  // Downsampled before its normals are estimated: a golden scan with many duplicate points made
  // the neighbour searches quadratic (80 000 duplicates took 14 s, 500 000 points over 90 s;
  // test Inspect.ATemplateFromAGoldenWithDuplicatesBuildsInLinearTime). Normals are estimated on
  // the cloud at half the template's voxel, then it is downsampled to the voxel.
  const double voxel = recipe.template_source.voxel_mm;
  if (!golden.has_normals()) {
    golden = voxel_downsample(golden, voxel > 0 ? 0.5 * voxel : 0.25);
    log->info("golden template of {}: estimating normals on {} points", recipe.id, golden.size());
    estimate_normals(golden, 12, viewpoint);
  }
  golden = voxel_downsample(golden, voxel);
  log->info("golden template of {}: {} points at {} mm; preparing the whole part and {} regions", recipe.id, golden.size(),
            voxel, recipe.regions.size());
  PartTemplate t;
  t.whole_ = PreparedCloud::prepare(golden, whole_settings(recipe));
  for (const auto& region : recipe.regions) {
    // Beyond the ROI so that ICP sees the surfaces the region sits on (kRegionContextMm).
    const Cloud roi = crop_box(golden, Transform::Identity(), box_min(region, kRegionContextMm), box_max(region, kRegionContextMm));
    if (roi.size() < 20)
      throw UserError("recipe " + recipe.source.string() + ": region '" + region.name + "' has only " +
                      std::to_string(roi.size()) + " golden template points inside its ROI; check roi_center_mm and roi_size_mm");
    PrepareSettings ps;
    ps.features = false;
    ps.coarse_voxel = recipe.vision.coarse_voxel_mm;
    // Region ICP starts at 2 mm: a lookup grid answers its nearest-point queries.
    ps.nearest_grid_cell = recipe.template_source.voxel_mm > 0 ? recipe.template_source.voxel_mm : 0.5;
    ps.nearest_grid_band = 2.5;
    t.regions_.push_back(RegionTemplate{region, PreparedCloud::prepare(roi, ps)});
  }
  t.find_edges();
  log->info("golden template of {}: built in {:.1f} s", recipe.id,
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  return t;
}

void PartTemplate::find_edges() const {
  // inspect()'s ICP is edge-aware: find the templates' edges at load, not in the first cycle
  whole_.impl().find_edges();
  for (const auto& r : regions_) r.cloud.impl().find_edges();
}

PartTemplate PartTemplate::load_or_build(const config::PartRecipe& recipe, const Cloud& golden_part,
                                         const std::string& golden_identity, bool* from_cache,
                                         const std::filesystem::path& cache_dir) {
  if (from_cache != nullptr) *from_cache = false;
  std::filesystem::path dir = cache_dir;
  if (dir.empty() && recipe.vision.cache && !recipe.source.empty())
    dir = recipe.source.parent_path() / ("." + recipe.source.stem().string() + ".vision-cache");
  if (dir.empty()) return build(recipe, golden_part);
  // Every file carries the whole key and is read only with it: files that two processes with
  // different goldens wrote into one directory at once are never taken for one template.
  const std::string key = cache_key(recipe, golden_identity, golden_part.size());
  {
    PartTemplate t;
    auto whole = PreparedCloud::load(dir / "whole.bin", key);
    bool ok = whole.has_value();
    if (ok) t.whole_ = *whole;
    for (std::size_t i = 0; ok && i < recipe.regions.size(); ++i) {
      auto r = PreparedCloud::load(dir / ("region-" + std::to_string(i) + ".bin"), key);
      ok = r.has_value();
      if (ok) t.regions_.push_back(RegionTemplate{recipe.regions[i], *r});
    }
    if (ok) {
      if (from_cache != nullptr) *from_cache = true;
      t.find_edges();
      return t;
    }
  }
  PartTemplate t = build(recipe, golden_part);
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) {
    log::get("vision")->warn("cannot create template cache {}: {}", dir.string(), ec.message());
    return t;
  }
  try {
    t.whole_.save(dir / "whole.bin", key);
    for (std::size_t i = 0; i < t.regions_.size(); ++i)
      t.regions_[i].cloud.save(dir / ("region-" + std::to_string(i) + ".bin"), key);
    std::ofstream(dir / "key.txt") << key;  // for people: what the files were built from
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

namespace {

using Clock = std::chrono::steady_clock;

/// Wall time per stage, for the report and the bench.
class StageTimer {
 public:
  StageTimer() : t0_(Clock::now()), last_(t0_) {}
  void mark(const char* stage) {
    const auto now = Clock::now();
    stages_.emplace_back(stage, std::chrono::duration<double>(now - last_).count());
    last_ = now;
  }
  [[nodiscard]] double total() const { return std::chrono::duration<double>(Clock::now() - t0_).count(); }
  std::vector<std::pair<std::string, double>> take() { return std::move(stages_); }

 private:
  Clock::time_point t0_;
  Clock::time_point last_;
  std::vector<std::pair<std::string, double>> stages_;
};

struct Box {
  Eigen::Vector3f min;
  Eigen::Vector3f max;
  [[nodiscard]] bool contains(const Eigen::Vector3f& p) const {
    return p.x() >= min.x() && p.y() >= min.y() && p.z() >= min.z() && p.x() <= max.x() && p.y() <= max.y() &&
           p.z() <= max.z();
  }
};

Box crop_of(const config::VisionSettings& vs) {
  return {Eigen::Vector3d(vs.crop_min_mm[0], vs.crop_min_mm[1], vs.crop_min_mm[2]).cast<float>(),
          Eigen::Vector3d(vs.crop_max_mm[0], vs.crop_max_mm[1], vs.crop_max_mm[2]).cast<float>()};
}

/// Where the part can be (fixture frame): the template's box at the nominal placement, grown
/// by the placement tolerance of the fixture prior, within the [vision] crop box.
Box part_neighbourhood(const config::PartRecipe& recipe, const PartTemplate& templ) {
  const Bounds b = bounds(templ.whole().fine());
  const Transform T = nominal_T_fixture_part(recipe);
  Eigen::Vector3f lo = Eigen::Vector3f::Constant(std::numeric_limits<float>::max());
  Eigen::Vector3f hi = -lo;
  for (int k = 0; k < 8; ++k) {
    const Eigen::Vector3d c((k & 1) ? b.max.x() : b.min.x(), (k & 2) ? b.max.y() : b.min.y(), (k & 4) ? b.max.z() : b.min.z());
    const Eigen::Vector3f q = (T * c).cast<float>();
    lo = lo.cwiseMin(q);
    hi = hi.cwiseMax(q);
  }
  const double rot = std::min(deg_to_rad(recipe.fixture.rotation_tolerance_deg), 3.0);
  const auto margin = static_cast<float>(recipe.fixture.position_tolerance_mm + 2.0 * std::sin(rot / 2) * 0.5 * b.diagonal() + 5.0);
  const Box crop = crop_of(recipe.vision);
  return {(lo - Eigen::Vector3f::Constant(margin)).cwiseMax(crop.min), (hi + Eigen::Vector3f::Constant(margin)).cwiseMin(crop.max)};
}

/// The fixture plane (n.x + d = 0) fitted to a sample of the cropped scan, when it is the
/// fixture: horizontal and at or below the part's bottom.
std::optional<Eigen::Vector4f> fixture_plane(const config::PartRecipe& recipe, const PartTemplate& templ, const Cloud& sample) {
  const auto& vs = recipe.vision;
  if (!vs.remove_plane) return std::nullopt;
  PlaneSettings ps;
  ps.distance = vs.plane_distance_mm;
  ps.probability = vs.plane_probability;
  // Only points up to a little above the part's bottom can be the fixture: large faces of the
  // part itself (seen densely) must not win the RANSAC.
  const double part_bottom = nominal_T_fixture_part(recipe).translation().z() + bounds(templ.whole().fine()).min.z();
  const auto below = static_cast<float>(part_bottom + 5.0);
  Cloud low;
  for (const auto& p : sample.points)
    if (p.z() <= below) low.points.push_back(p);
  auto plane = fit_plane(low, ps);
  if (!plane) return std::nullopt;
  const double nz = std::abs(plane->coefficients[2]);
  if (nz <= 0.95) return std::nullopt;
  const double z0 = -plane->coefficients[3] / plane->coefficients[2];
  if (z0 >= part_bottom + 2.0 * vs.plane_distance_mm) return std::nullopt;
  return Eigen::Vector4f(plane->coefficients.cast<float>());
}

bool on_plane(const std::optional<Eigen::Vector4f>& plane, const Eigen::Vector3f& p, float distance) {
  return plane && std::abs(plane->head<3>().dot(p) + (*plane)[3]) <= distance;
}

double scene_voxel(const config::PartRecipe& recipe) { return recipe.template_source.voxel_mm > 0 ? recipe.template_source.voxel_mm : 0.5; }

/// An empty fixture, told apart from a wrong or misplaced part: almost nothing above the
/// fixture plane where the part should stand. The footprint is the template's top view at the
/// nominal placement, grown by the placement tolerance; "almost nothing" is fewer than a tenth
/// of the points the template shows from above (clamps and clutter stand beside the part).
std::optional<Error> empty_fixture(const config::PartRecipe& recipe, const PartTemplate& templ, const Cloud& scene) {
  const Transform T_fixture_part = nominal_T_fixture_part(recipe);
  const Eigen::Matrix3f R = T_fixture_part.linear().cast<float>();
  const Eigen::Vector3f t = T_fixture_part.translation().cast<float>();
  const auto& fine = templ.whole().fine();
  Eigen::Vector2f lo = Eigen::Vector2f::Constant(std::numeric_limits<float>::max()), hi = -lo;
  std::size_t seen_from_above = 0;
  for (std::size_t i = 0; i < fine.size(); ++i) {
    const Eigen::Vector3f q = R * fine.points[i] + t;
    lo = lo.cwiseMin(q.head<2>());
    hi = hi.cwiseMax(q.head<2>());
    if (i < fine.normals.size() && (R * fine.normals[i]).z() > 0.3f) ++seen_from_above;
  }
  const double extent = (hi - lo).norm();
  const auto grow = static_cast<float>(recipe.fixture.position_tolerance_mm +
                                       0.5 * extent * std::sin(deg_to_rad(recipe.fixture.rotation_tolerance_deg)));
  lo.array() -= grow;
  hi.array() += grow;
  // The template and the scene are both at the template's voxel size: comparable counts.
  std::size_t inside = 0;
  for (const auto& p : scene.points)
    if (p.x() >= lo.x() && p.x() <= hi.x() && p.y() >= lo.y() && p.y() <= hi.y()) ++inside;
  if (seen_from_above == 0 || inside * 10 >= seen_from_above) return std::nullopt;
  return Error{"vision.empty_fixture",
               "no part on the fixture: " + std::to_string(inside) + " scan points above the fixture plane where the part stands (the template shows about " +
                   std::to_string(seen_from_above) + " from above); place a part, or check the [fixture] position_mm of the recipe", ErrorKind::no_part};
}

/// How a region's excess is measured (inspect() and measure_region_excess()): the material
/// inside the ROI, the casting's face from its context too (a tool reaches beyond the ROI by its
/// radius); `face`: the casting's face to measure from, null: fitted on the scene.
ExcessSettings region_excess_settings(const config::PartRecipe& recipe, const RegionTemplate& rt,
                                      const FormOffset* face = nullptr) {
  ExcessSettings es;
  es.threshold_mm = rt.region.excess_threshold_mm;
  es.min_cluster_points = recipe.vision.excess_min_cluster_points;
  es.form_deviation_mm = recipe.vision.form_deviation_mm;
  es.face = face;
  es.material_min_mm = box_min(rt.region, 0.0).cast<float>();
  es.material_max_mm = box_max(rt.region, 0.0).cast<float>();
  return es;
}

/// Localisation, per-region ICP and excess on a preprocessed scene (fixture frame, voxelized
/// at the template resolution, outliers and fixture plane removed, near the part).
Result<Inspection> localise_and_measure(const config::PartRecipe& recipe, const PartTemplate& templ, Cloud&& scene,
                                        StageTimer& timer, const Cloud* edges = nullptr) {
  const auto& vs = recipe.vision;
  if (auto e = empty_fixture(recipe, templ, scene)) return *e;
  if (scene.size() < static_cast<std::size_t>(vs.min_region_points))
    return Error{"vision.no_part", "only " + std::to_string(scene.size()) +
                                       " scan points near the part's place on the fixture (after cropping, outlier and "
                                       "fixture-plane removal): is the part on the fixture and the scan in the fixture frame?", ErrorKind::wrong_part};
  // Coarse: FPFH + RANSAC bounded by the fixture prior. The scene's coarse cloud comes from
  // the same voxel hash; its normals are oriented towards the camera above the fixture.
  PrepareSettings ps = whole_settings(recipe);
  Cloud coarse = voxel_downsample(scene, vs.coarse_voxel_mm);
  const Eigen::Vector3f viewpoint(0.0f, 0.0f, 2000.0f);
  coarse.normals.resize(coarse.size());
  for (std::size_t i = 0; i < coarse.size(); ++i) coarse.normals[i] = (viewpoint - coarse.points[i]).normalized();
  const auto prepared = PreparedCloud::prepare(coarse, ps);
  timer.mark("scene normals + FPFH");
  const Transform prior_T = nominal_T_fixture_part(recipe);
  CoarseSettings cs;
  cs.max_iterations = vs.ransac_max_iterations;
  cs.prior = PosePrior{prior_T, recipe.fixture.position_tolerance_mm, deg_to_rad(recipe.fixture.rotation_tolerance_deg)};
  auto coarse_result = coarse_align(templ.whole(), prepared, cs);
  timer.mark("coarse RANSAC");
  // Whole part: ICP at a few mm resolution, from the coarse pose; the prior itself is the
  // fallback candidate when coarse matching failed or its ICP does not fit.
  FineSettings fs;
  fs.max_iterations = vs.icp_max_iterations;
  fs.edge_aware = true;
  // At the coarse voxel first (from the coarse pose up to 2x the voxel); a last stage at the
  // scene's full resolution follows (below).
  const double whole_voxel = std::max(2.0 * scene_voxel(recipe), vs.coarse_voxel_mm);
  const Cloud scene_whole = voxel_downsample(scene, whole_voxel);
  FineSettings wfs = fs;
  // Flash and risers are material the template does not have, always outside it (up to 4 mm
  // beside a wall): with plain least squares they pulled the whole part 0.3-0.7 mm sideways
  // (simulator, 3 seeds) and every region refined from there or planned on it inherited it.
  // Points more than 0.3 mm outside get no weight at the final distance. Tukey weights did
  // about as well sideways but down-weighted the grazing walls and left a 0.11 deg yaw
  // (8 seeds: whole-part error at the regions 0.13-0.17 mm median with Tukey).
  wfs.trim_outside_mm = kTrimOutsideMm;
  wfs.trim_neighbourhood_mm = kMaterialNeighbourhoodMm;
  wfs.heights_only_slope_deg = kHeightsOnlySlopeDeg;
  wfs.fitness_distance = std::max(whole_voxel, 3.0 * templ.whole().fine_spacing());
  std::optional<Registration> best;
  if (coarse_result) {
    if (auto r = refine(templ.whole(), scene_whole, coarse_result->T_scene_template, wfs)) best = *r;
  }
  if (!best || best->fitness < 0.5 * vs.min_fitness) {
    auto r = refine(templ.whole(), scene_whole, prior_T, wfs);
    if (r && (!best || r->fitness > best->fitness)) best = *r;
  }
  if (!best || best->fitness < 0.5 * vs.min_fitness)
    return Error{"vision.no_part", "the part was not found in the scan (best fitness " +
                                       std::to_string(best ? best->fitness : 0.0) +
                                       "): is it on the fixture, within the placement tolerance of the recipe?", ErrorKind::wrong_part};
  if (best->fitness < vs.min_part_fitness)
    return Error{"vision.no_match", "the scan does not match the part of recipe '" + recipe.id + "': whole-part fitness " +
                                        std::to_string(best->fitness) + " below [vision] min_part_fitness " +
                                        std::to_string(vs.min_part_fitness) +
                                        ": is it the right part (not the other hand of a pair), the right way round?", ErrorKind::wrong_part};
  Inspection out;
  out.whole = *best;
  timer.mark("whole-part ICP, voxel grid");
  {
    // Then at the scene's full resolution, from that pose: a part seen from above is fixed
    // sideways by its edges, and a 3 mm voxel's centroid at an edge is up to a millimetre off
    // the surface. With edge-aware residuals, the material's neighbourhood left out and heights
    // only from flat faces, the whole part's pose at the regions went from 0.043-0.094 mm and
    // 0.032 deg to 0.034-0.039 mm and 0.008 deg (median of 50 simulator seeds, form deviation
    // off). The fitness stays the 3 mm stage's: min_part_fitness is calibrated on it.
    FineSettings ffs = wfs;
    ffs.max_distance = kFullResolutionIcpMm;
    ffs.min_distance = kFullResolutionIcpMm;
    ffs.max_iterations = 12;
    ffs.flat_sample = kFlatSample;
    ffs.occluding_edges = edges;
    ffs.edge_weight = kOccludingEdgeWeight;
    if (auto r = refine(templ.whole(), scene, best->T_scene_template, ffs)) {
      out.whole.T_scene_template = r->T_scene_template;
      out.whole.iterations += r->iterations;
      out.whole.converged = r->converged;
    }
  }
  timer.mark("whole-part ICP, full resolution");
  // Per region: fine ICP on the region's own template at the scene's full (template)
  // resolution, then the excess material.
  const Transform T_part_scene = out.whole.T_scene_template.inverse();
  for (const auto& rt : templ.regions()) {
    RegionResult rr;
    rr.name = rt.region.name;
    const Cloud local = crop_box(scene, T_part_scene, box_min(rt.region, kRegionContextMm), box_max(rt.region, kRegionContextMm));
    rr.scene_points = local.size();
    if (local.size() < static_cast<std::size_t>(vs.min_region_points)) {
      rr.error = Error{"vision.too_few_points", "region '" + rr.name + "': only " + std::to_string(local.size()) +
                                                    " scan points in its ROI (needs " + std::to_string(vs.min_region_points) + ")"};
      out.regions.push_back(std::move(rr));
      continue;
    }
    FineSettings rfs = fs;
    rfs.max_distance = 2.0;
    // Material is trimmed as in the whole part's ICP (points more than 0.3 mm outside, and
    // their 1.5 mm neighbourhood): with Tukey weights instead, the boss's flash (a ring with
    // gaps) pulls its fit 0.16 mm sideways (median, 50 seeds); trimmed, 0.034 mm on 16 seeds
    // (Tukey and trimming together: 0.056 mm).
    rfs.trim_outside_mm = kTrimOutsideMm;
    rfs.trim_neighbourhood_mm = kMaterialNeighbourhoodMm;
    rfs.degenerate_ratio = kDegenerateRatio;
    // The region's fitness counts the template surface the camera could see: not walls facing
    // away from it, and for a riser not the pad under it (counted as misses, they hold the
    // riser region's fitness at a good pose to 0.51-0.59 on most simulated castings). Only
    // risers: leaving covered points out can raise a wrong (sunk) pose's fitness up to twice
    // its share of matched points, and a flash covers too little of its template to need it.
    rfs.viewpoint = viewpoint;
    if (rt.region.type == config::RegionType::riser)
      rfs.covered_mm = *std::max_element(rt.region.roi_size_mm.begin(), rt.region.roi_size_mm.end());
    // pose = "part": the whole part's pose (no iteration), its fitness measured on the region's
    // template as the region's own fit would be
    const bool part_pose = rt.region.pose == config::RegionPose::part;
    if (part_pose) rfs.max_iterations = 0;
    auto r = refine(rt.cloud, local, out.whole.T_scene_template, rfs);
    if (r && part_pose) r->converged = true;
    if (!r) {
      rr.error = Error{r.error().code, "region '" + rr.name + "': " + r.error().message, r.error().kind};
    } else {
      rr.registration = *r;
      if (r->fitness < vs.min_fitness)
        rr.error = Error{"vision.low_fitness", "region '" + rr.name + "': fitness " + std::to_string(r->fitness) +
                                                   " below min_fitness " + std::to_string(vs.min_fitness), ErrorKind::wrong_part};
      rr.excess = measure_excess(rt.cloud, transformed(local, r->T_scene_template.inverse()), region_excess_settings(recipe, rt));
    }
    out.regions.push_back(std::move(rr));
  }
  timer.mark("regions: ICP + excess");
  out.scene_part = transformed(scene, T_part_scene);
  out.deviation_mm = signed_distances(templ.whole(), out.scene_part.points);
  timer.mark("deviation map");
  out.seconds = timer.total();
  out.stage_seconds = timer.take();
  return out;
}

std::optional<Error> check_extent(const Bounds& b) {
  const double extent = b.diagonal();
  if (extent < 5.0)
    return Error{"vision.units", "the scan spans only " + std::to_string(extent) +
                                     " units: it looks like metres, Fettle expects millimetres (scale it by 1000)"};
  return std::nullopt;
}

}  // namespace

ExcessMaterial measure_region_excess(const config::PartRecipe& recipe, const RegionTemplate& rt, const Cloud& scene_part,
                                     const Transform& T_part_region, const FormOffset* face) {
  const Transform T_region_part = T_part_region.inverse();
  const Cloud local = crop_box(scene_part, T_region_part, box_min(rt.region, kRegionContextMm), box_max(rt.region, kRegionContextMm));
  return measure_excess(rt.cloud, transformed(local, T_region_part), region_excess_settings(recipe, rt, face));
}

Result<Inspection> inspect(const config::PartRecipe& recipe, const PartTemplate& templ, const Cloud& scan,
                           const Transform& T_fixture_scan) {
  StageTimer timer;
  const auto& vs = recipe.vision;
  if (scan.empty()) return Error{"vision.empty_scan", "the scan has no valid points", ErrorKind::no_part};
  if (auto e = check_extent(bounds(scan))) return *e;
  // 1. Pass-through crop in the fixture frame (one pass, no copy of the scan): the crop box
  //    for the plane sample, the part's neighbourhood for everything else.
  const Box crop = crop_of(vs);
  const Box near = part_neighbourhood(recipe, templ);
  const Eigen::Matrix3f R = T_fixture_scan.rotation().cast<float>();
  const Eigen::Vector3f t = T_fixture_scan.translation().cast<float>();
  Cloud inside;
  Cloud sample;
  std::size_t in_crop = 0;
  for (const auto& p : scan.points) {
    const Eigen::Vector3f q = R * p + t;
    if (!crop.contains(q)) continue;
    if (in_crop++ % 8 == 0) sample.points.push_back(q);
    if (near.contains(q)) inside.points.push_back(q);
  }
  if (in_crop < static_cast<std::size_t>(vs.min_region_points))
    return Error{"vision.no_part", "only " + std::to_string(in_crop) +
                                       " scan points inside the [vision] crop box: is the part on the fixture and the scan in the fixture frame?", ErrorKind::no_part};
  // 2. Voxel grid (centroid per voxel) first, so that outlier removal searches fewer points.
  Cloud scene = voxel_downsample(inside, scene_voxel(recipe));
  inside = Cloud{};
  timer.mark("crop + voxel");
  scene = remove_statistical_outliers(scene, vs.outlier_neighbours, vs.outlier_std_ratio);
  timer.mark("outlier removal");
  // 3. Environment: the fixture plane, fitted on a sample of the whole crop box.
  if (const auto plane = fixture_plane(recipe, templ, sample)) {
    Cloud off;
    off.points.reserve(scene.size());
    for (const auto& p : scene.points)
      if (!on_plane(plane, p, static_cast<float>(vs.plane_distance_mm))) off.points.push_back(p);
    scene = std::move(off);
  }
  timer.mark("plane removal");
  return localise_and_measure(recipe, templ, std::move(scene), timer);
}

Result<Inspection> inspect(const config::PartRecipe& recipe, const PartTemplate& templ, const OrganizedCloud& scan,
                           const Transform& T_fixture_camera) {
  return inspect(recipe, templ, std::vector<OrganizedView>{{&scan, T_fixture_camera}});
}

Result<Inspection> inspect(const config::PartRecipe& recipe, const PartTemplate& templ,
                           const std::vector<OrganizedView>& views) {
  StageTimer timer;
  const auto& vs = recipe.vision;
  if (views.empty()) return Error{"vision.no_views", "no view to inspect"};
  for (std::size_t i = 0; i < views.size(); ++i) {
    const OrganizedCloud* scan = views[i].cloud;
    if (scan == nullptr || scan->width * scan->height != scan->size() || scan->size() == 0)
      return Error{"vision.empty_scan", "view " + std::to_string(i) + ": the organized scan is empty or its size (" +
                                            std::to_string(scan ? scan->size() : 0) + ") is not width x height (" +
                                            std::to_string(scan ? scan->width : 0) + " x " +
                                            std::to_string(scan ? scan->height : 0) + ")", ErrorKind::no_part};
  }
  const Box crop = crop_of(vs);
  const Box near = part_neighbourhood(recipe, templ);
  const int threads = detail::thread_count(0);
  // 1. Image space, one pass over each view's pixels: validity, the pass-through crop, and the
  //    statistical outlier measure (mean distance to the valid pixels of a small window), whose
  //    mean and spread are each view's own (the views see the part at different distances).
  const int k = std::max(1, vs.outlier_neighbours);
  const int r = std::max(1, static_cast<int>(std::ceil((std::sqrt(k + 1.0) - 1.0) / 2.0)));
  struct Stats {
    double sum = 0, sum2 = 0;
    std::size_t n = 0, valid = 0;
    Eigen::Vector3f lo = Eigen::Vector3f::Constant(std::numeric_limits<float>::max());
    Eigen::Vector3f hi = Eigen::Vector3f::Constant(-std::numeric_limits<float>::max());
  };
  std::vector<std::vector<float>> mean_dist(views.size());
  std::vector<float> limit(views.size(), 0.0f);
  std::size_t valid = 0, measured = 0;
  Cloud edges;
  Eigen::Vector3f lo = Eigen::Vector3f::Constant(std::numeric_limits<float>::max());
  Eigen::Vector3f hi = -lo;
  // Each view's occluding edges (FineSettings::occluding_edges), found past its mixed pixels.
  // The mixed pixels themselves stay in the scene: dropping them (both those in the air and
  // those inside the solid) let the part slide more: worst region median 0.040 against
  // 0.036 mm (50 seeds, edge weight 1).
  for (const auto& view : views) {
    const OrganizedCloud& scan = *view.cloud;
    const Eigen::Matrix3f R = view.T_fixture_camera.rotation().cast<float>();
    const Eigen::Vector3f t = view.T_fixture_camera.translation().cast<float>();
    for (const auto& p : occluding_edges(scan, kEdgeJumpMm, kMixedToleranceMm).points) {
      const Eigen::Vector3f q = R * p + t;
      if (near.contains(q)) edges.points.push_back(q);
    }
  }
  timer.mark("occluding edges");
  for (std::size_t i = 0; i < views.size(); ++i) {
    const OrganizedCloud& scan = *views[i].cloud;
    const std::size_t w = scan.width;
    const std::size_t h = scan.height;
    const Eigen::Matrix3f R = views[i].T_fixture_camera.rotation().cast<float>();
    const Eigen::Vector3f t = views[i].T_fixture_camera.translation().cast<float>();
    auto& md = mean_dist[i];
    md.assign(scan.size(), -1.0f);
    std::vector<Stats> stats(static_cast<std::size_t>(threads));
    detail::parallel_for(h, threads, [&](std::size_t th, std::size_t b, std::size_t e) {
      Stats& st = stats[th];
      for (std::size_t v = b; v < e; ++v) {
        for (std::size_t u = 0; u < w; ++u) {
          const Eigen::Vector3f& p = scan.points[v * w + u];
          if (!p.allFinite()) continue;
          ++st.valid;
          st.lo = st.lo.cwiseMin(p);
          st.hi = st.hi.cwiseMax(p);
          if (!near.contains(R * p + t)) continue;
          float s = 0.0f;
          int n = 0;
          for (std::size_t vv = v >= static_cast<std::size_t>(r) ? v - r : 0; vv <= std::min(h - 1, v + r); ++vv)
            for (std::size_t uu = u >= static_cast<std::size_t>(r) ? u - r : 0; uu <= std::min(w - 1, u + r); ++uu) {
              const Eigen::Vector3f& q = scan.points[vv * w + uu];
              if ((vv == v && uu == u) || !q.allFinite()) continue;
              s += (q - p).norm();
              ++n;
            }
          const float m = n > 0 ? s / static_cast<float>(n) : std::numeric_limits<float>::infinity();
          md[v * w + u] = m;
          if (n > 0) {
            st.sum += m;
            st.sum2 += static_cast<double>(m) * m;
            ++st.n;
          }
        }
      }
    }, 16);
    Stats all;
    for (const auto& st : stats) {
      all.sum += st.sum;
      all.sum2 += st.sum2;
      all.n += st.n;
      all.valid += st.valid;
      all.lo = all.lo.cwiseMin(st.lo);
      all.hi = all.hi.cwiseMax(st.hi);
    }
    valid += all.valid;
    measured += all.n;
    if (all.valid > 0) lo = lo.cwiseMin(all.lo), hi = hi.cwiseMax(all.hi);
    const double mean = all.n > 0 ? all.sum / static_cast<double>(all.n) : 0.0;
    const double sd = all.n > 1 ? std::sqrt(std::max(0.0, all.sum2 / static_cast<double>(all.n) - mean * mean)) : 0.0;
    limit[i] = static_cast<float>(mean + vs.outlier_std_ratio * sd);
  }
  if (valid == 0) return Error{"vision.empty_scan", "the scan has no valid points (every pixel is NaN)", ErrorKind::no_part};
  if (auto e = check_extent(Bounds{lo, hi})) return *e;
  timer.mark("outlier removal");
  // 2. The fixture plane from a sample of the pixels in the crop box (every 8th row and column
  //    of every view).
  Cloud sample;
  for (const auto& view : views) {
    const OrganizedCloud& scan = *view.cloud;
    const Eigen::Matrix3f R = view.T_fixture_camera.rotation().cast<float>();
    const Eigen::Vector3f t = view.T_fixture_camera.translation().cast<float>();
    for (std::size_t v = 0; v < scan.height; v += 8)
      for (std::size_t u = 0; u < scan.width; u += 8) {
        const Eigen::Vector3f& p = scan.points[v * scan.width + u];
        if (!p.allFinite()) continue;
        const Eigen::Vector3f q = R * p + t;
        if (crop.contains(q)) sample.points.push_back(q);
      }
  }
  if (sample.size() < static_cast<std::size_t>(vs.min_region_points) / 64 + 3)
    return Error{"vision.no_part", "only about " + std::to_string(sample.size() * 64) +
                                       " scan points inside the [vision] crop box: is the part on the fixture and the scan in the fixture frame?", ErrorKind::no_part};
  const auto plane = fixture_plane(recipe, templ, sample);
  timer.mark("plane removal");
  // 3. The kept pixels of every view into one voxel grid (a hash per thread, merged): where
  //    views overlap, a voxel holds the centroid of all their points (one surface, no doubled
  //    layer).
  const auto plane_distance = static_cast<float>(vs.plane_distance_mm);
  std::vector<detail::VoxelAccumulator> acc;
  const std::size_t expected_voxels = measured / static_cast<std::size_t>(threads) / 2;
  for (int th = 0; th < threads; ++th) acc.emplace_back(scene_voxel(recipe), expected_voxels);
  for (std::size_t i = 0; i < views.size(); ++i) {
    const OrganizedCloud& scan = *views[i].cloud;
    const Eigen::Matrix3f R = views[i].T_fixture_camera.rotation().cast<float>();
    const Eigen::Vector3f t = views[i].T_fixture_camera.translation().cast<float>();
    const auto& md = mean_dist[i];
    const float lim = limit[i];
    detail::parallel_for(scan.height, threads, [&](std::size_t th, std::size_t b, std::size_t e) {
      for (std::size_t j = b * scan.width; j < e * scan.width; ++j) {
        if (!(md[j] >= 0.0f && md[j] <= lim)) continue;
        const Eigen::Vector3f q = R * scan.points[j] + t;
        if (!on_plane(plane, q, plane_distance)) acc[th].add(q);
      }
    }, 16);
  }
  for (std::size_t th = 1; th < acc.size(); ++th) acc[0].merge(acc[th]);
  Cloud scene;
  acc[0].write(scene.points);
  timer.mark("voxel grid");
  {
    Cloud off;
    for (const auto& p : edges.points)
      if (!on_plane(plane, p, plane_distance)) off.points.push_back(p);
    edges = std::move(off);
  }
  return localise_and_measure(recipe, templ, std::move(scene), timer, &edges);
}

}  // namespace fettle::vision
