#pragma once
// Excess material: scene points standing out of the template surface, per region.
#include <vector>

#include <Eigen/Core>

#include "fettle/vision/cloud.hpp"
#include "fettle/vision/registration.hpp"

namespace fettle::vision {

struct ExcessSettings {
  double threshold_mm = 0.2;        ///< signed distance along the template normal above which a point is excess
  double max_height_mm = 80.0;      ///< farther points are not material of this region (clutter, other parts)
  int min_cluster_points = 10;      ///< smaller clusters are noise
  double cluster_tolerance_mm = 0.0;  ///< 0 = 3 * scene spacing
};

struct ExcessMaterial {
  std::vector<Eigen::Vector3f> points;  ///< excess points, part (template) frame
  std::vector<float> heights_mm;        ///< their heights above the template surface
  double volume_mm3 = 0.0;
  double max_height_mm = 0.0;
  double footprint_mm2 = 0.0;           ///< template surface area under the excess
};

/// Scene points already in the template frame against a prepared template (fine points,
/// outward normals). Volume integrates, over the template's surface elements, the height of
/// the scene point nearest to each element (dropped along the normal onto the template) where
/// that point is excess: the scan resampled onto the template, no holes between two grids.
ExcessMaterial measure_excess(const PreparedCloud& templ, const Cloud& scene_in_template, const ExcessSettings& settings);

/// Signed distance of each point to the template surface along the template normal of its
/// nearest template point (positive = outside, i.e. material above the surface).
std::vector<float> signed_distances(const PreparedCloud& templ, const std::vector<Eigen::Vector3f>& points);

}  // namespace fettle::vision
