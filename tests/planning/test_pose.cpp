// The chamfer pose equations (Zhu et al. 2022, Eqs. 17–21) against hand-computed cases.
#include <gtest/gtest.h>

#include <cmath>

#include "fettle/planning/planner.hpp"

namespace fettle::planning {
namespace {

void expect_vec(const Vec3& a, const Vec3& b, double tol = 1e-9) {
  EXPECT_NEAR(a.x(), b.x(), tol);
  EXPECT_NEAR(a.y(), b.y(), tol);
  EXPECT_NEAR(a.z(), b.z(), tol);
}

TEST(ChamferPose, FortyFiveDegreesPutsTheCentreHalfRootTwoRAlongNAndW) {
  // contact at the flange's edge, n radial (+x), parting plane normal w = +z, R = 20 mm
  const Vec3 P(45.0, 0.0, 50.0);
  const auto cp = chamfer_pose(P, Vec3::UnitX(), Vec3::UnitZ(), 20.0, deg_to_rad(45.0));
  const double h = 20.0 * std::sqrt(2.0) / 2.0;  // 14.142135623...
  expect_vec(cp.tool_center, Vec3(45.0 + h, 0.0, 50.0 + h));
  expect_vec(cp.t, Vec3(0.0, -1.0, 0.0));  // t = n × w = x × z = -y
  expect_vec(cp.tool_axis, Vec3(std::sqrt(0.5), 0.0, std::sqrt(0.5)));
  // TCP at the tip: Q − R·z = P; tool z = axis, tool x = t
  expect_vec(cp.T_part_tool.translation(), P);
  expect_vec(cp.T_part_tool.linear().col(2), cp.tool_axis);
  expect_vec(cp.T_part_tool.linear().col(0), cp.t);
  EXPECT_NEAR((cp.tool_center - P).norm(), 20.0, 1e-12);
  EXPECT_NEAR(cp.T_part_tool.linear().determinant(), 1.0, 1e-12);
}

TEST(ChamferPose, ThirtyDegreesOnATiltedParting) {
  // n = +y, w = +z: θ = 30° → Q = P + R (cos30 n + sin30 w), R = 6 (ball-12)
  const Vec3 P(0.0, 7.0, 47.0);
  const auto cp = chamfer_pose(P, Vec3::UnitY(), Vec3::UnitZ(), 6.0, deg_to_rad(30.0));
  expect_vec(cp.tool_center, Vec3(0.0, 7.0 + 6.0 * std::sqrt(3.0) / 2.0, 47.0 + 3.0));
  expect_vec(cp.t, Vec3(1.0, 0.0, 0.0));  // y × z = x

  // the same case rotated: w tilted 10° about x, n perpendicular to it
  const Eigen::Matrix3d Rx = Eigen::AngleAxisd(deg_to_rad(10.0), Vec3::UnitX()).toRotationMatrix();
  const auto tilted = chamfer_pose(Rx * P, Rx * Vec3::UnitY(), Rx * Vec3::UnitZ(), 6.0, deg_to_rad(30.0));
  expect_vec(tilted.tool_center, Rx * cp.tool_center);
  expect_vec(tilted.t, Rx * cp.t);
}

TEST(ChamferPose, NinetyDegreesIsStraightAlongThePlaneNormal) {
  const auto cp = chamfer_pose(Vec3(1, 2, 3), Vec3::UnitX(), Vec3::UnitZ(), 5.0, deg_to_rad(90.0));
  expect_vec(cp.tool_center, Vec3(1, 2, 8));
  expect_vec(cp.tool_axis, Vec3::UnitZ());
}

}  // namespace
}  // namespace fettle::planning
