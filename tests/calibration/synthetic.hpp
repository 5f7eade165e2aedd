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
#include "fettle/vision/calibration/gray_code.hpp"
#include "fettle/vision/calibration/hand_eye.hpp"

namespace fettle::test {

/// The test camera: 1032 x 772 px, f = 1200 px, slight barrel distortion.
config::CameraIntrinsics test_camera(bool distorted = true);

/// Renders the board (with a one-square white margin) at T_camera_board through the camera.
cv::Mat render_board(const vision::calibration::BoardSpec& board, const config::CameraIntrinsics& camera,
                     const Transform& T_camera_board, double blur_sigma_px = 0.0, double noise_grey = 1.0,
                     unsigned seed = 1);

/// Renders a drawn board (vision::calibration::draw_board, e.g. a ChArUco board) at
/// T_camera_board through the camera; parts outside the image are cut off (partial views).
cv::Mat render_board_image(const vision::calibration::BoardImage& board, const config::CameraIntrinsics& camera,
                           const Transform& T_camera_board, double blur_sigma_px = 0.0, double noise_grey = 1.0,
                           unsigned seed = 1);

vision::calibration::GrayImage to_gray_image(const cv::Mat& m, const std::string& name);

/// A board pose facing the camera at `distance_mm`, offset and tilted (radians).
Transform board_pose_facing_camera(const vision::calibration::BoardSpec& board, double distance_mm, double dx_mm,
                                   double dy_mm, double tilt_x, double tilt_y, double spin_z);

/// A small random motion: per-axis Gaussian sigma in mm and degrees (a rotation vector with
/// sigma_deg on each axis and a translation with sigma_mm on each axis).
Transform noise(std::mt19937_64& rng, double sigma_mm, double sigma_deg);

struct HandEyeTruth {
  Transform T_base_camera;
  Transform T_flange_board;
};

/// The ground truth used by the hand-eye tests: the camera 600 mm above the table looking
/// down (as in the simulator), a board 80 mm in front of the flange (or, with
/// `board_on_flange_plate`, centred on the flange 25 mm in front of it, as
/// docs/calibration.md recommends).
HandEyeTruth hand_eye_truth(bool board_on_flange_plate = false);

/// How a synthetic hand-eye pose set is spread: the board centre at distance_mm +- depth_mm
/// from the camera and +- lateral_x/y_mm across the view, tilted up to tilt_deg about the
/// camera x and y axes and turned up to spin_deg about its normal (uniform random).
struct PoseDesign {
  double distance_mm = 480.0;
  double depth_mm = 60.0;
  double lateral_x_mm = 120.0;
  double lateral_y_mm = 90.0;
  double tilt_deg = 30.0;
  double spin_deg = 60.0;
  bool single_axis = false;  ///< spin only (a degenerate set)
  /// Designed rather than uniform: the board near the corners of the view (lateral +-80..100 %
  /// of the range) at the near, middle or far depth, each pose tilted by min_tilt_deg..tilt_deg
  /// towards a random direction.
  bool designed = false;
  double min_tilt_deg = 0.0;
};
/// The pose set docs/calibration.md recommends: the board near the corners of the view at
/// three depths (+-80 mm), each pose tilted 30-45 deg in its own direction, turned up to 90 deg.
PoseDesign recommended_design();

/// Noise added to every robot pose (flange frame) and every board pose (board frame), each
/// an independent `noise(rng, per-axis sigma)` draw.
struct PoseNoise {
  double robot_sigma_mm = 0.0;  ///< per axis
  double robot_sigma_deg = 0.0;
  double board_sigma_mm = 0.0;
  double board_sigma_deg = 0.0;
  /// The same noise on robot and board poses; `magnitude_mm/deg` is the RMS length of the 3D
  /// error (per-axis sigma = magnitude / sqrt(3)).
  static PoseNoise rms_magnitude(double magnitude_mm, double magnitude_deg);
  static PoseNoise per_axis(double sigma_mm, double sigma_deg);
};

std::vector<vision::calibration::HandEyeSample> hand_eye_samples(const HandEyeTruth& truth, int n,
                                                                 const PoseDesign& design, const PoseNoise& noise,
                                                                 std::uint64_t seed);
/// The same with the default design and per-axis noise (mm, deg) on both robot and board poses.
std::vector<vision::calibration::HandEyeSample> hand_eye_samples(const HandEyeTruth& truth, int n, double sigma_mm,
                                                                 double sigma_deg, std::uint64_t seed,
                                                                 bool single_axis = false);

/// A camera and a projector looking at a planar chessboard (Gray-code calibration tests).
/// Grey value of a camera pixel = albedo x (ambient + projector x pattern), area-averaged over
/// supersample x supersample points of the pixel, then blurred (optics) and noisy (sensor).
struct StructuredLightScene {
  config::CameraIntrinsics camera;
  config::CameraIntrinsics projector;
  Transform T_camera_projector = Transform::Identity();
  vision::calibration::BoardSpec board{9, 6, 20.0};
  Transform T_camera_board = Transform::Identity();
  double white_albedo = 0.9;
  double black_albedo = 0.12;
  double ambient_grey = 12.0;     ///< room light on an albedo-1 surface
  double projector_grey = 220.0;  ///< projector white on an albedo-1 surface
  double background_grey = 3.0;   ///< beyond the board (far away, not lit)
  int supersample = 3;            ///< samples per pixel axis; 1 = the pixel centre only
  double blur_sigma_px = 0.0;
  double noise_grey = 0.0;
  unsigned seed = 1;
  /// A disc on the board (board frame x, y in mm) that the projector's light does not reach
  /// (an object between projector and board); radius 0 = none.
  Eigen::Vector2d shadow_centre_mm = Eigen::Vector2d::Zero();
  double shadow_radius_mm = 0.0;
  /// A dark stain on the board (albedo stain_albedo); radius 0 = none.
  Eigen::Vector2d stain_centre_mm = Eigen::Vector2d::Zero();
  double stain_radius_mm = 0.0;
  double stain_albedo = 0.02;
};

struct StructuredLightRender {
  std::vector<vision::calibration::GrayImage> images;  ///< GrayCodeLayout order, named as the layout
  /// The projector pixel whose light falls on the board plane at each camera pixel centre
  /// (CV_32SC1; whether the board, the shadow or nothing is there; beyond the projector's image
  /// too, where it would be if the image went on).
  cv::Mat true_column, true_row;
  /// 255 where the pixel centre sees the board lit by the projector (CV_8UC1).
  cv::Mat lit;
  /// 255 where the pixel centre is in the shadow or on the stain (CV_8UC1).
  cv::Mat shadow_or_stain;
};

/// Renders what the camera sees of the board under each Gray-code pattern (the library's
/// gray_code_patterns(layout), looked up per projector pixel).
StructuredLightRender render_structured_light(const StructuredLightScene& scene,
                                              const vision::calibration::GrayCodeLayout& layout);

/// The Gray-code tests' setup: the test camera and a 1280 x 800 px projector (f = 1400 px,
/// principal point (640, 560), k1 = 0.02) 180 mm to the camera's right, toed in by 12 deg.
config::CameraIntrinsics structured_light_projector();
Transform structured_light_T_camera_projector();
StructuredLightScene structured_light_scene();
/// `n` board poses 430-570 mm from the camera, tilted up to 30 deg about two axes and turned up
/// to 30 deg, with the whole board (and its margin) inside both the camera's and the
/// projector's image.
std::vector<Transform> structured_light_board_poses(const StructuredLightScene& scene, int n, std::uint64_t seed);

/// Projects a point given in a camera's frame (mm) to its pixel, with the camera's distortion.
Eigen::Vector2d project_point(const config::CameraIntrinsics& k, const Vec3& p_mm);

/// Rotation angle (deg) and translation distance (mm) between two transforms.
double rotation_error_deg(const Transform& a, const Transform& b);
double translation_error_mm(const Transform& a, const Transform& b);

}  // namespace fettle::test
