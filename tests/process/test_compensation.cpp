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

/// What a synthetic cut of `region` starts from: its commanded trajectory and re-scanned ROI
/// (empty), and the re-scan's noise of sigma noise_mm drawn from `seed`.
struct CutStart {
  Cut c;
  fp::RegionVerification rv;
  std::mt19937 rng;
  std::normal_distribution<double> n;
  CutStart(const std::string& region, double noise_mm, unsigned seed) : rng(seed), n(0.0, noise_mm) {
    c.commanded.segment_regions = {region};
    rv.name = region;
  }
};

Cut grooves(const Vec3& offset, bool cross, double noise_mm, unsigned seed) {
  CutStart s("groove", noise_mm, seed);
  Cut& c = s.c;
  fp::RegionVerification& rv = s.rv;
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
        rv.roi_points_part.push_back((q + Vec3(0, 0, s.n(s.rng))).cast<float>());
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

TEST(Compensation, TheSurfaceBesideAFinIsNotACut) {
  // A fin 1.5 mm thick and 2 mm high along x on flat ground at z = 0, ground by the ball with
  // its tip 0.2 mm above the ground (its clearance). The re-scan shows the fin's stub where the
  // tool really was and the ground beside it where it always was: within 1 mm of the ball's
  // surface, in base-frame columns whose first-scan top was the fin. Read as cuts, those would
  // say the tool cut the clearance lower than told, the next plan would keep that much more.
  const auto recipe = ball_recipe();
  const Vec3 offset(0.0, 0.05, -0.06);
  constexpr double kClearance = 0.2, kHalfThickness = 0.75, kHeight = 2.0;
  CutStart s("groove", 0.02, 4);
  for (int i = 0; i <= 60; ++i) {
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = Vec3(-30.0 + i, 0.0, kClearance);
    p.kind = fettle::MoveKind::grind;
    s.c.commanded.points.push_back(p);
  }
  for (double x = -25; x <= 25; x += 0.2)
    for (double y = -5; y <= 5; y += 0.1) {
      const bool fin = std::abs(y) < kHalfThickness;
      s.c.before.scene_part.points.emplace_back(static_cast<float>(x), static_cast<float>(y),
                                                static_cast<float>(fin ? kHeight : 0.0));
      // the stub's top lies on the ball as it really was (commanded + offset); the ground as it was
      const double ball_y = y - offset.y();
      const double stub = kClearance + offset.z() + kRadius - std::sqrt(kRadius * kRadius - ball_y * ball_y);
      s.rv.roi_points_part.emplace_back(static_cast<float>(x), static_cast<float>(y),
                                        static_cast<float>((fin ? stub : 0.0) + s.n(s.rng)));
    }
  s.c.after.regions.push_back(s.rv);
  const auto m = fp::measure_cut_offset(recipe, s.c.before, {s.c.commanded}, s.c.after);
  ASSERT_TRUE(m) << m.error().message;
  EXPECT_NEAR(m->offset_mm.z(), offset.z(), 0.03) << m->describe();
  EXPECT_LT(m->rms_mm, 0.05) << m->describe();
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

// A region whose cut lies 0.12 mm off the cell's along z (its place's share of a hand-eye
// rotation, its wheel's wear) learns that as its own: commanded from it, bounded like the
// cell's, kept while the cell's is updated by the other regions, and forgotten when its wheel
// is changed (the new wheel is larger by the wear it held).
TEST(Compensation, EachRegionLearnsItsOwnOffsetAndForgetsItWithItsWheel) {
  fettle::config::CompensationSection settings;  // gain 0.5, max 0.5 mm
  fp::CellBias bias;
  const Vec3 cell(0.05, 0.0, -0.30), fin(0.05, 0.0, -0.18);
  fp::CutOffset m;
  m.offset_mm = cell;
  m.observed = Eigen::Matrix3d::Identity();
  fp::RegionCutOffset own;
  own.tool = "ball-12";
  own.observed = Vec3(0.0, 0.0, 1.0).asDiagonal();  // the fin's stub looks up: z only
  own.offset_mm = own.observed * fin;
  m.regions["side-fin"] = own;
  for (int cycle = 0; cycle < 6; ++cycle) bias.update(m, settings);
  EXPECT_LT((bias.bias_mm - cell).norm(), 0.01) << bias.describe();
  const Vec3 r = bias.region_bias_mm("side-fin");
  EXPECT_NEAR(r.z(), fin.z(), 0.01);
  EXPECT_NEAR(r.x(), bias.bias_mm.x(), 1e-12);  // sideways: the cell's
  EXPECT_LT((bias.region_bias_mm("riser") - bias.bias_mm).norm(), 1e-12);  // a region it never measured
  const Eigen::Matrix3d bound = 0.04 * Eigen::Matrix3d::Identity();
  const auto placed = bias.region_placement(bound);
  ASSERT_EQ(placed.size(), 1u);
  EXPECT_LT((placed.at("side-fin").bias_mm - r).norm(), 1e-12);
  EXPECT_LT((placed.at("side-fin").bound_mm2 - bound).norm(), 1e-12);
  // a cycle that measures the cell but not the fin leaves the fin's own where it was
  fp::CutOffset cell_only = m;
  cell_only.regions.clear();
  cell_only.offset_mm = cell + Vec3(0.0, 0.0, 0.04);
  bias.update(cell_only, settings);
  EXPECT_NEAR(bias.region_bias_mm("side-fin").z(), r.z(), 1e-12);
  bias.change_tool("flat-16");
  EXPECT_EQ(bias.regions.count("side-fin"), 1u);
  bias.change_tool("ball-12");
  EXPECT_EQ(bias.regions.count("side-fin"), 0u);
  EXPECT_LT((bias.region_bias_mm("side-fin") - bias.bias_mm).norm(), 1e-12);
}

const fettle::config::PartRecipe kNoRegions;  // no tool leans: the TCP's error is vertical

// The TCP's length error moves the cut along the tool's axis only: a wheel whose side grinds a
// wall does not feel it, a flat end or ball over a face feels all of it, and a chamfering tool
// leaning 45 deg moves it sideways by its sine (vertically the bound keeps all of it: the
// recipe's other tools stand straight).
TEST(Compensation, TheTcpsErrorBoundsTheCutAlongTheToolsAxisOnly) {
  fettle::config::SafetySection safety;
  safety.calibration_accuracy_mm = 0.20;
  safety.robot_accuracy_mm = 0.10;
  safety.tcp_accuracy_mm = 0.10;
  safety.robot_repeatability_mm = 0.15;
  const fettle::config::CompensationSection settings;
  auto recipe = ball_recipe().recipe;
  recipe.regions.front().type = fettle::config::RegionType::ring_flash;
  recipe.regions.front().contact = fettle::config::FlashContact::periphery;
  EXPECT_DOUBLE_EQ(fp::largest_tool_tilt_deg(recipe), 0.0);
  const auto side = fp::placement_uncertainty(safety, recipe, fp::CellBias{}, settings);
  EXPECT_NEAR(side.along_mm(Vec3::UnitX()), std::hypot(0.2, 0.1) + 0.15, 1e-9);
  EXPECT_NEAR(side.along_mm(Vec3::UnitY()), std::hypot(0.2, 0.1) + 0.15, 1e-9);
  EXPECT_NEAR(side.along_mm(Vec3::UnitZ()), std::sqrt(0.2 * 0.2 + 0.1 * 0.1 + 0.1 * 0.1) + 0.15, 1e-9);
  recipe.regions.front().contact = fettle::config::FlashContact::chamfer;
  recipe.regions.front().chamfer_deg = 45.0;
  EXPECT_DOUBLE_EQ(fp::largest_tool_tilt_deg(recipe), 45.0);
  const auto leaning = fp::placement_uncertainty(safety, recipe, fp::CellBias{}, settings);
  EXPECT_NEAR(leaning.along_mm(Vec3::UnitX()), std::sqrt(0.2 * 0.2 + 0.1 * 0.1 + 0.5 * 0.1 * 0.1) + 0.15, 1e-9);
  EXPECT_NEAR(leaning.along_mm(Vec3::UnitZ()), std::sqrt(0.2 * 0.2 + 0.1 * 0.1 + 0.1 * 0.1) + 0.15, 1e-9);
}

// The stated accuracies (calibration 0.20, robot 0.15, repeatability 0.15 mm) bound the cut at
// the systematic errors' root sum of squares plus the repeatability, 0.40 mm (the wheel keeps the
// deepest of its noisy poses), until the cell learns a direction; along it the systematic part
// shrinks with the estimate's updates and its scatter, the repeatability stays; the directions it
// never observed keep all of it.
TEST(Compensation, PlacementUncertaintyShrinksAlongWhatTheCellLearnedOnly) {
  fettle::config::SafetySection safety;
  safety.calibration_accuracy_mm = 0.20;
  safety.robot_accuracy_mm = 0.15;
  safety.robot_repeatability_mm = 0.15;
  const fettle::config::CompensationSection settings;  // gain 0.5
  fp::CellBias bias;
  const auto stated = fp::placement_uncertainty(safety, kNoRegions, bias, settings);
  const double all = std::hypot(0.2, 0.15) + 0.15;
  for (const Vec3& n : std::vector<Vec3>{Vec3::UnitX(), Vec3::UnitY(), Vec3::UnitZ(), Vec3(1, 1, 1).normalized()})
    EXPECT_NEAR(stated.along_mm(n), all, 1e-9);
  // cuts that face up: z is learned, a measurement scattered by 0.04 mm about a -0.25 mm offset
  fp::CutOffset up;
  up.observed = Vec3(0.0, 0.0, 1.0).asDiagonal();
  std::vector<double> z_bound;
  for (int k = 0; k < 8; ++k) {
    up.offset_mm = Vec3(0.0, 0.0, -0.25 + (k % 2 == 0 ? 0.04 : -0.04));
    bias.update(up, settings);
    z_bound.push_back(fp::placement_uncertainty(safety, kNoRegions, bias, settings).along_mm(Vec3::UnitZ()));
  }
  const auto learned = fp::placement_uncertainty(safety, kNoRegions, bias, settings);
  EXPECT_NEAR(learned.along_mm(Vec3::UnitX()), all, 1e-9);
  EXPECT_NEAR(learned.along_mm(Vec3::UnitY()), all, 1e-9);
  EXPECT_LT(z_bound.back(), z_bound.front());
  EXPECT_GE(z_bound.back(), 0.15 - 1e-9);  // the repeatability is never learned away
  EXPECT_LT(z_bound.back(), 0.17);         // 0.15 and a third of the scatter (about 0.05 mm squared)
  EXPECT_NE(learned.describe().find("0.40 mm sideways"), std::string::npos) << learned.describe();
  // nothing stated: nothing kept beyond the regions' allowances
  EXPECT_TRUE(fp::placement_uncertainty(fettle::config::SafetySection{}, kNoRegions, bias, settings).bound_mm2.isZero());
}

// A re-grind after a first grind that measured the cut 0.22 mm low (+-0.002) on faces that look
// up: along z it is commanded with that offset and bounded by the repeatability and that scatter
// (0.15 mm, not the 0.40 mm a cell that has learned nothing keeps); sideways, which the cut did
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
  const auto r = fp::regrind_compensation(safety, kNoRegions, cell, measured, settings);
  EXPECT_LT((r.bias_mm - Vec3(0.03, -0.02, -0.22)).norm(), 1e-12);
  EXPECT_NEAR(r.placement.along_mm(Vec3::UnitZ()), std::hypot(0.15, 0.002), 1e-9);
  const double all = std::hypot(0.2, 0.15) + 0.15;
  EXPECT_NEAR(r.placement.along_mm(Vec3::UnitX()), all, 1e-9);
  EXPECT_NEAR(r.placement.along_mm(Vec3::UnitY()), all, 1e-9);
  EXPECT_NEAR(fp::placement_uncertainty(safety, kNoRegions, cell, settings).along_mm(Vec3::UnitZ()), all, 1e-9);
  // nothing stated: nothing kept beyond the regions' allowances
  EXPECT_TRUE(fp::regrind_compensation(fettle::config::SafetySection{}, kNoRegions, cell, measured, settings).placement.bound_mm2.isZero());
}

// Two regions ground by the same ball 150 mm apart, cut 0.12 mm apart in height (a hand-eye
// rotation's lever, a wheel's wear): the whole cut's offset lies between them, each region's
// own is its own, and a re-grind commands each region with its own along what its cut observed.
TEST(Compensation, AReGrindTakesEachRegionsOwnOffset) {
  auto recipe = ball_recipe();
  recipe.recipe.regions.push_back(recipe.recipe.regions.front());
  recipe.recipe.regions.back().name = "far";
  const Vec3 near_offset(0.05, -0.04, -0.25), far_offset(0.05, -0.04, -0.13);
  auto cut = grooves(near_offset, true, 0.03, 7);
  const auto far = grooves(far_offset, false, 0.03, 8);  // one groove along x: x is not observed there
  const Vec3 shift(0.0, 150.0, 0.0);
  for (auto p : far.commanded.points) {
    p.T_base_tool.position_mm += shift;
    cut.commanded.points.push_back(p);
  }
  cut.commanded.segment_regions.push_back("far");
  for (auto& p : cut.commanded.points)
    if (p.T_base_tool.position_mm.y() > 100.0) p.segment = 1;
  for (const auto& p : far.before.scene_part.points) cut.before.scene_part.points.push_back(p + shift.cast<float>());
  auto rv = far.after.regions.front();
  rv.name = "far";
  for (auto& p : rv.roi_points_part) p += shift.cast<float>();
  cut.after.regions.push_back(rv);

  const auto m = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after);
  ASSERT_TRUE(m) << m.error().message;
  ASSERT_EQ(m->regions.count("groove"), 1u);
  ASSERT_EQ(m->regions.count("far"), 1u);
  const auto& g = m->regions.at("groove");
  const auto& f = m->regions.at("far");
  EXPECT_LT((g.offset_mm - near_offset).norm(), 0.02);
  EXPECT_NEAR(f.offset_mm.z(), far_offset.z(), 0.02);
  EXPECT_NEAR(f.offset_mm.y(), far_offset.y(), 0.02);
  EXPECT_LT((f.observed * Vec3::UnitX()).norm(), 0.1);  // the far groove runs along x
  // the whole cut's height is neither region's
  EXPECT_GT(std::abs(m->offset_mm.z() - far_offset.z()), 0.04) << m->describe();

  fettle::config::SafetySection safety;
  safety.calibration_accuracy_mm = 0.20;
  safety.robot_accuracy_mm = 0.15;
  safety.robot_repeatability_mm = 0.15;
  fp::CellBias cell;
  cell.bias_mm = Vec3(0.02, 0.0, -0.1);
  const auto rc = fp::regrind_compensation(safety, recipe.recipe, cell, *m, fettle::config::CompensationSection{});
  ASSERT_EQ(rc.regions.count("far"), 1u);
  const auto& rf = rc.regions.at("far");
  EXPECT_NEAR(rf.bias_mm.z(), far_offset.z(), 0.02);
  // along x, which the far groove did not observe, the whole cut's (observed by the near cross)
  EXPECT_NEAR(rf.bias_mm.x(), rc.bias_mm.x(), 0.005);
  EXPECT_NEAR(std::sqrt(Vec3::UnitZ().dot(rf.bound_mm2 * Vec3::UnitZ())), 0.15, 0.01);
  EXPECT_NEAR(rc.regions.at("groove").bias_mm.z(), near_offset.z(), 0.02);
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
  b.tools["flat-16"].removed_cm3 = 12.5;
  b.tools["flat-16"].changes = 2;
  b.tools["chamfer-disc"].sum_wv = 0.3;
  b.tools["chamfer-disc"].sum_vv = 4.0;
  b.tools["chamfer-disc"].measurements = 3;
  b.regions["side-fin"] = fp::RegionBias{Vec3(0.0, 0.0, -0.12), Vec3(0.0, 0.0, 1.0).asDiagonal(), "ball-12", 4};
  ASSERT_TRUE(fp::save_cell_bias(dir / "compensation.json", b));
  const auto r = fp::load_cell_bias(dir / "compensation.json");
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_LT((r->bias_mm - b.bias_mm).norm(), 1e-12);
  EXPECT_EQ(r->updates, 7u);
  EXPECT_EQ(r->calibration_id, "abc");
  EXPECT_LT((r->learned - b.learned).norm(), 1e-12);
  EXPECT_LT((r->scatter_mm2 - b.scatter_mm2).norm(), 1e-12);
  ASSERT_EQ(r->tools.size(), 2u);
  EXPECT_DOUBLE_EQ(r->tools.at("flat-16").removed_cm3, 12.5);
  EXPECT_EQ(r->tools.at("flat-16").changes, 2u);
  fettle::config::Tool disc;
  disc.wear_mm_per_cm3 = 0.05;
  EXPECT_DOUBLE_EQ(r->tools.at("chamfer-disc").rate_mm_per_cm3(disc), 0.075);
  EXPECT_EQ(r->tools.at("chamfer-disc").measurements, 3u);
  ASSERT_EQ(r->regions.count("side-fin"), 1u);
  EXPECT_EQ(r->regions.at("side-fin").tool, "ball-12");
  EXPECT_EQ(r->regions.at("side-fin").updates, 4u);
  EXPECT_LT((r->region_bias_mm("side-fin") - Vec3(0.1, -0.2, -0.12)).norm(), 1e-12);
  const auto none = fp::load_cell_bias(dir / "missing.json");
  ASSERT_TRUE(none);
  EXPECT_EQ(none->updates, 0u);
  std::ofstream(dir / "bad.json") << "{\"bias_mm\": [1, 2]}";
  const auto bad = fp::load_cell_bias(dir / "bad.json");
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("bad.json"), std::string::npos) << bad.error().message;
  std::filesystem::remove_all(dir);
}

