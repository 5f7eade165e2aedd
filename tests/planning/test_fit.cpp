// Plane, line and ellipse fits on exact synthetic data and with noise and outliers.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>
#include <random>

#include "fettle/planning/fit.hpp"
#include "../support/draws.hpp"

namespace fettle::planning {
namespace {

constexpr double kPi = std::numbers::pi;

std::vector<Vec3> plane_points(const Vec3& normal, double d, int n, double noise, double outlier_fraction,
                               std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-50.0, 50.0);
  std::normal_distribution<double> g(0.0, noise > 0 ? noise : 1.0);
  const Vec3 nrm = normal.normalized();
  const Vec3 e1 = nrm.unitOrthogonal(), e2 = nrm.cross(e1);
  std::vector<Vec3> pts;
  for (int i = 0; i < n; ++i) {
    // The draws are sequenced (C++ leaves the order of arguments and operands unspecified: gcc
    // draws them right to left, clang left to right, and the two would see different data); the
    // order is gcc's, the one the expectations below are measured with.
    if (i < static_cast<int>(outlier_fraction * n)) {
      const double z = u(rng), y = u(rng), x = u(rng);
      pts.emplace_back(x, y, z);
      continue;
    }
    const double b = u(rng), a = u(rng);
    Vec3 p = -d / normal.norm() * nrm + a * e1 + b * e2;
    if (noise > 0) p += g(rng) * nrm;
    pts.push_back(p);
  }
  return pts;
}

TEST(PlaneFit, RecoversAnExactPlane) {
  const Vec3 normal(0.2, -0.1, 1.0);
  const double d = -50.0;  // 0.2x - 0.1y + z - 50 = 0 (before normalisation)
  const auto pts = plane_points(normal, d, 200, 0.0, 0.0, 1);
  const auto plane = fit_plane_ransac(pts);
  ASSERT_TRUE(plane);
  const Vec3 expected = normal.normalized();
  EXPECT_NEAR(std::abs(plane->normal.dot(expected)), 1.0, 1e-12);
  const double sign = plane->normal.dot(expected) > 0 ? 1.0 : -1.0;
  EXPECT_NEAR(sign * plane->d, d / normal.norm(), 1e-9);
  EXPECT_EQ(plane->inliers, 200U);
}

TEST(PlaneFit, IgnoresOutliersAndAveragesNoise) {
  const Vec3 normal(0.0, 0.3, 1.0);
  const auto pts = plane_points(normal, -20.0, 2000, 0.05, 0.3, 2);
  const auto plane = fit_plane_ransac(pts, {0.3, 200, 7});
  ASSERT_TRUE(plane);
  const double angle = std::acos(std::min(1.0, std::abs(plane->normal.dot(normal.normalized()))));
  EXPECT_LT(angle, 0.2 * kPi / 180.0);
  EXPECT_NEAR(std::abs(plane->d), 20.0 / normal.norm(), 0.05);
  EXPECT_NEAR(static_cast<double>(plane->inliers), 1400.0, 60.0);  // the 70 % on the plane
  // without RANSAC the outliers drag the plane away
  const auto lsq = fit_plane_lsq(pts);
  ASSERT_TRUE(lsq);
  EXPECT_GT(std::acos(std::min(1.0, std::abs(lsq->normal.dot(normal.normalized())))), 1.0 * kPi / 180.0);
}

// Two planes, the larger one's points not admitted: the fit finds the smaller, admitted one, and
// counts only admitted inliers.
TEST(PlaneFit, OnlyAdmittedPointsMakeThePlane) {
  auto pts = plane_points(Vec3(0, 0, 1), -35.0, 3000, 0.0, 0.0, 3);  // the larger: z = 35
  const std::size_t below = pts.size();
  const auto fin = plane_points(Vec3(0, 0, 1), -50.0, 600, 0.0, 0.0, 4);  // the smaller: z = 50
  pts.insert(pts.end(), fin.begin(), fin.end());
  const auto plain = fit_plane_ransac(pts, {0.5, 200, 1});
  ASSERT_TRUE(plain);
  EXPECT_NEAR(std::abs(plain->d), 35.0, 0.01) << "without admission the larger plane wins";
  const auto admitted = fit_plane_ransac(pts, {0.5, 200, 1}, [&](std::size_t i, const Vec3&) { return i >= below; });
  ASSERT_TRUE(admitted);
  EXPECT_NEAR(std::abs(admitted->d), 50.0, 0.01);
  EXPECT_EQ(admitted->inliers, 600U);
  EXPECT_FALSE(fit_plane_ransac(pts, {0.5, 50, 1}, [](std::size_t, const Vec3&) { return false; }))
      << "nothing admitted: no plane, never a least-squares guess through everything";
}

// The admitted points one in ten: a plain RANSAC of 200 samples draws three of them in about
// one run in five; hypotheses from samples the plane would not admit are not counted, so every
// run finds the plane.
TEST(PlaneFit, AFewAdmittedPointsAmongManyAreFoundInEveryRun) {
  auto pts = plane_points(Vec3(0.1, 0, 1), -35.0, 5400, 0.0, 0.0, 5);
  const std::size_t below = pts.size();
  const auto fin = plane_points(Vec3(0, 0, 1), -50.0, 600, 0.0, 0.0, 6);
  pts.insert(pts.end(), fin.begin(), fin.end());
  const auto admit = [&](std::size_t i, const Vec3& n) { return i >= below && std::abs(n.z()) > 0.99; };
  for (std::uint64_t seed = 1; seed <= 10; ++seed) {
    const auto plane = fit_plane_ransac(pts, {0.5, 200, seed}, admit);
    ASSERT_TRUE(plane) << "seed " << seed;
    EXPECT_NEAR(std::abs(plane->d), 50.0, 0.01) << "seed " << seed;
    EXPECT_EQ(plane->inliers, 600U) << "seed " << seed;
  }
}

TEST(LineFit, RecoversAnExactLineAndRobustlyANoisyOne) {
  const Vec3 p0(-95, -70, 36), dir = Vec3(1, 0.05, 0.01).normalized();
  std::vector<Vec3> exact;
  for (int i = 0; i < 100; ++i) exact.push_back(p0 + i * 0.9 * dir);
  const auto line = fit_line_ransac(exact);
  ASSERT_TRUE(line);
  EXPECT_NEAR(std::abs(line->direction.dot(dir)), 1.0, 1e-12);
  EXPECT_LT(line->distance(p0), 1e-9);

  std::mt19937_64 rng(3);
  std::normal_distribution<double> g(0.0, 0.2);
  std::uniform_real_distribution<double> u(-100.0, 100.0);
  std::vector<Vec3> noisy;
  for (int i = 0; i < 1000; ++i) noisy.push_back(p0 + i * 0.09 * dir + fettle::test::draw3<Vec3>(g, rng));
  for (int i = 0; i < 300; ++i) noisy.push_back(fettle::test::draw3<Vec3>(u, rng));
  const auto robust = fit_line_ransac(noisy, {1.0, 300, 5});
  ASSERT_TRUE(robust);
  EXPECT_GT(std::abs(robust->direction.dot(dir)), std::cos(0.5 * kPi / 180.0));
  EXPECT_LT(robust->distance(p0 + 50 * dir), 0.1);
}

std::vector<Eigen::Vector2d> ellipse_points(const EllipseGeometry& e, int n, double noise, int outliers,
                                            std::uint64_t seed, double arc = 2 * kPi) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0.0, noise > 0 ? noise : 1.0);
  std::uniform_real_distribution<double> u(-80.0, 80.0);
  std::vector<Eigen::Vector2d> pts;
  for (int i = 0; i < n; ++i) {
    Eigen::Vector2d p = e.point(arc * i / n);
    if (noise > 0) p += fettle::test::draw2<Eigen::Vector2d>(g, rng);
    pts.push_back(p);
  }
  for (int i = 0; i < outliers; ++i) pts.push_back(fettle::test::draw2<Eigen::Vector2d>(u, rng));
  return pts;
}

