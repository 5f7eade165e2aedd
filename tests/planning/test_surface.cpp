// The sampled-template signed distance against the analytic one, and a plan on it.
#include <gtest/gtest.h>

#include <cmath>

#include "fettle/planning/surface.hpp"
#include "synthetic_part.hpp"

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
