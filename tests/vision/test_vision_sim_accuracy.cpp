// Accuracy of the vision stage on the simulator's ground truth (issue 4): seeded pump-body
// castings placed within +-3 mm / +-3 degrees on the fixture, scanned with the default
// 3.2 MP scanner (sigma_z 0.05 mm, dropouts, flying pixels, outliers), inspected through the
// organized-cloud path. Per region: pose error (at the region's ROI centre) median <= 0.05 mm
// and <= 0.05 degrees, worst <= 0.1 mm and <= 0.1 degrees, every region found; the riser's
// excess volume within 5 % of the truth.
//
// Seeds: FETTLE_ACCURACY_SEEDS (default 8; ctest and `make accuracy-vision` run 50).
//
// FETTLE_ACCURACY_VERBOSE=1 prints every seed's region and whole-part errors, and the riser's
// measured and true excess volume and footprint.
//
// FETTLE_ACCURACY_FORM=1 keeps the recipe's form deviation (the assertions then do not hold:
// a region's true pose is no longer the part's). It prints, per region, how far the region's
// template lands from the casting's true (deformed, material-free) surface, placed with the
// region's pose and with the whole part's: the measure for choosing `pose = "part"`.
//
// FETTLE_ACCURACY_GROUND=1 removes every bit of flash and riser first (an oracle grind): it
// separates the pull of the material from the scanner's errors.
//
// FETTLE_ACCURACY_RESIDUALS=1 prints, per seed, how far the data itself pins the pose: the
// residuals of the points near the golden body at the TRUE pose, per surface class (top,
// walls by the way they face, slant: edges and roundings), and the error of an ideal fit: the
// rigid correction a point-to-plane fit on the exact golden surface makes from the true pose
// (points more than 0.3 mm outside trimmed, as the whole-part ICP trims). Once for the
// preprocessed scene the ICP sees, once for the raw capture (FETTLE_ACCURACY_VIEW2=<slide mm>
// adds a second view's raw points). With FETTLE_ACCURACY_GROUND=1 (no material) that is the
// scanner's bound: no fit of those points does better than their ideal fit. (With material
// the ideal fit is pulled by the material too.)
//
// FETTLE_ACCURACY_FIRST=<seed>: start at this seed (default 1).
//
// FETTLE_ACCURACY_VIEWS2=<slide mm>: a second view at this slide position, both inspected as
// fettled does with two photo positions: organized, at the slide's poses refined on the
// overlap (register_views). FETTLE_ACCURACY_UNORGANIZED=1: the view(s) through the unorganized
// path instead (two views: fuse_views first). The unorganized path (voxel grid, then k-nearest
// outlier removal on the voxels) costs accuracy, the fusion does not (figures in
// docs/vision.md, "Not done yet").
//
// Run by ctest on 50 seeds (8 under the sanitizers; tests/vision/CMakeLists.txt). The worst
// case is met because the whole part's last ICP also measures the scan's occluding edges:
// without them the whole part's yaw, times the lever arm to the riser, puts the riser up to
// 0.17 mm off (docs/vision.md, "Occluding edges"; the latest figures in docs/results.md).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "fettle/config/load.hpp"
#include "fettle/sim/sim.hpp"
#include "fettle/vision/inspect.hpp"
#include "fettle/vision/multiview.hpp"
#include "test_support.hpp"

using namespace fettle::vision;
using fettle::Transform;
using fettle::Vec3;

