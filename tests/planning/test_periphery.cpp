// Ring flash on a wall below the top of a flange (the simulator's pump body): the paper's
// 45-degree chamfer disc cannot reach it without cutting the flange; the side of the disc
// (contact = periphery, tool axis along the parting-plane normal) grinds it flush.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "synthetic_part.hpp"

namespace fettle::planning {
namespace {

using testing::ring_fin;
using testing::sdf_box;
using testing::sdf_cylinder;

/// A flange of radius 45 whose top is at z = 65, on a plate whose top is at z = 35.
double tall_flange_sdf(const Vec3& p) {
  return std::min(sdf_box(p, Vec3(-110, -85, 0), Vec3(110, 85, 35)), sdf_cylinder(p, 0, 0, 45, 0, 65));
}

struct FinScene {
  config::Tool disc;
  config::Region ring;
  RegionInput input;
};

/// A fin 3 mm wide and 1.2 mm thick at z = 50, 15 mm below the flange top.
FinScene fin_scene(config::FlashContact contact) {
  FinScene s;
  s.disc.name = "chamfer-disc";
  s.disc.shape = config::ToolShape::cylinder;
  s.disc.diameter_mm = 40.0;
  s.disc.length_mm = 6.0;
  s.ring.name = "flange-ring";
  s.ring.type = config::RegionType::ring_flash;
  s.ring.tool = "chamfer-disc";
  s.ring.contact = contact;
  s.ring.overlap_mm = 10.0;
  s.ring.allowance_mm = 0.05;
  s.ring.roi_center_mm = {0.0, 0.0, 50.0};
  s.ring.roi_size_mm = {110.0, 110.0, 20.0};
  s.input.region = &s.ring;
  s.input.tool = &s.disc;
  // the camera sees the fin's top face (z = 50.6)
  for (const auto& p : ring_fin(0, 0, 45, 50.6, 3.0, 0.0, 0.5)) s.input.excess_points_part.push_back(p);
  s.input.template_sdf = tall_flange_sdf;
  return s;
}

TEST(PeripheryContact, ChamferDiscAt45DegreesIsRefusedForAFinBelowTheFlangeTop) {
  auto s = fin_scene(config::FlashContact::chamfer);
  s.input.region = &s.ring;
  s.input.tool = &s.disc;
  const auto plan = plan_region(s.input, PlannerSettings{});
  // the disc face reaches into the flange wall above the fin: either no pose or a pose far
  // off the fin; never a pose that cuts the template
  if (plan) {
    for (const auto& p : plan->points)
      EXPECT_LE(tool_penetration_mm(s.disc, p.T_base_tool.to_transform(), tall_flange_sdf), s.ring.allowance_mm + 1e-6);
  } else {
    EXPECT_EQ(plan.error().code, "planning.gouge");
  }
}

TEST(PeripheryContact, DiscSideRunsAlongTheWallWithItsAxisVertical) {
  auto s = fin_scene(config::FlashContact::periphery);
  s.input.region = &s.ring;
  s.input.tool = &s.disc;
  const auto plan = plan_region(s.input, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  ASSERT_GT(plan->points.size(), 280U);  // 2 pi 45 mm at <= 1 mm plus overlap
  for (std::size_t i = 1; i + 1 < plan->points.size(); ++i) {
    const Transform T = plan->points[i].T_base_tool.to_transform();
    EXPECT_NEAR(T.linear().col(2).z(), 1.0, 1e-3) << "point " << i;  // axis along the plane normal
    const Vec3 tip = T.translation();
    // the disc's rim touches the wall: its axis 45 + 20 mm from the flange axis
    EXPECT_NEAR(std::hypot(tip.x(), tip.y()), 65.0 + s.ring.allowance_mm, 0.05) << "point " << i;
    // the disc's height spans the fin (z 49.4 .. 50.6)
    EXPECT_LT(tip.z(), 49.4);
    EXPECT_GT(tip.z() + s.disc.length_mm, 50.6);
    const double pen = tool_penetration_mm(s.disc, T, tall_flange_sdf);
    EXPECT_LE(pen, -s.ring.allowance_mm + 1e-6);
    EXPECT_GE(pen, -s.ring.allowance_mm - 0.05);
  }
}

TEST(PeripheryContact, ValidatedTrajectoryForTheWholeLoop) {
  auto s = fin_scene(config::FlashContact::periphery);
  s.input.region = &s.ring;
  s.input.tool = &s.disc;
  const auto traj = plan_part("pump-body", {s.input}, PlannerSettings{});
  ASSERT_TRUE(traj) << traj.error().message;
  EXPECT_EQ(traj->segment_regions.size(), 1U);
}

TEST(PeripheryContact, BallEquatorOnTheWall) {
  auto s = fin_scene(config::FlashContact::periphery);
  config::Tool ball;
  ball.name = "ball-6";
  ball.shape = config::ToolShape::ball;
  ball.diameter_mm = 6.0;
  s.input.region = &s.ring;
  s.input.tool = &ball;
  const auto plan = plan_region(s.input, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  for (std::size_t i = 1; i + 1 < plan->points.size(); ++i) {
    const Transform T = plan->points[i].T_base_tool.to_transform();
    const Vec3 centre = T.translation() + 3.0 * T.linear().col(2);
    EXPECT_NEAR(std::hypot(centre.x(), centre.y()), 48.0 + s.ring.allowance_mm, 0.05);
    EXPECT_NEAR(centre.z(), 50.6, 0.05);  // on the fitted plane of the fin's top face
  }
}

}  // namespace
}  // namespace fettle::planning