void expect_same_ellipse(const Conic& c, const EllipseGeometry& truth, double tol_mm, double tol_rad) {
  ASSERT_TRUE(c.is_ellipse());
  const auto e = ellipse_geometry(c);
  ASSERT_TRUE(e);
  EXPECT_NEAR(e->center.x(), truth.center.x(), tol_mm);
  EXPECT_NEAR(e->center.y(), truth.center.y(), tol_mm);
  EXPECT_NEAR(e->semi_major, truth.semi_major, tol_mm);
  EXPECT_NEAR(e->semi_minor, truth.semi_minor, tol_mm);
  const double da = std::remainder(e->angle_rad - truth.angle_rad, kPi);  // axis direction is mod π
  EXPECT_NEAR(da, 0.0, tol_rad);
}

TEST(EllipseFit, DirectFitRecoversAnExactEllipse) {
  EllipseGeometry truth;
  truth.center = {3.0, -2.0};
  truth.semi_major = 40.0;
  truth.semi_minor = 25.0;
  truth.angle_rad = 0.3;
  const auto pts = ellipse_points(truth, 60, 0.0, 0, 1);
  const auto c = fit_ellipse_direct(pts);
  ASSERT_TRUE(c);
  expect_same_ellipse(*c, truth, 1e-6, 1e-8);
  for (const auto& p : pts) EXPECT_LT(c->sampson_distance(p), 1e-6);
}