/// A recipe with one region ground by the side of a 40 mm disc (axis along base z).
fp::LoadedRecipe disc_recipe() {
  fp::LoadedRecipe r;
  fettle::config::Tool disc;
  disc.name = "chamfer-disc";
  disc.shape = fettle::config::ToolShape::cylinder;
  disc.diameter_mm = 40.0;
  disc.length_mm = 6.0;
  r.recipe.tools.push_back(disc);
  fettle::config::Region region;
  region.name = "ring";
  region.tool = "chamfer-disc";
  region.roi_center_mm = {0.0, 0.0, 5.0};
  region.roi_size_mm = {200.0, 200.0, 20.0};
  r.recipe.regions.push_back(region);
  return r;
}

/// The disc's side ground round a fin on a ring: the disc's axis goes round a 50 mm circle
/// (tip at z = 0), and the re-scan shows the wall it left where the disc really was (offset)
/// with its real radius (commanded less `wear`), facing the ring's centre.
Cut ring_wall(const Vec3& offset, double wear, double noise_mm, unsigned seed) {
  CutStart s("ring", noise_mm, seed);
  Cut& c = s.c;
  fp::RegionVerification& rv = s.rv;
  const double R = 20.0 - wear;
  for (int i = 0; i < 360; ++i) {
    const double a = i * M_PI / 180.0;
    const Vec3 u(std::cos(a), std::sin(a), 0.0);
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = 50.0 * u;
    p.kind = fettle::MoveKind::grind;
    c.commanded.points.push_back(p);
    for (double z = 1.0; z <= 5.0; z += 1.0) {
      const Vec3 q = 50.0 * u + offset - R * u + Vec3(0, 0, z) + s.n(s.rng) * u;
      rv.roi_points_part.push_back(q.cast<float>());
      // the fin stood 3 mm higher over the same place
      c.before.scene_part.points.emplace_back(static_cast<float>(q.x()), static_cast<float>(q.y()), 9.0f);
    }
  }
  c.after.regions.push_back(rv);
  return c;
}

