// Accuracy of the vision stage on the simulator's ground truth (issue 4): seeded pump-body
// castings placed within +-3 mm / +-3 degrees on the fixture, scanned with the default
// 3.2 MP scanner (sigma_z 0.05 mm, dropouts, flying pixels, outliers), inspected through the
// organized-cloud path. Per region: pose error (at the region's ROI centre) median <= 0.05 mm
// and <= 0.05 degrees, worst <= 0.1 mm and <= 0.1 degrees, every region found; the riser's
// excess volume within 5 % of the truth.
//
// Seeds: FETTLE_ACCURACY_SEEDS (default 8; `make accuracy-vision` runs 50).
//
// FETTLE_ACCURACY_VERBOSE=1 prints every seed's region and whole-part errors.
//
// FETTLE_ACCURACY_FORM=1 keeps the recipe's form deviation (the assertions then do not hold:
// a region's true pose is no longer the part's). It prints, per region, how far the region's
// template lands from the casting's true (deformed, material-free) surface, placed with the
// region's pose and with the whole part's: the measure for choosing `pose = "part"`.
//
// FETTLE_ACCURACY_GROUND=1 removes every bit of flash and riser first (an oracle grind): it
// separates the pull of the material from the scanner's errors.
//
// DISABLED (not run by ctest / CI) because the vision stage does not meet it yet: on 50 seeds
// (2026-12-02, region fitness over the visible surface, flange and riser on the part's pose)
// every region is found, and the median region errors are flange 0.049 mm, riser 0.085 mm,
// straight flash 0.069 mm, boss 0.171 mm / 0.10 degrees (its own ICP; the whole part's pose is
// 0.043 mm there); worst 0.56 mm / 0.39 degrees; the riser volume within 14.4 %. (Until that
// day the riser region failed its 0.6 fitness on 7 of 8 seeds.) `make accuracy-vision` runs it anyway (--gtest_also_run_disabled_tests);
// remove the DISABLED_ prefix once it passes.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "fettle/config/load.hpp"
#include "fettle/sim/sim.hpp"
#include "fettle/vision/inspect.hpp"
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

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

}  // namespace

TEST(VisionSimAccuracy, DISABLED_SeededCastingsArePlacedWithin50MicronsAndFiveHundredthsOfADegree) {
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
  for (int seed = 1; seed <= seeds; ++seed) {
    auto casting = fettle::sim::Casting::make(recipe, static_cast<std::uint64_t>(seed));
    if (std::getenv("FETTLE_ACCURACY_GROUND") != nullptr) casting.remove_all_material();
    const auto capture = scanner.capture(casting, 0.0);
    std::optional<fettle::sim::Casting> body;  // FETTLE_ACCURACY_FORM: the casting without its material
    if (std::getenv("FETTLE_ACCURACY_FORM") != nullptr) {
      body = casting;
      body->remove_all_material();
    }
    const auto r = inspect(recipe, templ, capture.cloud, capture.truth.T_base_camera);
    if (!r) {
      ADD_FAILURE() << "seed " << seed << ": " << r.error().message;
      ++failures;
      continue;
    }
    ASSERT_EQ(r->regions.size(), recipe.regions.size());
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
          const Transform T_part_template = capture.truth.T_base_part.inverse() * T_scene_region;
          double sum = 0.0;
          std::size_t n = 0;
          for (std::size_t k = 0; k < fine.size(); k += 4) {
            const double d = body->distance_to_surface_mm(T_part_template * fine.points[k].cast<double>());
            sum += d * d;
            ++n;
          }
          return n > 0 ? std::sqrt(sum / static_cast<double>(n)) : 0.0;
        };
        surface_region_mm[rr.name].push_back(rms(rr.registration.T_scene_template));
        surface_whole_mm[rr.name].push_back(rms(r->whole.T_scene_template));
      }
      const auto& truth = capture.truth.regions[i];
      if (truth.type == fettle::config::RegionType::riser && truth.volume_mm3 > 0)
        riser_volume_error.push_back((rr.excess.volume_mm3 - truth.volume_mm3) / truth.volume_mm3);
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
