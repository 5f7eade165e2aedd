// A golden casting's template from views of it on the fixture (process::build_template,
// `fettle template build`): a hand-fettled simulated casting with its form deviation, seen by
// the cell's two views beside the fixture's clamps and clutter.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <vector>

#include "fettle/config/load.hpp"
#include "fettle/process/pipeline.hpp"
#include "fettle/sim/sim.hpp"
#include "fettle/vision/inspect.hpp"

namespace fettle::process {
namespace {

namespace fs = std::filesystem;

config::PartRecipe pump_body() {
  auto recipe = config::load_part(fs::path(FETTLE_SOURCE_DIR) / "config/parts/pump-body.toml");
  recipe.geometry.variation.form_deviation_mm = 0.5;  // a sand casting's
  return recipe;
}

/// Three views of `casting` at the camera's full resolution (its mixed pixels join a clamp to
/// the casting as they do in the cell).
std::vector<View> views_of(const sim::Casting& casting) {
  sim::ScannerConfig c;
  c.photo_positions_mm = {0.0, 60.0, 120.0};
  const sim::Scanner scanner(c);
  std::vector<View> views;
  for (std::size_t k = 0; k < c.photo_positions_mm.size(); ++k) {
    const auto cap = scanner.capture(casting, c.photo_positions_mm[k], k);
    views.push_back({cap.cloud, cap.truth.T_base_camera, cap.truth.slide_position_mm});
  }
  return views;
}

sim::Casting hand_fettled(const config::PartRecipe& recipe, std::uint64_t seed) {
  auto c = sim::Casting::make(recipe, seed);
  c.remove_all_material();
  c.set_T_base_part(vision::nominal_T_fixture_part(recipe));
  return c;
}

// The template lies on the casting's own surface (its form deviation, not the nominal's), holds
// nothing of the clamps and clutter beside it, and every normal points out of the casting.
TEST(TemplateBuild, AHandFettledCastingsViewsMakeATemplateOnItsOwnSurfaceWithOutwardNormals) {
  const auto recipe = pump_body();
  const auto casting = hand_fettled(recipe, 3);
  TemplateBuildSettings settings;  // the pump body's box from its drawing, 2 mm margin
  settings.box_min_mm = Vec3(-112.0, -87.0, 0.0);
  settings.box_max_mm = Vec3(112.0, 87.0, 70.0);
  const auto built = build_template(recipe, views_of(casting), settings);
  ASSERT_TRUE(built) << built.error().message;
  const auto& t = built->cloud;
  ASSERT_TRUE(t.has_normals());
  EXPECT_GT(t.size(), 50000U);
  EXPECT_GT(built->dropped_points, 0U) << "the clamps and clutter are seen and dropped";
  std::vector<double> own, nominal;
  std::size_t outward = 0, judged = 0;
  for (std::size_t i = 0; i < t.size(); ++i) {
    const Vec3 p = t.points[i].cast<double>();
    own.push_back(std::abs(casting.distance_to_body_mm(p)));
    nominal.push_back(std::abs(casting.distance_to_golden_mm(p)));
    // outward: along the golden solid's distance gradient where it is clear (not at an edge)
    Vec3 g;
    for (int k = 0; k < 3; ++k) {
      Vec3 d = Vec3::Zero();
      d(k) = 0.2;
      g(k) = casting.golden_sdf_mm(p + d) - casting.golden_sdf_mm(p - d);
    }
    if (g.norm() < 0.3) continue;  // an edge or a corner: the gradient is not one face's
    ++judged;
    if (t.normals[i].cast<double>().dot(g) > 0.0) ++outward;
  }
  const auto pct = [](std::vector<double> v, double q) {
    std::sort(v.begin(), v.end());
    return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))];
  };
  EXPECT_LT(pct(own, 0.5), 0.05);
  EXPECT_LT(pct(own, 0.95), 0.15);
  EXPECT_LT(pct(own, 0.999), 1.0) << "no clamp or clutter point";
  EXPECT_GT(pct(nominal, 0.9), pct(own, 0.9) + 0.05) << "the casting's own form, not the nominal's";
  ASSERT_GT(judged, t.size() / 2);
  EXPECT_GT(static_cast<double>(outward), 0.99 * static_cast<double>(judged)) << outward << " of " << judged;
}

// An empty fixture (the clamps and clutter only) is no template: the error names a region
// that finds nothing and what to check.
TEST(TemplateBuild, AnEmptyFixtureIsAnErrorThatSaysWhatToCheck) {
  const auto recipe = pump_body();
  auto casting = hand_fettled(recipe, 3);
  casting.take_off_fixture();
  const auto built = build_template(recipe, views_of(casting));
  ASSERT_FALSE(built);
  EXPECT_TRUE(built.error().code == "template.regions" || built.error().code == "template.empty") << built.error().code;
  EXPECT_NE(built.error().message.find("golden casting"), std::string::npos) << built.error().message;
}

}  // namespace
}  // namespace fettle::process