namespace {

int seed_count() {
  const char* env = std::getenv("FETTLE_ACCURACY_SEEDS");
  const int n = env != nullptr ? std::atoi(env) : 8;
  return std::max(1, n);
}

fettle::config::PartRecipe accuracy_recipe() {
  auto recipe = fettle::config::load_part(FETTLE_SOURCE_DIR "/config/parts/pump-body.toml");
  recipe.vision.cache = false;
  // The placement is what the test varies (+-3 mm, +-3 degrees: the shipped values). The
  // body's smooth form deviation (+-0.2 mm over 90-200 mm waves) is left out: it tilts a
  // region's surface by up to ~0.5 degrees against the part frame, so a region's "true pose"
  // would not be the part's pose any more.
  if (std::getenv("FETTLE_ACCURACY_FORM") == nullptr) recipe.geometry.variation.form_deviation_mm = 0.0;
  return recipe;
}

PartTemplate golden_template(const fettle::config::PartRecipe& recipe) {
  const auto golden = fettle::sim::Casting::golden(recipe);
  Cloud cloud;
  for (const auto& s : golden.sample_golden_surface(0.25)) {
    cloud.points.push_back(s.position_mm);
    cloud.normals.push_back(s.normal);
  }
  return PartTemplate::build(recipe, cloud);
}

struct ClassStats {
  double sum = 0, sum2 = 0;
  long n = 0;
};

/// The residuals and the ideal fit of FETTLE_ACCURACY_RESIDUALS (see the top of the file).
struct IdealFit {
  std::map<std::string, ClassStats> classes;
  Transform T_part_template = Transform::Identity();  ///< the golden moved onto the points
};

IdealFit ideal_fit(const fettle::sim::Casting& casting, const std::vector<Vec3>& points_part) {
  IdealFit out;
  Eigen::Matrix<double, 6, 6> A = Eigen::Matrix<double, 6, 6>::Zero();
  Eigen::Matrix<double, 6, 1> b = Eigen::Matrix<double, 6, 1>::Zero();
  for (const Vec3& p : points_part) {
    const double d = casting.golden_sdf_mm(p);
    if (!(std::abs(d) <= 1.0)) continue;
    Vec3 g;
    for (int k = 0; k < 3; ++k) {
      Vec3 h = Vec3::Zero();
      h(k) = 0.05;
      g(k) = (casting.golden_sdf_mm(p + h) - casting.golden_sdf_mm(p - h)) / 0.1;
    }
    if (!(g.norm() > 0.5)) continue;
    g.normalize();
    const char* cls = g.z() > 0.999                       ? "top"
                      : g.z() > 0.9                       ? "shallow"
                      : g.z() < -0.9                      ? "bottom"
                      : std::abs(g.z()) >= 0.3            ? "slant"
                      : std::abs(g.x()) > std::abs(g.y()) ? (g.x() > 0 ? "wall+x" : "wall-x")
                                                          : (g.y() > 0 ? "wall+y" : "wall-y");
    auto& c = out.classes[cls];
    c.sum += d, c.sum2 += d * d, ++c.n;
    if (d > 0.3) continue;
    Eigen::Matrix<double, 6, 1> J;
    J.head<3>() = p.cross(g);
    J.tail<3>() = g;
    A += J * J.transpose();
    b -= J * d;
  }
  const Eigen::Matrix<double, 6, 1> x = A.ldlt().solve(b);  // moves the points onto the golden
  Transform C = Transform::Identity();
  if (x.head<3>().norm() > 0) C.linear() = Eigen::AngleAxisd(x.head<3>().norm(), x.head<3>().normalized()).toRotationMatrix();
  C.translation() = x.tail<3>();
  out.T_part_template = C.inverse();
  return out;
}

void print_classes(int seed, const char* what, const IdealFit& f) {
  std::printf("seed %d %s residuals at the true pose (mm):", seed, what);
  for (const auto& [cls, c] : f.classes) {
    const double mean = c.sum / static_cast<double>(c.n);
    std::printf("  %s %.3f+-%.3f (%ld)", cls.c_str(), mean,
                std::sqrt(std::max(0.0, c.sum2 / static_cast<double>(c.n) - mean * mean)), c.n);
  }
  std::printf("\n");
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

}  // namespace

TEST(VisionSimAccuracy, SeededCastingsArePlacedWithin50MicronsAndFiveHundredthsOfADegree) {
  const auto recipe = accuracy_recipe();
  ASSERT_DOUBLE_EQ(recipe.geometry.variation.placement_tolerance_mm, 3.0);
  ASSERT_DOUBLE_EQ(recipe.geometry.variation.placement_tolerance_deg, 3.0);
  const auto templ = golden_template(recipe);
  fettle::sim::ScannerConfig sc;
  ASSERT_DOUBLE_EQ(sc.noise.sigma_z_mm, 0.05);
  const fettle::sim::Scanner scanner{sc};

  const int seeds = seed_count();
  std::map<std::string, std::vector<double>> err_mm;
  std::map<std::string, std::vector<double>> err_deg;
  std::map<std::string, std::vector<double>> whole_mm, whole_deg;
  std::vector<double> all_mm;
  std::vector<double> all_deg;
  std::vector<double> riser_volume_error;
  std::map<std::string, std::vector<double>> surface_region_mm, surface_whole_mm;
  int failures = 0;
  const char* first_env = std::getenv("FETTLE_ACCURACY_FIRST");
  const int first = first_env != nullptr ? std::max(1, std::atoi(first_env)) : 1;
  for (int seed = first; seed < first + seeds; ++seed) {
    auto casting = fettle::sim::Casting::make(recipe, static_cast<std::uint64_t>(seed));
    if (std::getenv("FETTLE_ACCURACY_GROUND") != nullptr) casting.remove_all_material();
    const auto capture = scanner.capture(casting, 0.0);
    std::optional<fettle::sim::Casting> body;  // FETTLE_ACCURACY_FORM: the casting without its material
    if (std::getenv("FETTLE_ACCURACY_FORM") != nullptr) {
      body = casting;
      body->remove_all_material();
    }
    const auto r = [&]() -> fettle::Result<Inspection> {
      const char* v2 = std::getenv("FETTLE_ACCURACY_VIEWS2");
      if (v2 == nullptr && std::getenv("FETTLE_ACCURACY_UNORGANIZED") != nullptr)
        return inspect(recipe, templ, transformed(to_cloud(capture.cloud), capture.truth.T_base_camera));
      if (v2 == nullptr) return inspect(recipe, templ, capture.cloud, capture.truth.T_base_camera);
      // the cell's way with two photo positions (as fettled's pipeline): both organized views at
      // the slide's poses refined on their overlap, or with FETTLE_ACCURACY_UNORGANIZED fused first
      const auto second = scanner.capture(casting, std::atof(v2), 1);
      if (std::getenv("FETTLE_ACCURACY_UNORGANIZED") == nullptr) {
        const std::vector<OrganizedView> calibrated{{&capture.cloud, capture.truth.T_base_camera},
                                                    {&second.cloud, second.truth.T_base_camera}};
        auto refined = register_views(calibrated, FuseSettings{});
        if (!refined) return refined.error();
        return inspect(recipe, templ, *refined);
      }
      std::vector<View> views(2);
      views[0].cloud = to_cloud(capture.cloud);
      views[1].cloud = to_cloud(second.cloud);
      views[1].T_first_view = capture.truth.T_base_camera.inverse() * second.truth.T_base_camera;
      auto fused = fuse_views(views, FuseSettings{});
      if (!fused) return fused.error();
      return inspect(recipe, templ, transformed(fused->cloud, capture.truth.T_base_camera));
    }();
    if (!r) {
      ADD_FAILURE() << "seed " << seed << ": " << r.error().message;
      ++failures;
      continue;
    }
    ASSERT_EQ(r->regions.size(), recipe.regions.size());
    if (std::getenv("FETTLE_ACCURACY_RESIDUALS") != nullptr) {
      const Transform T_part_base = capture.truth.T_base_part.inverse();
      std::vector<Vec3> pre;  // the preprocessed scene, part frame at the true pose
      for (const auto& q : r->scene_part.points) pre.push_back(T_part_base * (r->whole.T_scene_template * q.cast<double>()));
      std::vector<Vec3> raw;
      std::vector<fettle::sim::Capture> views{capture};
      if (const char* v2 = std::getenv("FETTLE_ACCURACY_VIEW2")) views.push_back(scanner.capture(casting, std::atof(v2), 1));
      for (const auto& view : views) {
        const Transform T_part_camera = T_part_base * view.truth.T_base_camera;
        for (std::size_t k = 0; k < view.cloud.size(); ++k)
          if (view.cloud.is_valid(k)) raw.push_back(T_part_camera * view.cloud.points[k].cast<double>());
      }
      const auto fit_pre = ideal_fit(casting, pre), fit_raw = ideal_fit(casting, raw);
      print_classes(seed, "preprocessed scene", fit_pre);
      print_classes(seed, views.size() > 1 ? "raw capture (two views)" : "raw capture", fit_raw);
      for (std::size_t i = 0; i < recipe.regions.size(); ++i) {
        const auto& roi = recipe.regions[i].roi_center_mm;
        const Vec3 c(roi[0], roi[1], roi[2]);
        const auto& T = capture.truth.T_base_part;
        const auto a = test::pose_error_at(T * fit_pre.T_part_template, T, c);
        const auto b = test::pose_error_at(T * fit_raw.T_part_template, T, c);
        const auto w = test::pose_error_at(r->whole.T_scene_template, T, c);
        std::printf("seed %d %-18s ideal fit: preprocessed %.4f mm %.4f deg, raw %.4f mm %.4f deg; whole-part ICP %.4f mm %.4f deg\n",
                    seed, recipe.regions[i].name.c_str(), a.translation, fettle::rad_to_deg(a.rotation_rad), b.translation,
                    fettle::rad_to_deg(b.rotation_rad), w.translation, fettle::rad_to_deg(w.rotation_rad));
      }
    }
    if (std::getenv("FETTLE_ACCURACY_VERBOSE") != nullptr) {
      // the whole part's rotation error about the part's axes, and its slide at the first region
      const Transform D = capture.truth.T_base_part.inverse() * r->whole.T_scene_template;
      const Eigen::AngleAxisd aa(D.linear());
      const Vec3 rv = aa.axis() * fettle::rad_to_deg(aa.angle());
      const auto& roi = recipe.regions[0].roi_center_mm;
      const Vec3 c(roi[0], roi[1], roi[2]);
      const Vec3 dt = D * c - c;
      std::printf("seed %3d whole part: rotation error about x y z %+.4f %+.4f %+.4f deg, at %s %+.4f %+.4f %+.4f mm\n", seed, rv.x(), rv.y(), rv.z(),
                  recipe.regions[0].name.c_str(), dt.x(), dt.y(), dt.z());
    }
    for (std::size_t i = 0; i < r->regions.size(); ++i) {
      const auto& rr = r->regions[i];
      if (!rr.ok()) {
        ADD_FAILURE() << "seed " << seed << ": " << rr.error->message;
        ++failures;
        continue;
      }
      const auto& roi = recipe.regions[i].roi_center_mm;
      const auto e = test::pose_error_at(rr.registration.T_scene_template, capture.truth.T_base_part,
                                         Vec3(roi[0], roi[1], roi[2]));
      const double deg = fettle::rad_to_deg(e.rotation_rad);
      err_mm[rr.name].push_back(e.translation);
      err_deg[rr.name].push_back(deg);
      all_mm.push_back(e.translation);
      all_deg.push_back(deg);
      // the whole part's pose at the same point, for comparison (printed, not a target)
      const auto w = test::pose_error_at(r->whole.T_scene_template, capture.truth.T_base_part, Vec3(roi[0], roi[1], roi[2]));
      whole_mm[rr.name].push_back(w.translation);
      whole_deg[rr.name].push_back(fettle::rad_to_deg(w.rotation_rad));
      if (std::getenv("FETTLE_ACCURACY_VERBOSE") != nullptr)
        std::printf("seed %3d %-18s fitness %.3f (%zu hidden)  region %.4f mm %.4f deg  whole part %.4f mm %.4f deg "
                    "(%d iterations%s)\n",
                    seed, rr.name.c_str(), rr.registration.fitness, rr.registration.hidden, e.translation, deg, w.translation,
                    fettle::rad_to_deg(w.rotation_rad), r->whole.iterations, r->whole.converged ? "" : ", not converged");
      if (body) {
        // RMS distance of the region's template points to the true body surface (all of them:
        // the walls show a slide sideways)
        const auto& fine = templ.regions()[i].cloud.fine();
        const auto rms = [&](const Transform& T_scene_region) {
          return body->rms_distance_to_surface_mm(fine.points, capture.truth.T_base_part.inverse() * T_scene_region, 4);
        };
        surface_region_mm[rr.name].push_back(rms(rr.registration.T_scene_template));
        surface_whole_mm[rr.name].push_back(rms(r->whole.T_scene_template));
      }
      const auto& truth = capture.truth.regions[i];
      if (truth.type == fettle::config::RegionType::riser && truth.volume_mm3 > 0) {
        riser_volume_error.push_back((rr.excess.volume_mm3 - truth.volume_mm3) / truth.volume_mm3);
        if (std::getenv("FETTLE_ACCURACY_VERBOSE") != nullptr) {
          // the true footprint: where the casting stands above its golden top by the threshold
          const auto& rg = recipe.regions[i];
          double footprint = 0.0;
          for (double x = rg.roi_center_mm[0] - 0.5 * rg.roi_size_mm[0]; x < rg.roi_center_mm[0] + 0.5 * rg.roi_size_mm[0]; x += 0.1)
            for (double y = rg.roi_center_mm[1] - 0.5 * rg.roi_size_mm[1]; y < rg.roi_center_mm[1] + 0.5 * rg.roi_size_mm[1]; y += 0.1)
              if (casting.surface_z_mm(x, y) - casting.golden_top_z_mm(x, y) > rg.excess_threshold_mm) footprint += 0.01;
          std::printf("seed %3d %-18s excess volume %.1f mm3 on %.1f mm2, truth %.1f mm3 (%+.1f %%) on %.1f mm2\n", seed,
                      rr.name.c_str(), rr.excess.volume_mm3, rr.excess.footprint_mm2, truth.volume_mm3,
                      100.0 * riser_volume_error.back(), footprint);
        }
      }
    }
  }
  // The numbers, for the issue and for humans.
  std::printf("%d seeds, %d region failures\n", seeds, failures);
  std::printf("%-20s %12s %12s %12s %12s\n", "region", "median mm", "worst mm", "median deg", "worst deg");
  for (const auto& [name, v] : err_mm) {
    std::printf("%-20s %12.4f %12.4f %12.4f %12.4f\n", name.c_str(), median(v), *std::max_element(v.begin(), v.end()),
                median(err_deg[name]), *std::max_element(err_deg[name].begin(), err_deg[name].end()));
  }
  std::printf("the whole part's pose at each region's ROI centre, for comparison:\n");
  for (const auto& [name, v] : whole_mm) {
    std::printf("%-20s %12.4f %12.4f %12.4f %12.4f\n", name.c_str(), median(v), *std::max_element(v.begin(), v.end()),
                median(whole_deg[name]), *std::max_element(whole_deg[name].begin(), whole_deg[name].end()));
  }
  if (!surface_region_mm.empty()) {
    std::printf("RMS distance of each region's template to the true surface, median over seeds:\n");
    for (const auto& [name, v] : surface_region_mm)
      std::printf("%-20s region pose %.4f mm, whole part's pose %.4f mm\n", name.c_str(), median(v),
                  median(surface_whole_mm[name]));
  }
  double worst_volume = 0.0;
  for (double v : riser_volume_error) worst_volume = std::max(worst_volume, std::abs(v));
  std::printf("riser excess volume: worst error %.2f %% over %zu castings\n", 100.0 * worst_volume,
              riser_volume_error.size());

  EXPECT_EQ(failures, 0);
  ASSERT_FALSE(all_mm.empty());
  EXPECT_LE(median(all_mm), 0.05);
  EXPECT_LE(median(all_deg), 0.05);
  EXPECT_LE(*std::max_element(all_mm.begin(), all_mm.end()), 0.1);
  EXPECT_LE(*std::max_element(all_deg.begin(), all_deg.end()), 0.1);
  for (const auto& [name, v] : err_mm) {
    EXPECT_LE(median(v), 0.05) << name;
    EXPECT_LE(median(err_deg[name]), 0.05) << name;
  }
  EXPECT_EQ(riser_volume_error.size(), static_cast<std::size_t>(seeds - failures / 4));
  EXPECT_LE(worst_volume, 0.05);
}

// The boss is a cylinder on the tilted face: turning about the face's normal moves almost
// none of its surface, and its own ICP, free to turn, is pulled 0.16-0.21 deg about it by its
// flash on these seeds while the whole part's pose is within 0.01 deg. It keeps the whole
// part's turn in that direction (FineSettings::degenerate_ratio) and fixes the rest.
TEST(VisionSimAccuracy, TheBossKeepsThePartsTurnAboutItsAxis) {
  auto recipe = accuracy_recipe();
  const auto templ = golden_template(recipe);
  const fettle::sim::Scanner scanner{fettle::sim::ScannerConfig{}};
  std::size_t boss = recipe.regions.size();
  for (std::size_t i = 0; i < recipe.regions.size(); ++i)
    if (recipe.regions[i].name == "boss-circle") boss = i;
  ASSERT_LT(boss, recipe.regions.size());
  // The shipped recipe puts the boss on the whole part's pose (its own fit slides sideways on a
  // few castings); this test is about the boss's own fit, so it asks for it.
  recipe.regions[boss].pose = fettle::config::RegionPose::region;
  const auto& roi = recipe.regions[boss].roi_center_mm;
  for (const int seed : {6, 9, 23}) {
    const auto casting = fettle::sim::Casting::make(recipe, static_cast<std::uint64_t>(seed));
    const auto capture = scanner.capture(casting, 0.0);
    const auto r = inspect(recipe, templ, capture.cloud, capture.truth.T_base_camera);
    ASSERT_TRUE(r.ok()) << "seed " << seed << ": " << r.error().message;
    const auto& rr = r->regions[boss];
    ASSERT_TRUE(rr.ok()) << "seed " << seed << ": " << rr.error->message;
    const auto e = test::pose_error_at(rr.registration.T_scene_template, capture.truth.T_base_part, Vec3(roi[0], roi[1], roi[2]));
    EXPECT_LE(fettle::rad_to_deg(e.rotation_rad), 0.05) << "seed " << seed;
    EXPECT_LE(e.translation, 0.1) << "seed " << seed;
  }
}

// The cell's two photo positions (slide at 0 and 120 mm), as fettled's pipeline takes them:
// the second view's calibrated pose is refined on the overlap. The simulator's flying pixels
// beside the part's edges differ between the two viewpoints; registered with them, the second
// view comes out about 0.05 mm off along the slide, without them under 0.01 mm (printed below).
TEST(MultiView, OrganizedViewsRegisterOnTheirOverlapWithoutTheirFlyingPixels) {
  const auto recipe = accuracy_recipe();
  const fettle::sim::Scanner scanner{fettle::sim::ScannerConfig{}};
  const auto casting = fettle::sim::Casting::make(recipe, 1);
  const auto first = scanner.capture(casting, 0.0);
  const auto second = scanner.capture(casting, 120.0, 1);
  // the slide's calibration 0.3 mm and 0.05 deg off
  Transform T_off = Transform::Identity();
  T_off.translation() = Vec3(0.3, -0.2, 0.1);
  T_off.linear() = Eigen::AngleAxisd(fettle::deg_to_rad(0.05), Vec3::UnitZ()).toRotationMatrix();
  const std::vector<OrganizedView> calibrated{{&first.cloud, first.truth.T_base_camera},
                                              {&second.cloud, second.truth.T_base_camera * T_off}};
  const auto error_of = [&](const std::vector<OrganizedView>& views) {
    EXPECT_TRUE(views[0].T_fixture_camera.isApprox(first.truth.T_base_camera)) << "the first view's pose is kept";
    const Transform d = views[1].T_fixture_camera.inverse() * second.truth.T_base_camera;
    return d.translation().norm();
  };
  const auto refined = register_views(calibrated, FuseSettings{});
  ASSERT_TRUE(refined.ok()) << refined.error().message;
  const double with_filter = error_of(*refined);
  FuseSettings unfiltered;
  unfiltered.jump_edge_mm = 0.0;
  const auto biased = register_views(calibrated, unfiltered);
  ASSERT_TRUE(biased.ok()) << biased.error().message;
  const double without_filter = error_of(*biased);
  std::printf("second view's pose error: %.4f mm refined (flying pixels left out), %.4f mm with them\n", with_filter,
              without_filter);
  EXPECT_LE(with_filter, 0.03);
  EXPECT_GT(without_filter, with_filter);
}

// Both views into one voxel grid: every region within 0.05 mm / 0.05 deg on seeds 1 and 5 (on
// 5, fusing the two views first and inspecting the unorganized cloud places the part 0.09 mm
// off at the boss).
TEST(MultiView, TwoOrganizedViewsPlaceThePartWithin50Microns) {
  const auto recipe = accuracy_recipe();
  const auto templ = golden_template(recipe);
  const fettle::sim::Scanner scanner{fettle::sim::ScannerConfig{}};
  for (const int seed : {1, 5}) {
    const auto casting = fettle::sim::Casting::make(recipe, static_cast<std::uint64_t>(seed));
    const auto first = scanner.capture(casting, 0.0);
    const auto second = scanner.capture(casting, 120.0, 1);
    const auto one = inspect(recipe, templ, first.cloud, first.truth.T_base_camera);
    ASSERT_TRUE(one.ok()) << "seed " << seed << ": " << one.error().message;
    const auto views = register_views(
        {{&first.cloud, first.truth.T_base_camera}, {&second.cloud, second.truth.T_base_camera}}, FuseSettings{});
    ASSERT_TRUE(views.ok()) << views.error().message;
    const auto two = inspect(recipe, templ, *views);
    ASSERT_TRUE(two.ok()) << "seed " << seed << ": " << two.error().message;
    // one voxel grid: the second view adds the voxels the first does not see (about 8 % on the
    // pump body), not a second layer
    EXPECT_GT(two->scene_part.size(), one->scene_part.size() * 103 / 100) << "seed " << seed;
    EXPECT_LT(two->scene_part.size(), one->scene_part.size() * 13 / 10) << "seed " << seed;
    ASSERT_EQ(two->regions.size(), recipe.regions.size());
    for (std::size_t i = 0; i < recipe.regions.size(); ++i) {
      const auto& roi = recipe.regions[i].roi_center_mm;
      const auto& rr = two->regions[i];
      ASSERT_TRUE(rr.ok()) << "seed " << seed << " " << rr.name << ": " << rr.error->message;
      const auto e =
          test::pose_error_at(rr.registration.T_scene_template, first.truth.T_base_part, Vec3(roi[0], roi[1], roi[2]));
      std::printf("seed %d %-18s two views %.4f mm %.4f deg\n", seed, rr.name.c_str(), e.translation,
                  fettle::rad_to_deg(e.rotation_rad));
      EXPECT_LE(e.translation, 0.05) << "seed " << seed << " " << rr.name;
      EXPECT_LE(fettle::rad_to_deg(e.rotation_rad), 0.05) << "seed " << seed << " " << rr.name;
    }
  }
}
