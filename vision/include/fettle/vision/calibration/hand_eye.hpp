#pragma once
// Eye-to-hand calibration: a fixed camera, the calibration object on the robot flange.
//
// Board method (paper Eqs. 7-8): for every robot pose i,
//   T_base_flange[i] * T_flange_board = T_base_camera * T_camera_board[i]      (A_i X = Y B_i)
// solved linearly (Kronecker/vec form for the rotations, then least squares for the
// translations) and refined jointly over X, Y and all poses by Gauss-Newton on SE(3), each
// pose's mismatch (A_i X)^-1 Y B_i weighted by its covariance (see HandEyeOptions).
// Sphere method: a sphere held by the robot at N TCP positions, its centre found in each
// 3D scan; a rigid fit (Umeyama) of the centres to the TCP positions gives T_base_camera.
#include <cstdint>
#include <string>
#include <vector>

#include "fettle/config/calibration.hpp"
#include "fettle/core/cloud.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"

namespace fettle::vision::calibration {

struct HandEyeSample {
  std::string name;
  Transform T_base_flange = Transform::Identity();   ///< robot pose (flange in base)
  Transform T_camera_board = Transform::Identity();  ///< board seen by the camera
};

struct HandEyeOptions {
  std::size_t min_poses = 6;
  /// Poses must rotate the flange by at least this much relative to each other...
  double min_rotation_deg = 10.0;
  /// ...about at least two axes this far apart (deg); less is a degenerate pose set.
  double min_axis_spread_deg = 15.0;
  /// Expected noise (1 sigma per axis) of the robot's flange poses and of the board poses the
  /// camera measures, applied in the flange and board frames. The refinement weights every
  /// pose's mismatch with the 6x6 covariance these give (rotation noise of the flange times the
  /// flange-to-board lever arm included); only their ratios change the result.
  double robot_noise_mm = 0.03;
  double robot_noise_deg = 0.03;
  double board_noise_mm = 0.03;
  double board_noise_deg = 0.03;
  /// A pose is an outlier when its residual exceeds outlier_factor x the median residual and
  /// the floor below; outliers are reported and left out of the solution.
  double outlier_factor = 5.0;
  double outlier_floor_mm = 0.5;
  double outlier_floor_deg = 0.25;
  bool drop_outliers = true;
};

struct HandEyeResult {
  Transform T_base_camera = Transform::Identity();
  Transform T_flange_board = Transform::Identity();  ///< board method only
  config::HandEyeResiduals residuals;                ///< per pose, rms, max, method
};

/// Checks that robot poses can determine a hand-eye calibration: enough of them, rotated
/// enough, about at least two different axes. The Error says what poses to add.
Status check_pose_set(const std::vector<Transform>& T_base_flange, const HandEyeOptions& options = {});

/// Board method. Errors: "calibration.too_few_poses", "calibration.degenerate_poses".
Result<HandEyeResult> calibrate_hand_eye_board(const std::vector<HandEyeSample>& samples,
                                               const HandEyeOptions& options = {});

struct SphereFitOptions {
  double radius_mm = 0.0;            ///< known sphere radius; 0 = unknown (fitted)
  double radius_tolerance_mm = 2.0;  ///< candidate spheres off the known radius are rejected
  double inlier_mm = 0.5;            ///< point-to-surface distance of an inlier
  int iterations = 400;
  std::size_t min_inliers = 30;
  std::uint64_t seed = 1;
};

struct SphereFit {
  Vec3 center_mm = Vec3::Zero();
  double radius_mm = 0.0;
  std::size_t inliers = 0;
  double rms_mm = 0.0;  ///< inlier point-to-surface RMS
};

/// RANSAC sphere fit, refined by least squares on the inliers. Error "calibration.no_sphere".
Result<SphereFit> fit_sphere(const std::vector<Vec3>& points_mm, const SphereFitOptions& options = {});
Result<SphereFit> fit_sphere(const OrganizedCloud& cloud, const SphereFitOptions& options = {});

struct SphereSample {
  std::string name;
  Vec3 tcp_base_mm = Vec3::Zero();       ///< sphere centre (robot TCP) in the base frame
  Vec3 center_camera_mm = Vec3::Zero();  ///< sphere centre found in the scan
};

/// Sphere method: Umeyama rigid fit of the centres to the TCP positions. Errors:
/// "calibration.too_few_poses", "calibration.degenerate_poses" (positions on a line or in a
/// small volume).
Result<HandEyeResult> calibrate_hand_eye_sphere(const std::vector<SphereSample>& samples,
                                                const HandEyeOptions& options = {});

}  // namespace fettle::vision::calibration
