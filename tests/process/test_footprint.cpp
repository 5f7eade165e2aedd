// The tool's grown volume the verification's swept footprint is made of (fettle/process/footprint.hpp).
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "fettle/process/footprint.hpp"

namespace fettle::process {
namespace {

config::Tool disc() {
  config::Tool t;
  t.name = "chamfer-disc";
  t.shape = config::ToolShape::cylinder;
  t.diameter_mm = 40.0;
  t.length_mm = 6.0;
  return t;
}

Transform tip_at(const Vec3& p, const Eigen::Matrix3d& R = Eigen::Matrix3d::Identity()) {
  Transform T = Transform::Identity();
  T.linear() = R;
  T.translation() = p;
  return T;
}

// The flange's disc grinds a fin 15 mm over the plate: the plate under it was never within the
// 2 mm margin of the disc, whose grown capsule (a 22 mm half-sphere under its end face) held it.
TEST(Footprint, ADiscPassingOverAFaceDoesNotHoldIt) {
  const auto v = ToolVolume::of(disc(), tip_at(Vec3(46.0, -46.0, 50.0)), 2.0, 3);
  EXPECT_EQ(v.region, 3U);
  EXPECT_FALSE(v.contains(Vec3(55.16, -54.63, 34.99)));  // the plate 15 mm below, 12.6 mm off the axis
  EXPECT_FALSE(v.contains(Vec3(46.0, -46.0, 35.0)));     // right under the axis
  EXPECT_FALSE(v.contains(Vec3(46.0, -46.0, 47.9)));     // 2.1 mm under the end face
  EXPECT_TRUE(v.contains(Vec3(46.0, -46.0, 48.1)));      // 1.9 mm under it
  EXPECT_TRUE(v.contains(Vec3(46.0 + 19.0, -46.0, 48.5)));  // under the end face near the rim
  EXPECT_TRUE(v.contains(Vec3(46.0 + 21.9, -46.0, 53.0)));  // beside the side, within the margin
  EXPECT_FALSE(v.contains(Vec3(46.0 + 22.1, -46.0, 53.0)));
  EXPECT_TRUE(v.contains(Vec3(46.0, -46.0, 57.9)));      // above the far end, within the margin
  EXPECT_FALSE(v.contains(Vec3(46.0, -46.0, 58.1)));
  // the rim's corner is rounded by the margin: 1.5 mm out and 1.5 mm down is 2.12 mm off it
  EXPECT_FALSE(v.contains(Vec3(46.0 + 21.5, -46.0, 48.5)));
  EXPECT_TRUE(v.contains(Vec3(46.0 + 21.2, -46.0, 48.8)));
  // the box holds the grown volume
  EXPECT_LE(v.box_min().z(), 48.0);
  EXPECT_GE(v.box_max().x(), 46.0 + 22.0);
}

TEST(Footprint, ABallIsItsSphereGrownByTheMargin) {
  config::Tool ball;
  ball.shape = config::ToolShape::ball;
  ball.diameter_mm = 12.0;
  const auto v = ToolVolume::of(ball, tip_at(Vec3(0.0, 0.0, 35.0)), 2.0);
  // the centre is the radius above the tip along the tool's z
  EXPECT_TRUE(v.contains(Vec3(0.0, 0.0, 41.0 - 7.9)));
  EXPECT_FALSE(v.contains(Vec3(0.0, 0.0, 41.0 - 8.1)));
  EXPECT_TRUE(v.contains(Vec3(7.9, 0.0, 41.0)));
  EXPECT_FALSE(v.contains(Vec3(8.1, 0.0, 41.0)));
}

TEST(Footprint, ATiltedCylinderIsMeasuredAlongItsOwnAxis) {
  config::Tool burr = disc();
  burr.diameter_mm = 10.0;
  const Eigen::Matrix3d R(Eigen::AngleAxisd(0.25 * std::numbers::pi, Vec3::UnitY()));
  const auto v = ToolVolume::of(burr, tip_at(Vec3::Zero(), R), 2.0);
  const Vec3 axis = R.col(2);
  EXPECT_TRUE(v.contains(-1.9 * axis));
  EXPECT_FALSE(v.contains(-2.1 * axis));
  EXPECT_TRUE(v.contains(3.0 * axis + 6.9 * R.col(0)));
  EXPECT_FALSE(v.contains(3.0 * axis + 7.1 * R.col(0)));
}

}  // namespace
}  // namespace fettle::process