TEST(Compensation, AWornDiscsRadiusIsMeasuredApartFromTheOffset) {
  const auto recipe = disc_recipe();
  const Vec3 offset(0.1, -0.08, 0.0);
  const auto cut = ring_wall(offset, 0.4, 0.03, 5);
  const auto m = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after);
  ASSERT_TRUE(m) << m.error().message;
  ASSERT_EQ(m->tools.count("chamfer-disc"), 1u) << m->describe();
  EXPECT_NEAR(m->tools.at("chamfer-disc").wear_mm, 0.4, 0.02);
  EXPECT_LT(m->tools.at("chamfer-disc").std_mm, 0.01);
  EXPECT_NEAR(m->offset_mm.x(), 0.1, 0.02) << m->describe();
  EXPECT_NEAR(m->offset_mm.y(), -0.08, 0.02) << m->describe();
  // the wall's normals all lie across the axis: the height is not observed
  EXPECT_EQ(m->observed_directions(), 2) << m->describe();
  // planned with the disc worn 0.3 mm, the cut shows the 0.1 mm it wore beyond that
  const auto again = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after, {{"chamfer-disc", 0.3}});
  ASSERT_TRUE(again) << again.error().message;
  ASSERT_EQ(again->tools.count("chamfer-disc"), 1u);
  EXPECT_NEAR(again->tools.at("chamfer-disc").wear_mm, 0.1, 0.02);
}

