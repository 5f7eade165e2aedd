// The simulated casting's geometry: ground-truth volumes against analytic values, the
// golden template, and part files with impossible geometry rejected with file:line.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <unistd.h>

#include "fettle/config/diagnostics.hpp"
#include "sim_test_util.hpp"

using namespace fettle::sim;  // NOLINT
using ::testing::HasSubstr;
using sim_test::pi;

namespace {

const RegionTruth& region(const std::vector<RegionTruth>& r, const std::string& name) {
  for (const auto& x : r)
    if (x.name == name) return x;
  throw std::runtime_error("no region " + name);
}

TEST(SimGeometry, RiserVolumeMatchesTheCylinderWithinTwoPercent) {
  const auto recipe = sim_test::pump_body();
  const auto c = Casting::make(recipe, 1, CastingOptions{.vary = false});
  const auto& f = recipe.geometry.risers.at(0);
  const double d = 0.5 * (f.diameter_mm.min + f.diameter_mm.max), h = 0.5 * (f.height_mm.min + f.height_mm.max);
  // A tilted plane top: the mean height over the disc is the centre height.
  const double expected = pi() * d * d / 4 * h;
  const auto material = c.material();  // by value: keep it while r refers into it
  const auto& r = region(material, "riser");
  EXPECT_NEAR(r.volume_mm3, expected, 0.02 * expected);
  const double tilt = 0.5 * (f.top_tilt_deg.min + f.top_tilt_deg.max) * pi() / 180;
  EXPECT_NEAR(r.max_height_mm, h + std::tan(tilt) * d / 2, 0.1);
}

// Every ring fin: the flange's ring flash and the boss's small circle flash.
TEST(SimGeometry, RingFlashVolumeMatchesTheAnnulusWithinTwoPercent) {
  const auto recipe = sim_test::pump_body();
  ASSERT_GE(recipe.geometry.ring_flashes.size(), 2u) << "the pump body has a flange ring and a boss circle";
  const auto c = Casting::make(recipe, 1, CastingOptions{.vary = false});
  const auto material = c.material();
  for (const auto& f : recipe.geometry.ring_flashes) {
    const double R = f.cylinder.radius_mm, e = 0.5 * (f.extent_mm.min + f.extent_mm.max);
    const double t = 0.5 * (f.thickness_mm.min + f.thickness_mm.max);
    const double expected = pi() * ((R + e) * (R + e) - R * R) * t;
    const auto& r = region(material, f.region);
    EXPECT_NEAR(r.volume_mm3, expected, 0.02 * expected) << f.region;
    EXPECT_NEAR(r.max_height_mm, e, 0.1) << f.region;
  }
}

TEST(SimGeometry, StraightFlashVolumeMatchesTheWallWithinTwoPercent) {
  const auto recipe = sim_test::pump_body();
  const auto c = Casting::make(recipe, 1, CastingOptions{.vary = false});
  const auto& f = recipe.geometry.straight_flashes.at(0);
  const double L = 0.5 * (f.length_mm.min + f.length_mm.max), h = 0.5 * (f.height_mm.min + f.height_mm.max);
  const double t = 0.5 * (f.thickness_mm.min + f.thickness_mm.max);
  const auto material = c.material();
  const auto& r = region(material, f.region);
  EXPECT_NEAR(r.volume_mm3, L * h * t, 0.02 * L * h * t);
}

TEST(SimGeometry, CastingsDifferBySeedWithinTheConfiguredRanges) {
  const auto recipe = sim_test::pump_body();
  const auto a = Casting::make(recipe, 1), b = Casting::make(recipe, 2);
  EXPECT_NE(region(a.material(), "riser").volume_mm3, region(b.material(), "riser").volume_mm3);
  const auto& tol = recipe.geometry.variation;
  for (const auto* c : {&a, &b}) {
    const auto& T = c->T_base_part();
    EXPECT_LE(std::abs(T.translation().x()), tol.placement_tolerance_mm + 1e-9);
    EXPECT_LE(std::abs(T.translation().y()), tol.placement_tolerance_mm + 1e-9);
    EXPECT_LE(fettle::rad_to_deg(fettle::rotation_angle_rad(T)), tol.placement_tolerance_deg + 1e-9);
    const auto& f = recipe.geometry.risers.at(0);
    const double hmax = region(c->material(), "riser").max_height_mm;
    EXPECT_GE(hmax, f.height_mm.min - 0.01);
  }
}

/// The pump body on coarse grids: placement does not depend on them, and castings build fast.
fettle::config::PartRecipe coarse_pump_body() {
  auto recipe = sim_test::pump_body();
  recipe.geometry.surface_grid_mm = 1.0;
  recipe.geometry.material_grid_mm = 0.5;
  return recipe;
}

// The casting comparison of `fettle-sim trial` measures against the casting's own body: a
// point on a perfectly fettled casting (no flash, its form deviation kept) is on it, however far
// the form deviation puts it from the golden surface.
TEST(SimGeometry, ThePerfectlyFettledCastingIsOnItsOwnBodyNotOnTheGolden) {
  auto recipe = coarse_pump_body();
  recipe.geometry.variation.form_deviation_mm = 0.5;
  Casting c = Casting::make(recipe, 7);
  c.remove_all_material();
  double worst_body = 0.0, worst_golden = 0.0;
  std::size_t n = 0;
  for (double y = -60; y <= 60; y += 5.0)
    for (double x = -100; x <= 100; x += 5.0) {
      const double z = c.surface_z_mm(x, y), golden = c.golden_top_z_mm(x, y);
      if (std::isnan(z) || std::isnan(golden)) continue;
      bool smooth = true;  // away from walls (the distance there is to the wall)
      for (double dx : {-3.0, 3.0})
        for (double dy : {-3.0, 3.0}) smooth = smooth && std::abs(c.golden_top_z_mm(x + dx, y + dy) - golden) < 1.0;
      if (!smooth) continue;
      ++n;
      const fettle::Vec3 p(x, y, z);
      worst_body = std::max(worst_body, c.distance_to_body_mm(p));
      worst_golden = std::max(worst_golden, c.distance_to_golden_mm(p));
    }
  EXPECT_GT(n, 300U);
  EXPECT_LT(worst_body, 0.02);
  EXPECT_GT(worst_golden, 0.3) << "the form deviation is there";
}

// A scan point just inside the foot of a step (the pad's 10 mm wall over the plate, 0.05 mm into
// the wall's column and 0.1 mm under the plate's top) is 0.11 mm from the surface, not the 10 mm
// up to its own column's top: the evaluation counted such points as 10 mm off the casting.
TEST(SimGeometry, APointJustInsideAStepsFootIsNearTheFloorBesideIt) {
  const auto recipe = sim_test::pump_body();
  const auto c = Casting::make(recipe, 1, CastingOptions{.vary = false});
  const double y = 48.0;
  double edge = std::nan("");  // the riser pad's wall: the pad at x < edge, the plate beyond
  for (double x = -60.0; x <= -50.0; x += 0.01)
    if (c.golden_top_z_mm(x - 0.01, y) - c.golden_top_z_mm(x, y) > 5.0) {
      edge = x - 0.005;
      break;
    }
  ASSERT_FALSE(std::isnan(edge)) << "the riser pad's wall at y = 48";
  const double top = c.golden_top_z_mm(edge - 1.0, y), floor = c.golden_top_z_mm(edge + 1.0, y);
  ASSERT_GT(top - floor, 5.0);
  const fettle::Vec3 foot(edge - 0.05, y, floor - 0.1);
  EXPECT_NEAR(c.distance_to_body_mm(foot), std::hypot(0.05, 0.1), 0.06);
  EXPECT_NEAR(c.distance_to_surface_mm(foot), std::hypot(0.05, 0.1), 0.06);
  // deeper in, half way up the wall and 3 mm into the pad: the wall is nearest
  EXPECT_NEAR(c.distance_to_body_mm(fettle::Vec3(edge - 3.0, y, 0.5 * (floor + top))), 3.0, 0.06);
}

// The body of a casting differs from the golden one by its smooth form deviation: within
// +-form_deviation_mm everywhere, and really there (over half the amplitude somewhere); none when
// the recipe sets 0.
TEST(SimGeometry, FormDeviationStaysWithinItsAmplitudeAndIsThere) {
  auto recipe = coarse_pump_body();
  const double amp = recipe.geometry.variation.form_deviation_mm;
  ASSERT_GT(amp, 0.0);
  auto largest_deviation = [](const Casting& c) {
    double worst = 0;
    std::size_t n = 0;
    for (double y = -150; y <= 150; y += 2.5)
      for (double x = -150; x <= 150; x += 2.5) {
        const double body = c.surface_z_mm(x, y), golden = c.golden_top_z_mm(x, y);
        if (std::isnan(body) || std::isnan(golden)) continue;
        // away from walls, where the grid's surface and the exact one differ by the step
        bool smooth = true;
        for (double dx : {-3.0, 3.0})
          for (double dy : {-3.0, 3.0}) smooth = smooth && std::abs(c.golden_top_z_mm(x + dx, y + dy) - golden) < 1.0;
        if (!smooth) continue;
        ++n;
        worst = std::max(worst, std::abs(body - golden));
      }
    EXPECT_GT(n, 1000u);
    return worst;
  };
  for (std::uint64_t seed : {1, 2, 3, 4, 5}) {
    Casting c = Casting::make(recipe, seed);
    c.remove_all_material();
    const double worst = largest_deviation(c);
    EXPECT_LE(worst, amp + 1e-4) << "seed " << seed;
    EXPECT_GT(worst, 0.5 * amp) << "seed " << seed;
  }
  recipe.geometry.variation.form_deviation_mm = 0.0;
  Casting flat = Casting::make(recipe, 1);
  flat.remove_all_material();
  EXPECT_LT(largest_deviation(flat), 1e-5);
}

// The scene around the part: the clamps and the clutter stand on the table where the camera
// sees them (an empty fixture, ideal capture); without them, nothing rises above the table.
TEST(SimGeometry, ClampsAndClutterStandOnTheTableInTheScan) {
  auto count_above_table = [](const fettle::config::PartRecipe& recipe) {
    Casting c = Casting::make(recipe, 3);
    c.take_off_fixture();
    auto cfg = sim_test::small_scanner();
    cfg.noise.enabled = false;
    const auto cap = Scanner(cfg).capture(c, 0.0);
    std::size_t above = 0;
    for (std::size_t k = 0; k < cap.cloud.size(); ++k)
      if (cap.cloud.is_valid(k) && (cap.truth.T_base_camera * cap.cloud.points[k].cast<double>()).z() > 1.0) ++above;
    return above;
  };
  auto recipe = coarse_pump_body();
  ASSERT_GT(recipe.geometry.clamps, 0);
  ASSERT_GT(recipe.geometry.clutter_items, 0);
  const auto with_both = count_above_table(recipe);
  recipe.geometry.clutter_items = 0;
  const auto clamps_only = count_above_table(recipe);
  recipe.geometry.clamps = 0;
  const auto none = count_above_table(recipe);
  EXPECT_EQ(none, 0u);
  EXPECT_GT(clamps_only, 500u);
  EXPECT_GT(with_both, clamps_only + 100u);
}

TEST(SimGeometry, PlacementVariesXYAndYawOverTheWholeConfiguredRangeAndNoTiltByDefault) {
  auto recipe = coarse_pump_body();
  recipe.geometry.variation.placement_tolerance_mm = 2.0;
  recipe.geometry.variation.placement_tolerance_deg = 1.5;
  double max_x = 0, max_y = 0, max_yaw = 0;
  for (std::uint64_t seed = 1; seed <= 20; ++seed) {
    const auto T = Casting::make(recipe, seed).T_base_part();
    max_x = std::max(max_x, std::abs(T.translation().x()));
    max_y = std::max(max_y, std::abs(T.translation().y()));
    max_yaw = std::max(max_yaw, fettle::rad_to_deg(std::abs(std::atan2(T.linear()(1, 0), T.linear()(0, 0)))));
    EXPECT_EQ(T.translation().z(), 0.0);
    EXPECT_NEAR(T.linear()(2, 2), 1.0, 1e-12) << "seed " << seed << " is tilted";  // resting flat
  }
  EXPECT_LE(max_x, 2.0);
  EXPECT_GT(max_x, 1.2);  // the range is used, not a fraction of it
  EXPECT_LE(max_y, 2.0);
  EXPECT_GT(max_y, 1.2);
  EXPECT_LE(max_yaw, 1.5 + 1e-9);
  EXPECT_GT(max_yaw, 0.9);
  EXPECT_EQ(Casting::make(recipe, 3, CastingOptions{.vary = false}).T_base_part().matrix(),
            fettle::Transform::Identity().matrix());  // the fixture's nominal placement
}

TEST(SimGeometry, PlacementTiltIsConfigurableAndThePartRestsOnItsLowestCorner) {
  auto recipe = coarse_pump_body();
  const auto flat = Casting::make(recipe, 5);
  recipe.geometry.variation.placement_tilt_deg = 1.0;
  const auto tilted = Casting::make(recipe, 5);
  // Only the placement changes: the casting itself (material, form) is the same.
  EXPECT_EQ(region(flat.material(), "riser").volume_mm3, region(tilted.material(), "riser").volume_mm3);
  EXPECT_NEAR(tilted.T_base_part().translation().x(), flat.T_base_part().translation().x(), 3.0);
  double max_tilt = 0;
  for (std::uint64_t seed = 1; seed <= 12; ++seed) {
    const auto c = Casting::make(recipe, seed);
    const auto& T = c.T_base_part();
    const double tilt = fettle::rad_to_deg(std::acos(std::clamp(T.linear()(2, 2), -1.0, 1.0)));
    EXPECT_LE(tilt, std::sqrt(2.0) * 1.0 + 1e-9) << "seed " << seed;
    max_tilt = std::max(max_tilt, tilt);
    // The body's bottom corners: the lowest is on the table, none below it.
    double low = 1e9;
    for (const auto& b : recipe.geometry.blocks)
      for (double x : {b.min_mm[0], b.max_mm[0]})
        for (double y : {b.min_mm[1], b.max_mm[1]}) low = std::min(low, (T * fettle::Vec3(x, y, b.min_mm[2])).z());
    EXPECT_NEAR(low, 0.0, 1e-9) << "seed " << seed;
  }
  EXPECT_GT(max_tilt, 0.5);
}

TEST(SimGeometry, GoldenTemplateHasNoMaterialAndItsSamplesLieOnItsSurface) {
  const auto recipe = sim_test::pump_body();
  const auto g = Casting::golden(recipe, 1);
  for (const auto& r : g.material()) EXPECT_EQ(r.volume_mm3, 0.0) << r.name;
  const auto pts = g.sample_golden_surface(2.0);
  ASSERT_GT(pts.size(), 5000u);
  std::size_t walls = 0;
  for (std::size_t i = 0; i < pts.size(); i += 37) {
    EXPECT_LT(g.distance_to_golden_mm(pts[i].position_mm.cast<double>()), 0.11);
    EXPECT_NEAR(pts[i].normal.norm(), 1.0f, 1e-4f);
    walls += std::abs(pts[i].normal.z()) < 0.1f ? 1 : 0;
  }
  EXPECT_GT(walls, 0u);
  // the flange top is at its configured height, and a point above it is that far away
  const auto& fl = recipe.geometry.ring_flashes.at(0).cylinder;
  EXPECT_NEAR(g.golden_sdf_mm(fettle::Vec3(fl.center_mm[0], fl.center_mm[1], fl.top_z_mm + 2.0)), 2.0, 1e-9);
  EXPECT_NEAR(g.distance_to_golden_mm(fettle::Vec3(fl.center_mm[0], fl.center_mm[1], fl.top_z_mm + 2.0)), 2.0, 1e-3);
}

// The gouge account's distance beside the block with the tilted top (x 55..110, its top 8 deg
// from level: at x = 55 it is 36.1 mm high, not the untilted 40): a ball passing the block at
// the end of the straight flash keeps 1.7 mm from its edge, and the distance says so. The
// untilted box's distance read 5.89 mm from the ball's centre where the base top is 6.05 away
// (a 0.1 mm gouge of a 12 mm ball that touches nothing); the surface samples agree with the exact one.
TEST(SimGeometry, GoldenDistanceBesideATiltedBlockIsExact) {
  const auto recipe = sim_test::pump_body();
  const auto g = Casting::golden(recipe, 1);
  const fettle::Vec3 ball_centre(49.2, -70.0, 41.05);
  EXPECT_NEAR(g.golden_sdf_mm(ball_centre), 41.05 - 35.0, 1e-9);  // the base top, not the block
  EXPECT_NEAR(g.distance_to_golden_mm(ball_centre), 6.05, 0.1);
  // nearest the block's low edge (55, y, 36.135): diagonally off it
  const double slope = std::tan(8.0 * pi() / 180.0);
  const double edge_z = 40.0 + slope * (55.0 - 82.5);
  const fettle::Vec3 beside(53.0, -70.0, 37.5);
  EXPECT_NEAR(g.golden_sdf_mm(beside), std::hypot(2.0, 37.5 - edge_z), 1e-9);
  EXPECT_NEAR(g.distance_to_golden_mm(beside), std::hypot(2.0, 37.5 - edge_z), 0.1);
  // inside the block: the tilted top's plane distance
  const fettle::Vec3 in(100.0, -20.0, 39.0);
  EXPECT_NEAR(g.golden_sdf_mm(in), (39.0 - (40.0 + slope * (100.0 - 82.5))) * std::cos(8.0 * pi() / 180.0), 1e-9);
}

class BadPartFile : public ::testing::Test {
 protected:
  std::filesystem::path write(const std::string& from, const std::string& to) {
    std::ifstream in(sim_test::kPumpBody);
    std::stringstream s;
    s << in.rdbuf();
    std::string text = s.str();
    const auto at = text.find(from);
    EXPECT_NE(at, std::string::npos) << from;
    text.replace(at, from.size(), to);
    path_ = std::filesystem::temp_directory_path() / ("fettle-sim-bad-" + std::to_string(::getpid()) + ".toml");
    std::ofstream(path_) << text;
    return path_;
  }
  void TearDown() override { std::filesystem::remove(path_); }
  std::filesystem::path path_;
};

TEST_F(BadPartFile, NegativeRadiusIsRejectedWithFileAndLine) {
  const auto p = write("radius_mm = 45.0", "radius_mm = -45.0");
  try {
    (void)fettle::config::load_part(p);
    FAIL() << "accepted a negative radius";
  } catch (const fettle::config::ConfigError& e) {
    EXPECT_THAT(e.what(), HasSubstr(p.string() + ":"));
    EXPECT_THAT(e.what(), HasSubstr("radius_mm"));
    ASSERT_FALSE(e.diagnostics().empty());
    EXPECT_GT(e.diagnostics().front().line, 0);
  }
}

TEST_F(BadPartFile, RiserOffTheBodyIsRejectedWithFileAndLine) {
  const auto p = write("center_mm = [-82.0, 48.0]", "center_mm = [-382.0, 48.0]");
  try {
    (void)fettle::config::load_part(p);
    FAIL() << "accepted a riser off the body";
  } catch (const fettle::config::ConfigError& e) {
    EXPECT_THAT(e.what(), HasSubstr("off the body"));
    EXPECT_GT(e.diagnostics().front().line, 0);
  }
}

TEST_F(BadPartFile, RegionRoiOffTheBodyIsRejectedWithFileAndLine) {
  const auto p = write("roi_center_mm = [82.0, -48.0, 47.0]", "roi_center_mm = [482.0, -48.0, 47.0]");
  try {
    (void)fettle::config::load_part(p);
    FAIL() << "accepted a region off the body";
  } catch (const fettle::config::ConfigError& e) {
    EXPECT_THAT(e.what(), HasSubstr("regions[2].roi_center_mm"));
    EXPECT_GT(e.diagnostics().front().line, 0);
  }
}

TEST_F(BadPartFile, FeatureNamingAnUnknownRegionIsRejected) {
  const auto p = write("region = \"riser\"", "region = \"rizer\"");
  EXPECT_THROW((void)fettle::config::load_part(p), fettle::config::ConfigError);
}

}  // namespace
