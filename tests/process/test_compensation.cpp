// The cell learns its own bias (fettle/process/compensation.hpp): the measurement of where the
// tool cut against where it was told to, on synthetic cuts whose offset is known, and the
// estimate's update, bounds and state file.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>
#include <vector>

#include <unistd.h>

#include "fettle/process/compensation.hpp"

namespace {

using fettle::Vec3;
namespace fp = fettle::process;

constexpr double kRadius = 6.0;  // ball-12

/// A recipe with one region ground by a 12 mm ball.
fp::LoadedRecipe ball_recipe() {
  fp::LoadedRecipe r;
  fettle::config::Tool ball;
  ball.name = "ball-12";
  ball.shape = fettle::config::ToolShape::ball;
  ball.diameter_mm = 2.0 * kRadius;
  r.recipe.tools.push_back(ball);
  fettle::config::Region region;
  region.name = "groove";
  region.tool = "ball-12";
  r.recipe.regions.push_back(region);
  return r;
}

/// Grooves ground by the ball (tip at z = 0, so its centre at z = kRadius): one along x at y = 0
/// and, with `cross`, one along y at x = 60. The re-scan shows each groove where the tool
/// really was (commanded + offset, plus noise); the first scan had material 2 mm above the
/// ball's centre everywhere, and flat untouched ground beside the grooves (the same in both
/// scans) that must not count.
struct Cut {
  fettle::Trajectory commanded;
  fettle::vision::Inspection before;
  fp::VerificationResult after;
};

Cut grooves(const Vec3& offset, bool cross, double noise_mm, unsigned seed) {
  Cut c;
  c.commanded.segment_regions = {"groove"};
  std::mt19937 rng(seed);
  std::normal_distribution<double> n(0.0, noise_mm);
  fp::RegionVerification rv;
  rv.name = "groove";
  auto pose = [&](const Vec3& tip) {
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = tip;
    p.kind = fettle::MoveKind::grind;
    c.commanded.points.push_back(p);
  };
  auto groove = [&](const Vec3& along, const Vec3& across, const Vec3& start) {
    for (int i = 0; i <= 40; ++i) pose(start + i * along);
    for (int i = 2; i < 39; ++i)
      for (int k = -12; k <= 12; ++k) {
        const double th = k * 5.0 * M_PI / 180.0;  // up to 60 deg either side of the bottom
        const Vec3 centre = start + i * along + Vec3(0, 0, kRadius) + offset;
        const Vec3 q = centre + kRadius * (std::sin(th) * across - std::cos(th) * Vec3::UnitZ());
        rv.roi_points_part.push_back((q + Vec3(0, 0, n(rng))).cast<float>());
      }
  };
  groove(Vec3::UnitX(), Vec3::UnitY(), Vec3(-20, 0, 0));
  if (cross) groove(Vec3::UnitY(), Vec3::UnitX(), Vec3(60, -20, 0));
  // the first scan: material above the grooves, and untouched ground at z = 0.5 beside them
  // (3.5 mm beside the groove's centre line: 0.5 mm off the ball's surface)
  for (double x = -30; x <= 80; x += 0.4)
    for (double y = -30; y <= 30; y += 0.4) {
      const bool beside = std::abs(y - 3.5 * (y > 0 ? 1 : -1)) < 0.3 && x > -18 && x < 18;
      c.before.scene_part.points.emplace_back(static_cast<float>(x), static_cast<float>(y),
                                              static_cast<float>(beside ? 0.5 : kRadius + 2.0));
      if (beside) rv.roi_points_part.emplace_back(static_cast<float>(x), static_cast<float>(y), 0.5f);
    }
  c.after.regions.push_back(rv);
  return c;
}

TEST(Compensation, MeasuresTheOffsetOfTheCutAlongEveryDirectionTheCutSurfacesFix) {
  const auto recipe = ball_recipe();
  const Vec3 offset(0.12, -0.1, -0.12);  // 0.2 mm, as a hand-eye calibration's worth
  const auto cut = grooves(offset, true, 0.03, 1);
  const auto m = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after);
  ASSERT_TRUE(m) << m.error().message;
  EXPECT_EQ(m->observed_directions(), 3) << m->describe();
  EXPECT_LT((m->offset_mm - offset).norm(), 0.02) << m->describe();
  // the untouched ground beside the grooves (0.5 mm off the ball's surface) is left out
  EXPECT_LT(m->rms_mm, 0.06) << m->describe();
}

