#pragma once
// Environment removal: RANSAC plane with the adaptive iteration count of Zhu et al. (Eq. 10).
#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "fettle/core/result.hpp"
#include "fettle/vision/cloud.hpp"

namespace fettle::vision {

/// Eq. 10: k = log(1 - p) / log(1 - w^n), rounded up: the number of random samples of n
/// points needed to draw at least one all-inlier sample with probability p when a
/// fraction w of the points are inliers. Clamped to [1, max_iterations].
std::int64_t ransac_iterations(double p, double inlier_ratio, int sample_size, std::int64_t max_iterations);

struct PlaneSettings {
  double distance = 0.5;       ///< inlier band (cloud unit)
  double probability = 0.999;  ///< p of Eq. 10
  std::int64_t max_iterations = 10000;
  std::uint64_t seed = 1;
};

struct PlaneFit {
  Eigen::Vector4d coefficients = Eigen::Vector4d::Zero();  ///< n.x + d = 0 with |n| = 1
  std::vector<std::size_t> inliers;
  std::int64_t iterations = 0;  ///< samples drawn (adapted by Eq. 10)
};

/// The dominant plane. Fails (vision.no_plane) for fewer than 3 points or no plane found.
Result<PlaneFit> fit_plane(const Cloud& cloud, const PlaneSettings& settings);

/// The cloud without the given indices.
Cloud remove_indices(const Cloud& cloud, const std::vector<std::size_t>& indices);

}  // namespace fettle::vision
