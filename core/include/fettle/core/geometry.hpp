#pragma once
// Geometry conventions used everywhere in Fettle:
//  - lengths in millimetres, angles in radians inside the code (degrees only at the edges);
//  - a transform is named after its frames: T_target_source maps points given in
//    `source` into `target` (p_target = T_target_source * p_source), e.g. T_base_camera.
#include <Eigen/Geometry>
#include <numbers>

namespace fettle {

using Transform = Eigen::Isometry3d;
using Vec3 = Eigen::Vector3d;
using Quat = Eigen::Quaterniond;

inline constexpr double deg_to_rad(double deg) { return deg * std::numbers::pi / 180.0; }
inline constexpr double rad_to_deg(double rad) { return rad * 180.0 / std::numbers::pi; }

/// A 6-DoF pose: position in mm and a unit quaternion.
struct Pose {
  Vec3 position_mm = Vec3::Zero();
  Quat orientation = Quat::Identity();

  [[nodiscard]] Transform to_transform() const {
    Transform T = Transform::Identity();
    T.linear() = orientation.normalized().toRotationMatrix();
    T.translation() = position_mm;
    return T;
  }
  static Pose from_transform(const Transform& T) {
    return Pose{T.translation(), Quat(T.rotation()).normalized()};
  }
};

/// Rotation angle of a transform (radians), e.g. for pose-error metrics.
inline double rotation_angle_rad(const Transform& T) {
  return Eigen::AngleAxisd(T.rotation()).angle();
}

}  // namespace fettle