TEST(EllipseFit, DirectFitOnAnArcOnlyIsStillAnEllipse) {
  EllipseGeometry truth;
  truth.center = {0.0, 0.0};
  truth.semi_major = 46.0;
  truth.semi_minor = 45.0;
  truth.angle_rad = 0.0;
  const auto c = fit_ellipse_direct(ellipse_points(truth, 100, 0.0, 0, 1, 0.9 * 2 * kPi));  // a 10 % gap
  ASSERT_TRUE(c);
  expect_same_ellipse(*c, truth, 1e-6, 1e-6);
}

TEST(EllipseFit, RansacIgnoresOutliersAndAveragesNoise) {
  EllipseGeometry truth;
  truth.center = {-5.0, 10.0};
  truth.semi_major = 47.0;
  truth.semi_minor = 44.0;
  truth.angle_rad = -0.7;
  const auto pts = ellipse_points(truth, 1500, 0.1, 500, 9);
  const auto c = fit_ellipse_ransac(pts, {0.4, 300, 3});
  ASSERT_TRUE(c);
  expect_same_ellipse(*c, truth, 0.1, 0.05);
  EXPECT_GT(c->inliers, 1400U);
  // the plain direct fit is ruined by the same outliers
  const auto direct = fit_ellipse_direct(pts);
  ASSERT_TRUE(direct);
  const auto e = ellipse_geometry(*direct);
  EXPECT_TRUE(!e || std::abs(e->semi_major - truth.semi_major) > 1.0 || (e->center - truth.center).norm() > 1.0);
}

TEST(EllipseFit, GradientGivesTheOutwardNormalOfACircle) {
  EllipseGeometry circle;
  circle.center = {10.0, 20.0};
  circle.semi_major = circle.semi_minor = 30.0;
  const auto c = fit_ellipse_direct(ellipse_points(circle, 40, 0.0, 0, 1));
  ASSERT_TRUE(c);
  for (double t : {0.0, 1.0, 2.5, 4.0}) {
    const Eigen::Vector2d p = circle.point(t);
    Eigen::Vector2d g = c->gradient(p).normalized();
    const Eigen::Vector2d radial = (p - circle.center).normalized();
    EXPECT_NEAR(g.dot(radial), 1.0, 1e-9);  // A > 0: the gradient points outward
  }
}

TEST(EllipseFit, RefusesDegenerateInput) {
  EXPECT_FALSE(fit_ellipse_direct({{0, 0}, {1, 1}, {2, 2}}));
  std::vector<Eigen::Vector2d> line;
  for (int i = 0; i < 20; ++i) line.emplace_back(i, 2.0 * i);
  const auto c = fit_ellipse_direct(line);
  EXPECT_TRUE(!c || !c->is_ellipse());
}

}  // namespace
}  // namespace fettle::planning
