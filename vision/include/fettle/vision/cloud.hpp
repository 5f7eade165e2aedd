#pragma once
// Unorganized point clouds as values (no point-cloud library in this header), file I/O and
// unit checks. Coordinates are millimetres inside Fettle; `fettle locate` accepts any unit.
#include <cstddef>
#include <filesystem>
#include <vector>

#include <Eigen/Core>

#include "fettle/core/cloud.hpp"
#include "fettle/core/geometry.hpp"

namespace fettle::vision {

/// Valid (finite) points, optionally with one unit normal per point.
struct Cloud {
  std::vector<Eigen::Vector3f> points;
  std::vector<Eigen::Vector3f> normals;  ///< empty, or one per point (unit; zero = unknown)

  [[nodiscard]] std::size_t size() const { return points.size(); }
  [[nodiscard]] bool empty() const { return points.empty(); }
  [[nodiscard]] bool has_normals() const { return !normals.empty() && normals.size() == points.size(); }
};

struct Bounds {
  Eigen::Vector3f min = Eigen::Vector3f::Zero();
  Eigen::Vector3f max = Eigen::Vector3f::Zero();
  [[nodiscard]] float diagonal() const { return (max - min).norm(); }
};

/// Axis-aligned bounds of the points (zero for an empty cloud).
Bounds bounds(const Cloud& cloud);

/// Reads a PLY or PCD file and keeps its finite points (normals too if the file has them).
/// Throws UserError when the file cannot be read, is empty or has no finite point.
Cloud load_cloud(const std::filesystem::path& file);

/// Writes a binary PLY (points, and normals when present). Throws UserError on failure.
void save_ply(const std::filesystem::path& file, const Cloud& cloud);

/// The finite points of an organized cloud.
Cloud to_cloud(const OrganizedCloud& organized);

/// Applies a rigid transform to points (and rotates normals).
Cloud transformed(const Cloud& cloud, const Transform& T_target_source);

/// Throws UserError when a cloud that should be in millimetres looks like metres (its extent
/// is under 5 units) or is implausibly large; `what` names the cloud in the message.
void require_millimetres(const Cloud& cloud, const std::string& what);

}  // namespace fettle::vision