/// A ring's fin as the cell's camera sees it from above, before and after a disc's side ground
/// it: the flange (r < 45, its top at z = 15), the fin standing out of its wall to r = 48 (its
/// top at z = 0.5) and the body's top at z = -12 beyond. The disc (axis vertical, its 6 mm
/// height centred on z = 0) is commanded round the flange `clearance` off the wall; it really
/// went `offset` off that and was `wear` smaller, so the fin's stub reaches out to
/// 45 + clearance + wear + offset . u. The wall is edge-on: the stub's top is all the re-scan
/// shows of the disc's side. `ground` false: the disc never came (the re-scan is the first scan).
Cut ring_fin(const Vec3& offset, double wear, double clearance, double noise_mm, unsigned seed, bool ground = true) {
  CutStart s("ring", noise_mm, seed);
  Cut& c = s.c;
  for (int i = 0; i < 360; ++i) {
    const double a = i * M_PI / 180.0;
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = (45.0 + clearance + 20.0) * Vec3(std::cos(a), std::sin(a), 0.0) - Vec3(0, 0, 3.0);
    p.kind = fettle::MoveKind::grind;
    c.commanded.points.push_back(p);
  }
  constexpr double kPixel = 0.15;  // the camera's pitch on the part at 600 mm
  for (double x = -52; x <= 52; x += kPixel)
    for (double y = -52; y <= 52; y += kPixel) {
      const double r = std::hypot(x, y);
      if (r < 40.0 || r > 52.0) continue;
      const Vec3 u(x / r, y / r, 0.0);
      const double stub = ground ? 45.0 + clearance + wear + offset.dot(u) : 48.0;
      const auto height = [&](double fin) { return r < 45.0 ? 15.0 : r < fin ? 0.5 : -12.0; };
      c.before.scene_part.points.emplace_back(static_cast<float>(x), static_cast<float>(y),
                                              static_cast<float>(height(48.0) + s.n(s.rng)));
      s.rv.roi_points_part.emplace_back(static_cast<float>(x), static_cast<float>(y),
                                        static_cast<float>(height(stub) + s.n(s.rng)));
    }
  c.after.regions.push_back(s.rv);
  return c;
}

