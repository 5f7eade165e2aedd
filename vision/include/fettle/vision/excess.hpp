#pragma once
// Excess material: scene points standing out of the template surface, per region.
#include <limits>
#include <optional>
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
  /// Material lies within this box (template frame; default: everywhere). The scene points
  /// around it still give the casting's face (FormOffset), so the face is known where a tool
  /// reaches beyond the region's ROI (a ball's edge at a pass's end).
  Eigen::Vector3f material_min_mm = Eigen::Vector3f::Constant(-std::numeric_limits<float>::infinity());
  Eigen::Vector3f material_max_mm = Eigen::Vector3f::Constant(std::numeric_limits<float>::infinity());
  /// The casting's face to measure the material from instead of fitting one to this scene
  /// (with form_deviation_mm > 0). A re-grind measures from the cycle's first scan: on a ground
  /// casting, the stub a pass left within the form deviation fits as the face.
  const struct FormOffset* face = nullptr;
};

/// The casting's own surface against the template in one region (part frame, mm along the
/// template's face normal), from the scan points on the template's upward faces:
/// - the plane at_origin_mm + per_mm_x x + per_mm_y y, a robust fit to the offsets within twice
///   the form deviation of the template: it carries the tilt a best fit to a deformed body takes;
/// - where the scan saw the face, the local offset: at nodes `local_pitch_mm` apart, a plane
///   through the offsets within `kLocalRadiusMm` (x-y) that lie within twice the form deviation
///   of the plane above, trimmed hard on its upper side (what stands on a face, a fin's root or a
///   riser's foot, is above it) and loosely below; without the samples within `kFootMm` of
///   what stands out of the face (refitted while that shows more), so a riser whose tilted top
///   meets the face on a ramp of material lower than the form deviation does not lift it;
/// - under a riser (nodes with no samples or samples on one side only): a quadratic through the
///   faces around it where they surround it, else harmonic from the nodes around;
/// - beyond the nodes by more than `kLocalRadiusMm` (off the region), the plane.
/// One plane does not follow sand-cast iron's form along a 140 mm flash; the local face does
/// (test Excess.TheLocalFaceFollowsAFormThePlaneCannot). Twice the form deviation: a face within
/// it of the nominal stands up to twice off a plane through it, and in the part's located frame
/// the registration's tilt and lift add to it (test
/// Excess.AFaceFartherFromTheRegionsPlaneThanTheFormDeviationIsStillFollowed).
struct FormOffset {
  /// Sand-cast form has wavelengths of 90 mm and more (the simulator's 90-200 mm): over 10 mm a
  /// plane follows it within 0.03 mm, and a fin's or a riser's foot is a minority of the points.
  static constexpr double kLocalRadiusMm = 10.0;
  /// The foot of material on a face (a fillet, mixed pixels and interreflection in the
  /// concave corner, the roughness of a riser's stub) is neither face nor clearly material:
  /// the face samples this close (x-y) to material are left out.
  static constexpr double kFootMm = 3.0;
  bool fitted = false;
  double at_origin_mm = 0.0, per_mm_x = 0.0, per_mm_y = 0.0;
  std::size_t points = 0;  ///< the face points the plane was fitted to (after trimming)
  double rms_mm = 0.0;     ///< their residual
  double local_x0 = 0.0, local_y0 = 0.0, local_pitch_mm = 4.0;  ///< node (i, j) at (x0 + i p, y0 + j p)
  int local_nx = 0, local_ny = 0;
  std::vector<float> local;  ///< per node (row-major in y), NaN where the face was not seen
  [[nodiscard]] double plane_at(double x_mm, double y_mm) const {
    return fitted ? at_origin_mm + per_mm_x * x_mm + per_mm_y * y_mm : 0.0;
  }
  /// The local offset where the scan saw the face: bilinear between the nodes around (x, y)
  /// that hold one; within `kLocalRadiusMm` beyond the nodes, the nearest edge's; else none.
  [[nodiscard]] std::optional<double> local_at(double x_mm, double y_mm) const;
  /// Whether (x, y) lies over the nodes (the faces the local fit saw, not the kLocalRadiusMm
  /// beyond them that local_at() still answers for).
  [[nodiscard]] bool over_nodes(double x_mm, double y_mm) const {
    return x_mm >= local_x0 && y_mm >= local_y0 && x_mm <= local_x0 + (local_nx - 1) * local_pitch_mm &&
           y_mm <= local_y0 + (local_ny - 1) * local_pitch_mm;
  }
  /// local_at(), else the plane.
  [[nodiscard]] double at(double x_mm, double y_mm) const {
    if (!fitted) return 0.0;
    const auto local_offset = local_at(x_mm, y_mm);
    return local_offset ? *local_offset : plane_at(x_mm, y_mm);
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
