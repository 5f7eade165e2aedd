#include <gtest/gtest.h>

#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"

namespace {
fettle::Result<int> half(int x) {
  if (x % 2 != 0) return fettle::Error{"math.odd", std::to_string(x) + " is odd"};
  return x / 2;
}
}  // namespace

TEST(Result, CarriesValueOrError) {
  const auto a = half(8);
  ASSERT_TRUE(a.ok());
  EXPECT_EQ(*a, 4);
  const auto b = half(7);
  ASSERT_FALSE(b.ok());
  EXPECT_EQ(b.error().code, "math.odd");
  EXPECT_EQ(b.error().message, "7 is odd");
}

TEST(Geometry, PoseRoundTripsThroughTransform) {
  fettle::Pose p{{10.0, -20.0, 30.0}, fettle::Quat(Eigen::AngleAxisd(0.3, fettle::Vec3(1, 2, 3).normalized()))};
  const auto q = fettle::Pose::from_transform(p.to_transform());
  EXPECT_TRUE(q.position_mm.isApprox(p.position_mm));
  EXPECT_NEAR(q.orientation.angularDistance(p.orientation), 0.0, 1e-12);
  EXPECT_NEAR(fettle::rotation_angle_rad(p.to_transform()), 0.3, 1e-12);
  EXPECT_NEAR(fettle::rad_to_deg(fettle::deg_to_rad(37.0)), 37.0, 1e-12);
}
