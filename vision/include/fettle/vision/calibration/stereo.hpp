#pragma once
// Camera-projector extrinsics (paper Eqs. 4-6): the projector is calibrated as an inverse
// camera from board corners seen by the camera and decoded in projector coordinates
// (e.g. from Gray-code patterns); a stereo calibration gives T_camera_projector.
#include <vector>

#include <Eigen/Core>

#include "fettle/config/calibration.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"

namespace fettle::vision::calibration {

/// One board pose: its corners in the board frame and where camera and projector see them.
struct StereoView {
  std::vector<Eigen::Vector3d> board_points_mm;
  std::vector<Eigen::Vector2d> camera_px;
  std::vector<Eigen::Vector2d> projector_px;
};

struct StereoOptions {
  /// Keep both intrinsics as given (true) or refine them with the extrinsics (false).
  bool fix_intrinsics = true;
  std::size_t min_views = 3;
};

struct StereoResult {
  Transform T_camera_projector = Transform::Identity();  ///< projector points -> camera frame
  config::CameraIntrinsics camera;
  config::CameraIntrinsics projector;
  double rms_px = 0.0;
};

/// The projector's intrinsics as an inverse camera (Zhang's method, cv::calibrateCamera, k3 = 0)
/// from the board points and their projector pixels of every view: the initial projector
/// intrinsics for calibrate_camera_projector when none are known. rms_px and views are set.
/// Errors: "calibration.too_few_views" (fewer than 3 views), "calibration.bad_views".
Result<config::CameraIntrinsics> calibrate_projector_intrinsics(const std::vector<StereoView>& views, int width_px,
                                                                int height_px);

/// cv::stereoCalibrate from the correspondences; `camera` and `projector` are the known (or
/// initial) intrinsics. Errors: "calibration.too_few_views", "calibration.bad_views".
Result<StereoResult> calibrate_camera_projector(const std::vector<StereoView>& views,
                                                const config::CameraIntrinsics& camera,
                                                const config::CameraIntrinsics& projector,
                                                const StereoOptions& options = {});

}  // namespace fettle::vision::calibration
