// RANSAC plane with the adaptive iteration count of Eq. 10.
#include "fettle/vision/plane.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <string>

#include <Eigen/Eigenvalues>

#include "detail.hpp"

namespace fettle::vision {

std::int64_t ransac_iterations(double p, double inlier_ratio, int sample_size, std::int64_t max_iterations) {
  max_iterations = std::max<std::int64_t>(1, max_iterations);
  if (!(inlier_ratio > 0.0)) return max_iterations;
  if (inlier_ratio >= 1.0 || !(p > 0.0)) return 1;
  p = std::min(p, 1.0 - 1e-12);
  const double all_inliers = std::pow(inlier_ratio, sample_size);  // w^n
  const double denom = std::log1p(-all_inliers);                   // log(1 - w^n)
  if (!(denom < 0.0)) return max_iterations;
  const double k = std::ceil(std::log1p(-p) / denom);
  if (!(k < static_cast<double>(max_iterations))) return max_iterations;
  return std::max<std::int64_t>(1, static_cast<std::int64_t>(k));
}

namespace {

std::size_t count_inliers(const std::vector<Eigen::Vector3f>& pts, const Eigen::Vector4f& plane, float dist, int threads) {
  std::vector<std::size_t> counts(static_cast<std::size_t>(threads), 0);
  detail::parallel_for(pts.size(), threads, [&](std::size_t t, std::size_t b, std::size_t e) {
    std::size_t c = 0;
    for (std::size_t i = b; i < e; ++i) c += std::abs(plane.head<3>().dot(pts[i]) + plane[3]) <= dist ? 1 : 0;
    counts[t] = c;
  });
  std::size_t n = 0;
  for (auto c : counts) n += c;
  return n;
}

}  // namespace

Result<PlaneFit> fit_plane(const Cloud& cloud, const PlaneSettings& settings) {
  const std::size_t n = cloud.size();
  if (n < 3)
    return Error{"vision.no_plane", "plane fit needs at least 3 points, the cloud has " + std::to_string(n)};
  const int threads = detail::thread_count(0);
  std::mt19937_64 rng(settings.seed);
  std::uniform_int_distribution<std::size_t> pick(0, n - 1);
  const auto dist = static_cast<float>(settings.distance);

  Eigen::Vector4f best = Eigen::Vector4f::Zero();
  std::size_t best_count = 0;
  std::int64_t k = settings.max_iterations;
  std::int64_t it = 0;
  for (; it < k; ++it) {
    const auto& a = cloud.points[pick(rng)];
    const auto& b = cloud.points[pick(rng)];
    const auto& c = cloud.points[pick(rng)];
    const Eigen::Vector3f nrm = (b - a).cross(c - a);
    const float len = nrm.norm();
    if (len < 1e-12f) continue;  // degenerate sample (collinear or repeated points)
    Eigen::Vector4f plane;
    plane.head<3>() = nrm / len;
    plane[3] = -plane.head<3>().dot(a);
    const std::size_t count = count_inliers(cloud.points, plane, dist, threads);
    if (count > best_count) {
      best_count = count;
      best = plane;
      // Eq. 10 with the best inlier ratio seen so far.
      k = std::min(k, ransac_iterations(settings.probability, static_cast<double>(count) / static_cast<double>(n), 3,
                                        settings.max_iterations));
    }
  }
  if (best_count < 3) return Error{"vision.no_plane", "no plane with at least 3 inliers found"};

  // Least-squares refit on the inliers, then the final inlier set.
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  std::vector<std::size_t> inl;
  for (std::size_t i = 0; i < n; ++i)
    if (std::abs(best.head<3>().dot(cloud.points[i]) + best[3]) <= dist) inl.push_back(i);
  for (auto i : inl) mean += cloud.points[i].cast<double>();
  mean /= static_cast<double>(inl.size());
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (auto i : inl) {
    const Eigen::Vector3d d = cloud.points[i].cast<double>() - mean;
    cov += d * d.transpose();
  }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
  es.computeDirect(cov);
  Eigen::Vector3d normal = es.eigenvectors().col(0).normalized();
  if (normal.dot(best.head<3>().cast<double>()) < 0) normal = -normal;
  PlaneFit fit;
  fit.coefficients.head<3>() = normal;
  fit.coefficients[3] = -normal.dot(mean);
  fit.iterations = it;
  const Eigen::Vector4f refined = fit.coefficients.cast<float>();
  for (std::size_t i = 0; i < n; ++i)
    if (std::abs(refined.head<3>().dot(cloud.points[i]) + refined[3]) <= dist) fit.inliers.push_back(i);
  if (fit.inliers.size() < best_count / 2) {  // the refit drifted (should not happen): keep the sample
    fit.coefficients = best.cast<double>();
    fit.inliers = std::move(inl);
  }
  return fit;
}

Cloud remove_indices(const Cloud& cloud, const std::vector<std::size_t>& indices) {
  std::vector<char> drop(cloud.size(), 0);
  for (auto i : indices)
    if (i < drop.size()) drop[i] = 1;
  Cloud out;
  const bool normals = cloud.has_normals();
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    if (drop[i]) continue;
    out.points.push_back(cloud.points[i]);
    if (normals) out.normals.push_back(cloud.normals[i]);
  }
  return out;
}

}  // namespace fettle::vision
