// The sampled-template signed distance against the analytic one, and a plan on it.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "fettle/planning/surface.hpp"
#include "synthetic_part.hpp"
#include "../support/draws.hpp"

namespace fettle::planning {
namespace {

/// Samples of the pad top (z = 45) around the riser and of the pad's walls, 0.5 mm apart.
void sample_pad(std::vector<Vec3>& pts, std::vector<Vec3>& nrm) {
  for (double x = -110; x <= -62; x += 0.5)
    for (double y = 22; y <= 85; y += 0.5) pts.emplace_back(x, y, 45.0), nrm.push_back(Vec3::UnitZ());
  for (double x = -110; x <= -62; x += 0.5)
    for (double z = 35; z <= 45; z += 0.5) pts.emplace_back(x, 22.0, z), nrm.push_back(-Vec3::UnitY());
}

TEST(SampledSdf, MatchesTheAnalyticDistanceNearTheSurface) {
  std::vector<Vec3> pts, nrm;
  sample_pad(pts, nrm);
  const auto sdf = sdf_from_samples(pts, nrm);
  for (const Vec3& p : {Vec3(-80, 50, 45.3), Vec3(-80.2, 50.1, 44.6), Vec3(-70.3, 60.7, 47.0), Vec3(-90, 23, 44.0)}) {
    EXPECT_NEAR(sdf(p), testing::part_sdf(p), 0.3) << p.transpose();
    EXPECT_EQ(sdf(p) > 0, testing::part_sdf(p) > 0) << p.transpose();
  }
  EXPECT_DOUBLE_EQ(sdf(Vec3(0, 0, 500)), 20.0);  // nothing near: far outside
  EXPECT_THROW(sdf_from_samples({Vec3::Zero()}, {}), std::invalid_argument);
}

/// A box's edge as a height-field sampler draws it: top samples stop short of the edge, wall
/// samples start half a spacing below the top, both with exact normals.
void sample_step(std::vector<Vec3>& pts, std::vector<Vec3>& nrm, bool wall_top_sample) {
  for (double x = -20; x <= -0.25; x += 0.5)
    for (double y = -10; y <= 10; y += 0.5) pts.emplace_back(x, y, 10.0), nrm.push_back(Vec3::UnitZ());
  for (double z = 0.25; z < 10.0; z += 0.5)
    for (double y = -10; y <= 10; y += 0.5) pts.emplace_back(0.0, y, z), nrm.push_back(Vec3::UnitX());
  if (wall_top_sample)
    for (double y = -10; y <= 10; y += 0.5) pts.emplace_back(0.0, y, 10.0), nrm.push_back(Vec3::UnitX());
  for (double x = 0.25; x <= 20; x += 0.5)  // the floor beside the step
    for (double y = -10; y <= 10; y += 0.5) pts.emplace_back(x, y, 0.0), nrm.push_back(Vec3::UnitZ());
}

TEST(SampledSdf, EdgesAreNeitherFalseGougesNorFalseContacts) {
  for (const bool wall_top_sample : {false, true}) {
    std::vector<Vec3> pts, nrm;
    sample_step(pts, nrm, wall_top_sample);
    const auto sdf = sdf_from_samples(pts, nrm);
    // Just above the top near the convex edge (the wall's top sample is nearest when it
    // exists; its tangent plane put this point 0.2 mm inside).
    EXPECT_NEAR(sdf(Vec3(-0.2, 0.1, 10.05)), 0.05, 0.03) << wall_top_sample;
    // High above the wall's top edge: the wall's tangent plane said 0 here. Off the sampled
    // patch the distance may come out short by up to one spacing (0.5 mm), never long.
    for (const Vec3& p : {Vec3(0.0, 0.0, 23.3), Vec3(0.5, 0.0, 13.0)}) {
      const double truth = std::hypot(p.x(), p.z() - 10.0);
      EXPECT_LE(sdf(p), truth + 0.05) << p.transpose() << " " << wall_top_sample;
      EXPECT_GE(sdf(p), truth - 0.6) << p.transpose() << " " << wall_top_sample;
    }
    // Inside below the edge: negative, the nearer face counts.
    EXPECT_NEAR(sdf(Vec3(-0.2, 0.0, 9.9)), -0.1, 0.03) << wall_top_sample;
    // Beside the wall and above the floor (concave corner): the nearer face.
    EXPECT_NEAR(sdf(Vec3(0.3, 0.0, 0.2)), 0.2, 0.05) << wall_top_sample;
    EXPECT_NEAR(sdf(Vec3(5.0, 0.0, 3.0)), 3.0, 0.05) << wall_top_sample;
  }
}

// Just past a wall's top edge and above the top (a flat tool's rim over the riser pad's edge):
// the wall's top sample is nearest, the point is off its sampled patch, and the wall's plane
// alone says 0.03 mm for a point 0.25 mm above the top, however high the tool lifts, so a riser
// plan beside the pad would be refused. Outside a convex edge both planes bound the distance.
TEST(SampledSdf, DiagonallyOffAConvexEdgeTheDistanceIsNotTheWallsAlone) {
  for (const bool wall_top_sample : {false, true}) {
    std::vector<Vec3> pts, nrm;
    sample_step(pts, nrm, wall_top_sample);
    const auto sdf = sdf_from_samples(pts, nrm);
    for (const Vec3& p : {Vec3(0.03, 0.1, 10.25), Vec3(0.1, 2.3, 10.5), Vec3(0.02, -4.0, 10.4)}) {
      const double truth = std::hypot(p.x(), p.z() - 10.0);
      EXPECT_GE(sdf(p), truth - 0.06) << p.transpose() << " " << wall_top_sample;
      EXPECT_LE(sdf(p), truth + 0.05) << p.transpose() << " " << wall_top_sample;
    }
  }
}

// A sampled edge is rarely exact: the top face's last sample can sit a few hundredths of a
// millimetre beside the wall's plane (a wall sampled as a staircase). Judged from the wall's
// side alone that convex edge looks concave, the top's tangent plane wins, and points beside
// the wall below the top read as inside: a burr beside the boss would be refused for a 12.8 mm
// "gouge" 9 mm from it. The convexity test is symmetric: the edge is judged from both sides.
TEST(SampledSdf, AConvexEdgeStaysConvexWhenTheTopSampleOverhangsTheWall) {
  std::vector<Vec3> pts, nrm;
  for (double x = -19.95; x <= 0.06; x += 0.5)  // the top's last column at x = +0.05, beside the wall
    for (double y = -10.4; y <= -0.39; y += 0.5) pts.emplace_back(x, y, 10.0), nrm.push_back(Vec3::UnitZ());
  for (double y = -10.0; y <= 0.01; y += 0.5)  // the wall x = 0, its top sample 0.8 mm below the top
    for (double z = 9.2; z > 0.0; z -= 0.5) pts.emplace_back(0.0, y, z), nrm.push_back(Vec3::UnitX());
  const auto sdf = sdf_from_samples(pts, nrm);
  // beside the wall's top corner, the wall's sample nearest: outside, at the distance to the
  // corner or short of it by at most one spacing (off the sampled patch)
  for (const Vec3& p : {Vec3(8.0, 3.0, 9.2), Vec3(3.0, 1.0, 9.2), Vec3(1.0, 0.5, 9.0)}) {
    const double truth = std::hypot(p.x(), p.y());
    EXPECT_GT(sdf(p), truth - 0.55) << p.transpose();
    EXPECT_LE(sdf(p), truth + 0.05) << p.transpose();
  }
  EXPECT_NEAR(sdf(Vec3(-0.3, -5.0, 9.8)), -0.2, 0.05);  // inside below the edge stays inside
}

// The nearest-sample search skips shells of cells known to be empty; the answer must not depend
// on the cell size: one 200 mm cell is a brute-force search over every sample.
TEST(SampledSdf, TheAnswerDoesNotDependOnTheCellSize) {
  std::vector<Vec3> pts, nrm;
  sample_pad(pts, nrm);
  // the pad's top and wall samples meet in coincident points with different normals: an exact
  // tie that any search order may break either way; move the wall's off the top's
  for (std::size_t i = 0; i < pts.size(); ++i)
    if (nrm[i].y() < -0.5) pts[i].x() += 0.013;
  const auto brute = sdf_from_samples(pts, nrm, 200.0, 25.0);
  const auto coarse = sdf_from_samples(pts, nrm, 4.0, 25.0);
  const auto fine = sdf_from_samples(pts, nrm, 0.7, 25.0);
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> x(-150.0, -20.0), y(-20.0, 125.0), z(0.0, 90.0);
  int far = 0;
  for (int k = 0; k < 3000; ++k) {
    const double pz = z(rng), py = y(rng), px = x(rng);  // sequenced as gcc drew them (tests/support/draws.hpp)
    const Vec3 p(px, py, pz);  // in the air, near the pad, and beyond the samples' box
    const double b = brute(p);
    far += b >= 25.0 ? 1 : 0;
    ASSERT_DOUBLE_EQ(coarse(p), b) << p.transpose();
    ASSERT_DOUBLE_EQ(fine(p), b) << p.transpose();
  }
  EXPECT_GT(far, 100);  // some queries had no sample within reach
}

TEST(SampledSdf, RiserPlanOnSamplesLeavesTheAllowance) {
  auto scene = testing::make_scene();
  std::vector<Vec3> pts, nrm;
  sample_pad(pts, nrm);
  scene.inputs[1].template_sdf = sdf_from_samples(pts, nrm);
  const auto plan = plan_region(scene.inputs[1], PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_EQ(plan->segments, static_cast<int>(std::ceil((plan->max_excess_mm - 0.05) / 2.0)));
  for (const auto& p : plan->points)
    if (p.segment == plan->segments - 1 && p.kind == MoveKind::grind) {
      EXPECT_NEAR(p.T_base_tool.position_mm.z(), 45.05, 0.02);
    }
}

}  // namespace
}  // namespace fettle::planning