TEST(Compensation, ADirectionNoCutSurfaceFixesIsReportedUnobservedNotGuessed) {
  const auto recipe = ball_recipe();
  const Vec3 offset(0.15, 0.0, -0.1);
  const auto cut = grooves(offset, false, 0.03, 2);  // one groove along x: x is not fixed
  const auto m = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after);
  ASSERT_TRUE(m) << m.error().message;
  EXPECT_EQ(m->observed_directions(), 2) << m->describe();
  // along the groove only the ball's 1 mm pose spacing tilts the normals a little: x is neither
  // observed nor given the true 0.15 mm
  EXPECT_LT(std::abs(m->offset_mm.x()), 0.02) << m->describe();
  EXPECT_LT((m->observed * Vec3::UnitX()).norm(), 0.1) << m->describe();
  EXPECT_NEAR(m->offset_mm.z(), -0.1, 0.02) << m->describe();
}

TEST(Compensation, NoCutIsAnErrorThatSaysSo) {
  const auto recipe = ball_recipe();
  auto cut = grooves(Vec3::Zero(), true, 0.0, 3);
  cut.after.regions.front().roi_points_part.clear();
  const auto m = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after);
  ASSERT_FALSE(m);
  EXPECT_EQ(m.error().code, "compensation.no_cut");
  EXPECT_NE(m.error().message.find("no cut to measure"), std::string::npos) << m.error().message;
}

TEST(Compensation, TheEstimateConvergesOnTheCellsOffsetAndStaysWithinItsBound) {
  const auto recipe = ball_recipe();
  const Vec3 truth(0.12, -0.1, -0.12);
  fettle::config::CompensationSection settings;  // gain 0.5, max 0.5 mm
  fp::CellBias bias;
  for (unsigned cycle = 0; cycle < 5; ++cycle) {
    // the path is commanded with the estimate taken off: the re-scan against it still shows
    // the cell's whole offset (the measurement does not depend on the estimate)
    auto cut = grooves(truth, true, 0.03, 10 + cycle);
    const auto m = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after);
    ASSERT_TRUE(m) << m.error().message;
    bias.update(*m, settings);
  }
  EXPECT_EQ(bias.updates, 5u);
  // 0.5^5 of the offset is left, plus the measurement's noise: under a third of it (issue's goal)
  EXPECT_LT((bias.bias_mm - truth).norm(), truth.norm() / 3.0) << bias.describe();
  EXPECT_LT((bias.bias_mm - truth).norm(), 0.02) << bias.describe();

  fp::CutOffset huge;
  huge.offset_mm = Vec3(3.0, 0.0, 0.0);
  huge.observed = Eigen::Matrix3d::Identity();
  for (int i = 0; i < 20; ++i) bias.update(huge, settings);
  EXPECT_NEAR(bias.bias_mm.norm(), settings.max_offset_mm, 1e-9) << bias.describe();
}

// The stated accuracies (calibration 0.20, robot 0.15, repeatability 0.15 mm) bound the cut at
// their root sum of squares, 0.29 mm, until the cell learns a direction; along it the systematic
// part shrinks with the estimate's updates and its scatter, the repeatability stays; the
// directions it never observed keep all of it.
TEST(Compensation, PlacementUncertaintyShrinksAlongWhatTheCellLearnedOnly) {
  fettle::config::SafetySection safety;
  safety.calibration_accuracy_mm = 0.20;
  safety.robot_accuracy_mm = 0.15;
  safety.robot_repeatability_mm = 0.15;
  const fettle::config::CompensationSection settings;  // gain 0.5
  fp::CellBias bias;
  const auto stated = fp::placement_uncertainty(safety, bias, settings);
  const double all = std::sqrt(0.2 * 0.2 + 0.15 * 0.15 + 0.15 * 0.15);
  for (const Vec3& n : std::vector<Vec3>{Vec3::UnitX(), Vec3::UnitY(), Vec3::UnitZ(), Vec3(1, 1, 1).normalized()})
    EXPECT_NEAR(stated.along_mm(n), all, 1e-9);
  // cuts that face up: z is learned, a measurement scattered by 0.04 mm about a -0.25 mm offset
  fp::CutOffset up;
  up.observed = Vec3(0.0, 0.0, 1.0).asDiagonal();
  std::vector<double> z_bound;
  for (int k = 0; k < 8; ++k) {
    up.offset_mm = Vec3(0.0, 0.0, -0.25 + (k % 2 == 0 ? 0.04 : -0.04));
    bias.update(up, settings);
    z_bound.push_back(fp::placement_uncertainty(safety, bias, settings).along_mm(Vec3::UnitZ()));
  }
  const auto learned = fp::placement_uncertainty(safety, bias, settings);
  EXPECT_NEAR(learned.along_mm(Vec3::UnitX()), all, 1e-9);
  EXPECT_NEAR(learned.along_mm(Vec3::UnitY()), all, 1e-9);
  EXPECT_LT(z_bound.back(), z_bound.front());
  EXPECT_GE(z_bound.back(), 0.15 - 1e-9);  // the repeatability is never learned away
  EXPECT_LT(z_bound.back(), 0.17);         // 0.15 and a third of the scatter (about 0.05 mm squared)
  EXPECT_NE(learned.describe().find("0.29 mm sideways"), std::string::npos) << learned.describe();
  // nothing stated: nothing kept beyond the regions' allowances
  EXPECT_TRUE(fp::placement_uncertainty(fettle::config::SafetySection{}, bias, settings).bound_mm2.isZero());
}