TEST(Compensation, AWornDiscShowsItsRadiusInTheStubItLeaves) {
  // The stub's outer edge is where the real disc stopped: its width round the ring splits into
  // the disc's shortfall (the same all round) and the offset across the axis (cos-shaped).
  const auto recipe = disc_recipe();
  const Vec3 offset(0.1, -0.08, 0.0);
  const auto cut = ring_fin(offset, 0.5, 0.3, 0.03, 11);
  const auto m = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after);
  ASSERT_TRUE(m) << m.error().message;
  ASSERT_EQ(m->tools.count("chamfer-disc"), 1u) << m->describe();
  const double wear = m->tools.at("chamfer-disc").wear_mm;
  // the samples lie within stub_edge_mm of the edge, nearer the wall: the radius is measured
  // short by up to that much, never long (a disc planned smaller than it is cuts the wall)
  EXPECT_LE(wear, 0.5 + 0.02);
  EXPECT_GE(wear, 0.5 - 0.12);
  EXPECT_NEAR(m->offset_mm.x(), 0.1, 0.03) << m->describe();
  EXPECT_NEAR(m->offset_mm.y(), -0.08, 0.03) << m->describe();
  ASSERT_EQ(m->regions.count("ring"), 1u);
  EXPECT_NEAR(m->regions.at("ring").offset_mm.x(), 0.1, 0.03);
  // planned with the disc worn 0.3 mm, the stub shows the 0.2 mm it wore beyond that
  const auto again = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after, {{"chamfer-disc", 0.3}});
  ASSERT_TRUE(again) << again.error().message;
  ASSERT_EQ(again->tools.count("chamfer-disc"), 1u);
  EXPECT_NEAR(again->tools.at("chamfer-disc").wear_mm, wear - 0.3, 0.03);
}

