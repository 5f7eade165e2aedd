// RANSAC sphere fit (the sphere method of hand-eye calibration finds its centre in each scan).
#include <algorithm>
#include <cmath>
#include <optional>
#include <random>
#include <string>

#include <Eigen/Dense>

#include "fettle/vision/calibration/hand_eye.hpp"

namespace fettle::vision::calibration {

namespace {

struct Sphere {
  Vec3 c;
  double r;
};

/// Algebraic fit x^2+y^2+z^2 + D x + E y + F z + G = 0 through 4 or more points.
std::optional<Sphere> algebraic(const std::vector<Vec3>& pts, const std::vector<std::size_t>& idx) {
  Eigen::MatrixXd A(static_cast<Eigen::Index>(idx.size()), 4);
  Eigen::VectorXd b(static_cast<Eigen::Index>(idx.size()));
  for (std::size_t k = 0; k < idx.size(); ++k) {
    const Vec3& p = pts[idx[k]];
    A.row(static_cast<Eigen::Index>(k)) << p.x(), p.y(), p.z(), 1.0;
    b(static_cast<Eigen::Index>(k)) = -p.squaredNorm();
  }
  Eigen::ColPivHouseholderQR<Eigen::MatrixXd> qr(A);
  if (qr.rank() < 4) return std::nullopt;
  const Eigen::Vector4d s = qr.solve(b);
  const Vec3 c = -0.5 * s.head<3>();
  const double r2 = c.squaredNorm() - s(3);
  if (!(r2 > 0.0) || !std::isfinite(r2)) return std::nullopt;
  return Sphere{c, std::sqrt(r2)};
}

/// Geometric least squares sum (|p - c| - r)^2 by Gauss-Newton; r fixed when known.
Sphere refine(const std::vector<Vec3>& pts, const std::vector<std::size_t>& idx, Sphere s, bool fix_radius) {
  for (int iter = 0; iter < 20; ++iter) {
    Eigen::Matrix4d H = Eigen::Matrix4d::Zero();
    Eigen::Vector4d g = Eigen::Vector4d::Zero();
    for (const std::size_t i : idx) {
      const Vec3 d = pts[i] - s.c;
      const double n = d.norm();
      if (n < 1e-9) continue;
      const double res = n - s.r;
      Eigen::Vector4d J;
      J << -d / n, -1.0;
      if (fix_radius) J(3) = 0.0;
      H += J * J.transpose();
      g += J * res;
    }
    if (fix_radius) H(3, 3) = 1.0;
    const Eigen::Vector4d step = -H.ldlt().solve(g);
    s.c += step.head<3>();
    if (!fix_radius) s.r += step(3);
    if (step.norm() < 1e-9) break;
  }
  return s;
}

}  // namespace

Result<SphereFit> fit_sphere(const std::vector<Vec3>& pts, const SphereFitOptions& o) {
  if (pts.size() < std::max<std::size_t>(o.min_inliers, 4))
    return Error{"calibration.no_sphere", "the scan has " + std::to_string(pts.size()) +
                                              " valid points, too few to find a sphere (need " +
                                              std::to_string(std::max<std::size_t>(o.min_inliers, 4)) +
                                              "); check that the sphere is in the camera's view and lit"};
  const bool known = o.radius_mm > 0.0;
  std::mt19937_64 rng(o.seed);
  std::uniform_int_distribution<std::size_t> pick(0, pts.size() - 1);
  std::size_t best_count = 0;
  Sphere best{Vec3::Zero(), 0.0};
  std::vector<std::size_t> sample(4);
  for (int it = 0; it < o.iterations; ++it) {
    for (auto& s : sample) s = pick(rng);
    auto cand = algebraic(pts, sample);
    if (!cand) continue;
    if (known && std::abs(cand->r - o.radius_mm) > o.radius_tolerance_mm) continue;
    if (known) cand->r = o.radius_mm;
    std::size_t count = 0;
    for (const auto& p : pts) count += std::abs((p - cand->c).norm() - cand->r) <= o.inlier_mm ? 1 : 0;
    if (count > best_count) {
      best_count = count;
      best = *cand;
    }
  }
  if (best_count < o.min_inliers)
    return Error{"calibration.no_sphere",
                 "no sphere" + (known ? " of radius " + std::to_string(o.radius_mm) + " mm" : std::string()) +
                     " found in the scan (best candidate had " + std::to_string(best_count) + " points within " +
                     std::to_string(o.inlier_mm) + " mm, need " + std::to_string(o.min_inliers) +
                     "); check the sphere radius and that the sphere is in view"};
  // Refine on the inliers, then once more with the refined inlier set.
  SphereFit fit;
  for (int pass = 0; pass < 2; ++pass) {
    std::vector<std::size_t> inl;
    for (std::size_t i = 0; i < pts.size(); ++i)
      if (std::abs((pts[i] - best.c).norm() - best.r) <= o.inlier_mm) inl.push_back(i);
    best = refine(pts, inl, best, known);
    double ss = 0.0;
    for (const std::size_t i : inl) ss += std::pow((pts[i] - best.c).norm() - best.r, 2);
    fit.inliers = inl.size();
    fit.rms_mm = inl.empty() ? 0.0 : std::sqrt(ss / static_cast<double>(inl.size()));
  }
  fit.center_mm = best.c;
  fit.radius_mm = best.r;
  return fit;
}

Result<SphereFit> fit_sphere(const OrganizedCloud& cloud, const SphereFitOptions& o) {
  std::vector<Vec3> pts;
  pts.reserve(cloud.size());
  for (const auto& p : cloud.points)
    if (p.allFinite()) pts.push_back(p.cast<double>());
  return fit_sphere(pts, o);
}

}  // namespace fettle::vision::calibration