// A re-grind after a first grind that measured the cut 0.22 mm low (+-0.002) on faces that look
// up: along z it is commanded with that offset and bounded by the repeatability and that scatter
// (0.15 mm, not the 0.29 mm a cell that has learned nothing keeps); sideways, which the cut did
// not observe, it keeps the cell's estimate and the whole stated bound.
TEST(Compensation, AReGrindIsBoundedByWhatItsCycleMeasured) {
  fettle::config::SafetySection safety;
  safety.calibration_accuracy_mm = 0.20;
  safety.robot_accuracy_mm = 0.15;
  safety.robot_repeatability_mm = 0.15;
  const fettle::config::CompensationSection settings;
  fp::CellBias cell;
  cell.bias_mm = Vec3(0.03, -0.02, -0.05);
  fp::CutOffset measured;
  measured.observed = Vec3(0.0, 0.0, 1.0).asDiagonal();
  measured.offset_mm = Vec3(0.0, 0.0, -0.22);
  measured.std_mm = Vec3(0.0, 0.0, 0.002);
  const auto r = fp::regrind_compensation(safety, cell, measured, settings);
  EXPECT_LT((r.bias_mm - Vec3(0.03, -0.02, -0.22)).norm(), 1e-12);
  EXPECT_NEAR(r.placement.along_mm(Vec3::UnitZ()), std::hypot(0.15, 0.002), 1e-9);
  const double all = std::sqrt(0.2 * 0.2 + 0.15 * 0.15 + 0.15 * 0.15);
  EXPECT_NEAR(r.placement.along_mm(Vec3::UnitX()), all, 1e-9);
  EXPECT_NEAR(r.placement.along_mm(Vec3::UnitY()), all, 1e-9);
  EXPECT_NEAR(fp::placement_uncertainty(safety, cell, settings).along_mm(Vec3::UnitZ()), all, 1e-9);
  // nothing stated: nothing kept beyond the regions' allowances
  EXPECT_TRUE(fp::regrind_compensation(fettle::config::SafetySection{}, cell, measured, settings).placement.bound_mm2.isZero());
}

TEST(Compensation, TheStateFileKeepsTheEstimateAndABadOneIsNamed) {
  const auto dir = std::filesystem::temp_directory_path() / ("fettle-comp-" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  fp::CellBias b;
  b.bias_mm = Vec3(0.1, -0.2, 0.05);
  b.updates = 7;
  b.calibration_id = "abc";
  b.learned = Vec3(0.0, 0.0, 1.0).asDiagonal();
  b.scatter_mm2(2, 2) = 0.0025;
  ASSERT_TRUE(fp::save_cell_bias(dir / "compensation.json", b));
  const auto r = fp::load_cell_bias(dir / "compensation.json");
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_LT((r->bias_mm - b.bias_mm).norm(), 1e-12);
  EXPECT_EQ(r->updates, 7u);
  EXPECT_EQ(r->calibration_id, "abc");
  EXPECT_LT((r->learned - b.learned).norm(), 1e-12);
  EXPECT_LT((r->scatter_mm2 - b.scatter_mm2).norm(), 1e-12);
  const auto none = fp::load_cell_bias(dir / "missing.json");
  ASSERT_TRUE(none);
  EXPECT_EQ(none->updates, 0u);
  std::ofstream(dir / "bad.json") << "{\"bias_mm\": [1, 2]}";
  const auto bad = fp::load_cell_bias(dir / "bad.json");
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("bad.json"), std::string::npos) << bad.error().message;
  std::filesystem::remove_all(dir);
}

}  // namespace