TEST(Compensation, AReGrindTakesTheWearItsCycleMeasured) {
  // The disc was planned worn 0.1 mm; its stub says 0.4 mm more (+- 0.02): the re-grind plans it
  // at least 0.1 + 0.4 - 2 x 0.02 worn. The ball's radius did not show: the cell's least stays.
  fp::CutOffset measured;
  measured.tools["chamfer-disc"] = fp::ToolWearMeasured{0.4, 0.02, 800};
  const fp::ToolWearMm commanded{{"chamfer-disc", 0.1}, {"ball-12", 0.05}};
  const fp::ToolWearMm cell_least{{"chamfer-disc", 0.1}, {"ball-12", 0.05}};
  auto w = fp::regrind_tool_wear(cell_least, measured, commanded);
  EXPECT_NEAR(w.at("chamfer-disc"), 0.46, 1e-12);
  EXPECT_DOUBLE_EQ(w.at("ball-12"), 0.05);
  // a measurement within its own scatter of nothing never takes the least below the cell's
  measured.tools["chamfer-disc"] = fp::ToolWearMeasured{0.01, 0.02, 800};
  w = fp::regrind_tool_wear(cell_least, measured, commanded);
  EXPECT_DOUBLE_EQ(w.at("chamfer-disc"), 0.1);
}

TEST(Compensation, AFinsOwnEdgeIsNotAWheelsEdge) {
  // The fin stands into the commanded disc where the disc never came: its own edge is not cut
  // (the first scan ended there too) and says nothing of the disc's radius.
  const auto recipe = disc_recipe();
  const auto cut = ring_fin(Vec3::Zero(), 0.5, 0.3, 0.03, 12, false);
  const auto m = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after);
  EXPECT_FALSE(m) << m->describe();
}

TEST(Compensation, ABallsRadiusAgainstAGroovesBottomIsLeftToTheOffset) {
  // a groove's bottom looks up: the ball's radius and the offset's height move it alike, and
  // the fit does not split them by guesswork
  const auto recipe = ball_recipe();
  const auto cut = grooves(Vec3(0.0, 0.0, -0.1), true, 0.03, 6);
  const auto m = fp::measure_cut_offset(recipe, cut.before, {cut.commanded}, cut.after);
  ASSERT_TRUE(m) << m.error().message;
  EXPECT_EQ(m->tools.count("ball-12"), 0u) << m->tools.begin()->second.wear_mm;
  EXPECT_NEAR(m->offset_mm.z(), -0.1, 0.02) << m->describe();
}

