// RANSAC plane (environment removal) and the adaptive iteration count of Eq. 10.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "fettle/vision/plane.hpp"
#include "test_support.hpp"
#include "../support/draws.hpp"

using namespace fettle::vision;

TEST(RansacIterations, FollowsEquation10) {
  // k = log(1 - p) / log(1 - w^n), rounded up.
  EXPECT_EQ(ransac_iterations(0.99, 0.5, 3, 1000000), static_cast<std::int64_t>(std::ceil(std::log(0.01) / std::log(0.875))));
  EXPECT_EQ(ransac_iterations(0.99, 0.5, 3, 1000000), 35);
  EXPECT_EQ(ransac_iterations(0.999, 0.3, 3, 1000000), 253);  // log(0.001)/log(1-0.027) = 252.4
  EXPECT_EQ(ransac_iterations(0.99, 0.9, 3, 1000000), 4);     // log(0.01)/log(0.271) = 3.53
}

TEST(RansacIterations, GrowsWithSampleSizeAndShrinksWithInlierRatio) {
  EXPECT_GT(ransac_iterations(0.99, 0.5, 4, 1000000), ransac_iterations(0.99, 0.5, 3, 1000000));
  EXPECT_LT(ransac_iterations(0.99, 0.8, 3, 1000000), ransac_iterations(0.99, 0.4, 3, 1000000));
}

TEST(RansacIterations, EdgeCasesAreClamped) {
  EXPECT_EQ(ransac_iterations(0.99, 0.0, 3, 5000), 5000);   // no inliers: the cap
  EXPECT_EQ(ransac_iterations(0.99, 1.0, 3, 5000), 1);      // all inliers: one sample is enough
  EXPECT_EQ(ransac_iterations(0.99, 0.01, 3, 5000), 5000);  // would need 4.6 million: capped
}

TEST(FitPlane, FindsTheDominantPlaneOfSacPlaneTest) {
  const Cloud cloud = load_cloud(test::data("sac_plane_test.pcd"));
  ASSERT_EQ(cloud.size(), 3283U);
  ASSERT_TRUE(cloud.has_normals());
  PlaneSettings s;
  s.distance = 0.03;  // the scene is in metres, as in PCL's own RANSAC tests
  s.probability = 0.99;
  const auto fit = fit_plane(cloud, s);
  ASSERT_TRUE(fit.ok()) << fit.error().message;
  EXPECT_GT(fit->inliers.size(), 2000U);
  // Eq. 10 stopped the search long before the cap.
  EXPECT_LT(fit->iterations, 200);
  // The file's own normals of the inliers agree with the fitted plane's normal.
  const Eigen::Vector3f n = fit->coefficients.head<3>().cast<float>();
  double agree = 0.0;
  std::size_t with_normal = 0;
  for (auto i : fit->inliers) {
    if (cloud.normals[i].isZero()) continue;  // the file has a few NaN normals
    agree += std::abs(n.dot(cloud.normals[i]));
    ++with_normal;
  }
  ASSERT_GT(with_normal, 1900U);
  EXPECT_GT(agree / static_cast<double>(with_normal), 0.9);
  // Every inlier is within the band.
  for (auto i : fit->inliers) EXPECT_LE(std::abs(n.dot(cloud.points[i]) + static_cast<float>(fit->coefficients[3])), 0.0301f);
}

TEST(FitPlane, RecoversASyntheticPlaneAmongClutter) {
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<float> u(-100.0f, 100.0f);
  std::normal_distribution<float> noise(0.0f, 0.05f);
  Cloud c;
  const Eigen::Vector3f n = Eigen::Vector3f(0.1f, -0.2f, 1.0f).normalized();
  const float d = -12.0f;
  for (int i = 0; i < 3000; ++i) {  // plane points
    const auto xy = fettle::test::draws<2>(u, rng);
    Eigen::Vector3f p(xy[0], xy[1], 0.0f);
    p.z() = (-d - n.x() * p.x() - n.y() * p.y()) / n.z() + noise(rng);
    c.points.push_back(p);
  }
  for (int i = 0; i < 2000; ++i) {  // clutter
    const auto a = fettle::test::draws<3>(u, rng);
    c.points.emplace_back(a[0], a[1], a[2] + 60.0f);
  }
  PlaneSettings s;
  s.distance = 0.3;
  const auto fit = fit_plane(c, s);
  ASSERT_TRUE(fit.ok());
  Eigen::Vector3d got = fit->coefficients.head<3>();
  double off = fit->coefficients[3];
  if (got.dot(n.cast<double>()) < 0) {
    got = -got;
    off = -off;
  }
  EXPECT_NEAR(got.dot(n.cast<double>()), 1.0, 1e-4);
  EXPECT_NEAR(off, d, 0.05);
  EXPECT_GE(fit->inliers.size(), 2990U);
  EXPECT_LE(fit->inliers.size(), 3100U);
  const Cloud rest = remove_indices(c, fit->inliers);
  EXPECT_EQ(rest.size(), c.size() - fit->inliers.size());
}

TEST(FitPlane, TooFewPointsIsAnError) {
  Cloud c;
  c.points = {Eigen::Vector3f::Zero(), Eigen::Vector3f::UnitX()};
  const auto fit = fit_plane(c, {});
  ASSERT_FALSE(fit.ok());
  EXPECT_EQ(fit.error().code, "vision.no_plane");
}
