#pragma once
// A point cloud as devices deliver it, independent of any point-cloud library.
#include <cstdint>
#include <limits>
#include <vector>

#include <Eigen/Core>

namespace fettle {

/// An organized cloud (one point per camera pixel), millimetres, camera frame.
/// Invalid pixels hold NaN in all three coordinates. Row-major: index = v * width + u.
struct OrganizedCloud {
  std::uint32_t width = 0;
  std::uint32_t height = 0;
  std::vector<Eigen::Vector3f> points;

  [[nodiscard]] std::size_t size() const { return points.size(); }
  [[nodiscard]] bool is_valid(std::size_t i) const { return points[i].allFinite(); }
  [[nodiscard]] std::size_t count_valid() const {
    std::size_t n = 0;
    for (const auto& p : points) n += p.allFinite() ? 1 : 0;
    return n;
  }
  static Eigen::Vector3f invalid() {
    const float nan = std::numeric_limits<float>::quiet_NaN();
    return {nan, nan, nan};
  }
};

}  // namespace fettle