// A wheel whose side finishes a region and whose rate is only stated: planned at its least wear
// (none) and worn by up to its most, it leaves a stub that wide beside the wall. Once that could
// pass the verification's 0.3 mm level less the region's allowance, the cell asks for a new
// wheel, long before its life; a cup wheel's flat end on a riser leaves nothing, its life holds.
TEST(Compensation, AWheelWhoseWearIsNotKnownWellEnoughIsChanged) {
  fettle::config::PartRecipe recipe;
  fettle::config::Tool disc;
  disc.name = "chamfer-disc";
  disc.shape = fettle::config::ToolShape::cylinder;
  disc.wear_mm_per_cm3 = 0.05;
  disc.wear_tolerance_pct = 30.0;
  disc.max_wear_mm = 5.0;
  fettle::config::Tool cup = disc;
  cup.name = "flat-16";
  recipe.tools = {disc, cup};
  fettle::config::Region ring;
  ring.name = "flange-ring";
  ring.type = fettle::config::RegionType::ring_flash;
  ring.tool = "chamfer-disc";
  ring.allowance_mm = 0.12;
  fettle::config::Region riser;
  riser.name = "riser";
  riser.type = fettle::config::RegionType::riser;
  riser.tool = "flat-16";
  recipe.regions = {ring, riser};
  ASSERT_TRUE(fp::wear_slack_mm(recipe, disc).has_value());
  EXPECT_NEAR(*fp::wear_slack_mm(recipe, disc), 0.18, 1e-12);
  EXPECT_FALSE(fp::wear_slack_mm(recipe, cup).has_value());

  fp::CellBias bias;
  // 2 cm3 so far and 0.5 more: at most 1.3 x 0.05 x 2.5 = 0.1625 mm, the least 0: within 0.18
  bias.add_removed({{"chamfer-disc", 2.0}, {"flat-16", 2.0}});
  EXPECT_TRUE(bias.worn_out(recipe, {{"chamfer-disc", 0.5}, {"flat-16", 0.5}}).empty());
  // 3 cm3 and 0.5 more: up to 0.2275 mm, more than the ring's finish leaves unknown
  bias.add_removed({{"chamfer-disc", 1.0}, {"flat-16", 1.0}});
  const auto worn = bias.worn_out(recipe, {{"chamfer-disc", 0.5}, {"flat-16", 0.5}});
  ASSERT_EQ(worn.size(), 1u);
  EXPECT_EQ(worn[0].tool, "chamfer-disc");
  EXPECT_NE(worn[0].why.find("0.18 mm"), std::string::npos) << worn[0].why;
  // a measured rate narrows the range: three cuts that showed the radius on one line
  for (int k = 0; k < 3; ++k) {
    fp::CutOffset measured;
    measured.tools["chamfer-disc"] = fp::ToolWearMeasured{0.04 * (3.0 + k), 0.005, 900};
    bias.add_wear_measurements(measured, bias.tool_wear_mm(recipe));
    if (k < 2) bias.add_removed({{"chamfer-disc", 1.0}});
  }
  EXPECT_TRUE(bias.worn_out(recipe, {{"chamfer-disc", 0.5}}).empty());
}

