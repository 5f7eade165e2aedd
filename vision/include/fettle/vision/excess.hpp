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
  /// The body's form deviation (+-): see config::VisionSettings::form_deviation_mm. 0 = off.
  double form_deviation_mm = 0.0;
};

/// The casting's own surface against the template in one region: offset(x, y) = at_origin_mm
/// + per_mm_x * x + per_mm_y * y (part frame, mm along the template's face normal), a robust
/// plane fitted to the offsets of the scan points on the template's upward faces that lie
/// within the form deviation of it. Smooth form deviation (sand-cast iron: wavelengths of 100
/// mm and more) is close to a plane over a region's ROI.
struct FormOffset {
  bool fitted = false;
  double at_origin_mm = 0.0, per_mm_x = 0.0, per_mm_y = 0.0;
  std::size_t points = 0;  ///< the face points the plane was fitted to (after trimming)
  double rms_mm = 0.0;     ///< their residual
  [[nodiscard]] double at(double x_mm, double y_mm) const {
    return fitted ? at_origin_mm + per_mm_x * x_mm + per_mm_y * y_mm : 0.0;
  }
};

struct ExcessMaterial {
  std::vector<Eigen::Vector3f> points;  ///< excess points, part (template) frame
  std::vector<float> heights_mm;        ///< their heights above the template surface
  double volume_mm3 = 0.0;
  double max_height_mm = 0.0;
  double footprint_mm2 = 0.0;           ///< template surface area under the excess
  FormOffset form;                      ///< the casting's own surface (settings.form_deviation_mm > 0)
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
