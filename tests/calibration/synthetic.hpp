#pragma once
// Synthetic ground truth for the calibration tests: chessboard images rendered through a
// known camera (OpenCV), hand-eye pose sets with known T_base_camera / T_flange_board.
#include <random>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "fettle/config/calibration.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/vision/calibration/board.hpp"
#include "fettle/vision/calibration/hand_eye.hpp"

namespace fettle::test {

/// The test camera: 1032 x 772 px, f = 1200 px, slight barrel distortion.
config::CameraIntrinsics test_camera(bool distorted = true);

/// Renders the board (with a one-square white margin) at T_camera_board through the camera.
cv::Mat render_board(const vision::calibration::BoardSpec& board, const config::CameraIntrinsics& camera,
                     const Transform& T_camera_board, double blur_sigma_px = 0.0, double noise_grey = 1.0,
                     unsigned seed = 1);

vision::calibration::GrayImage to_gray_image(const cv::Mat& m, const std::string& name);

/// A board pose facing the camera at `distance_mm`, offset and tilted (radians).
Transform board_pose_facing_camera(const vision::calibration::BoardSpec& board, double distance_mm, double dx_mm,
                                   double dy_mm, double tilt_x, double tilt_y, double spin_z);

/// A small random motion: per-axis Gaussian sigma in mm and degrees.
Transform noise(std::mt19937_64& rng, double sigma_mm, double sigma_deg);

struct HandEyeTruth {
  Transform T_base_camera;
  Transform T_flange_board;
};

/// The ground truth used by the hand-eye tests: the camera 600 mm above the table looking
/// down (as in the simulator), a board 80 mm in front of the flange.
HandEyeTruth hand_eye_truth();

/// `n` well-spread board poses in the camera and the matching robot poses, with per-axis
/// noise added to both (mm, deg).
std::vector<vision::calibration::HandEyeSample> hand_eye_samples(const HandEyeTruth& truth, int n, double sigma_mm,
                                                                 double sigma_deg, std::uint64_t seed,
                                                                 bool single_axis = false);

/// Rotation angle (deg) and translation distance (mm) between two transforms.
double rotation_error_deg(const Transform& a, const Transform& b);
double translation_error_mm(const Transform& a, const Transform& b);

}  // namespace fettle::test