TEST(Compensation, AWheelsWearIsPredictedFromTheIronItRemovedAtItsMeasuredRate) {
  fettle::config::PartRecipe recipe;
  fettle::config::Tool disc;
  disc.name = "chamfer-disc";
  disc.wear_mm_per_cm3 = 0.05;    // stated ...
  disc.wear_tolerance_pct = 30.0;  // ... within 30 %
  disc.max_wear_mm = 1.0;
  recipe.tools.push_back(disc);
  fp::CellBias bias;
  EXPECT_DOUBLE_EQ(bias.tool_wear(recipe).at("chamfer-disc").most_mm, 0.0);
  // the stated rate and its tolerance until the cut has shown the radius three times; the
  // wheel's own rate is 0.07 mm/cm3
  const double truth = 0.07;
  for (int cycle = 1; cycle <= 3; ++cycle) {
    bias.add_removed({{"chamfer-disc", 4.0}});
    const auto w = bias.tool_wear(recipe).at("chamfer-disc");
    if (cycle < 3) {
      EXPECT_NEAR(w.expected_mm, 0.05 * 4.0 * cycle, 1e-12);
      EXPECT_DOUBLE_EQ(w.least_mm, 0.0);  // a stated rate may not hold for this wheel at all
      EXPECT_NEAR(w.most_mm, 1.3 * w.expected_mm, 1e-12);
    }
    if (cycle == 2) {  // at most 1.3 x 0.05 x 12 = 0.78 mm after one more casting: within its life
      EXPECT_TRUE(bias.worn_out(recipe, {{"chamfer-disc", 4.0}}).empty());
    }
    // planned with the least, the cut shows what the wheel wore beyond it
    const auto planned = bias.tool_wear_mm(recipe);
    fp::CutOffset measured;
    measured.tools["chamfer-disc"] = fp::ToolWearMeasured{truth * 4.0 * cycle - planned.at("chamfer-disc"), 0.005, 900};
    bias.add_wear_measurements(measured, planned);
  }
  auto w = bias.tool_wear(recipe).at("chamfer-disc");
  EXPECT_NEAR(w.expected_mm, 0.84, 1e-9);
  EXPECT_NEAR(w.least_mm, 0.84, 1e-9);  // three measurements on one line: no scatter left
  EXPECT_NEAR(w.most_mm, 0.84, 1e-9);
  // its life: 0.07 x 16 = 1.12 mm after one more casting like the last
  const auto worn = bias.worn_out(recipe, {{"chamfer-disc", 4.0}});
  ASSERT_EQ(worn.size(), 1u);
  EXPECT_EQ(worn[0].tool, "chamfer-disc");
  EXPECT_NE(worn[0].why.find("its life: 1.00 mm"), std::string::npos) << worn[0].why;
  // a new wheel starts from zero at the rate its kind showed
  bias.change_tool("chamfer-disc");
  EXPECT_DOUBLE_EQ(bias.tool_wear(recipe).at("chamfer-disc").most_mm, 0.0);
  bias.add_removed({{"chamfer-disc", 2.0}});
  EXPECT_NEAR(bias.tool_wear(recipe).at("chamfer-disc").expected_mm, 0.14, 1e-9);
  EXPECT_EQ(bias.tools.at("chamfer-disc").changes, 1u);
  // a scattered measurement widens the range again
  bias.add_removed({{"chamfer-disc", 2.0}});
  fp::CutOffset off;
  off.tools["chamfer-disc"] = fp::ToolWearMeasured{0.1, 0.005, 900};
  bias.add_wear_measurements(off, bias.tool_wear_mm(recipe));
  w = bias.tool_wear(recipe).at("chamfer-disc");
  EXPECT_LT(w.least_mm, w.expected_mm - 0.01);
  EXPECT_GT(w.most_mm, w.expected_mm + 0.01);
}

TEST(Compensation, TheIronRemovedIsWhatTheReScanLacksAgainstTheFirstScan) {
  const auto recipe = disc_recipe();
  fettle::vision::Inspection before;
  fp::VerificationResult after;
  fp::RegionVerification rv;
  rv.name = "ring";
  // 20 x 10 mm ground from 5 mm down to 2 mm, and beside it 20 x 10 mm the tool left as it was
  // (0.05 mm of the scanner's noise lower: not iron removed)
  for (double x = 0.05; x < 20.0; x += 0.1)
    for (double y = 0.05; y < 20.0; y += 0.1) {
      before.scene_part.points.emplace_back(static_cast<float>(x), static_cast<float>(y), 5.0f);
      rv.roi_points_part.emplace_back(static_cast<float>(x), static_cast<float>(y), y < 10.0 ? 2.0f : 4.95f);
    }
  // a 8 mm step both scans see, the re-scan without the top's last 0.5 mm (a wall's top edge one
  // scan samples and the other does not): no iron removed
  for (double x = 30.05; x < 40.0; x += 0.1)
    for (double y = 0.05; y < 20.0; y += 0.1) {
      before.scene_part.points.emplace_back(static_cast<float>(x), static_cast<float>(y), x < 35.0 ? 10.0f : 2.0f);
      rv.roi_points_part.emplace_back(static_cast<float>(x), static_cast<float>(y), x < 34.5 ? 10.0f : 2.0f);
    }
  // and a feature above the ROI's box (z 15-20) over part of it, which the re-scan's ROI leaves out
  for (double x = 0.05; x < 5.0; x += 0.1)
    for (double y = 0.05; y < 20.0; y += 0.1)
      before.scene_part.points.emplace_back(static_cast<float>(x), static_cast<float>(y), 18.0f);
  after.regions.push_back(rv);
  const auto removed = fp::measure_removed_cm3(recipe, before, after);
  ASSERT_EQ(removed.count("chamfer-disc"), 1u);
  // 3 mm x 200 mm2 = 0.6 cm3 less the row of 0.6 mm columns along the edge to the unground face,
  // whose neighbours hold that face (0.55 cm3); the step adds nothing (0.1 cm3 if it did)
  EXPECT_NEAR(removed.at("chamfer-disc"), 0.575, 0.03);
  // a fin standing out from a wall: the first inspection found 0.3 cm3 along the template's
  // normals where the columns see 3 mm of air under it
  fettle::vision::RegionResult fin;
  fin.name = "ring";
  fin.excess.volume_mm3 = 300.0;
  before.regions.push_back(fin);
  EXPECT_NEAR(fp::measure_removed_cm3(recipe, before, after).at("chamfer-disc"), 0.3, 1e-9);
}

}  // namespace
