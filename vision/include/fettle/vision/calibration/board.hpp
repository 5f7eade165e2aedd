#pragma once
// Camera intrinsics from chessboard images (Zhang's method through OpenCV), board
// detection with blur and partial-view checks, and board poses (solvePnP) for hand-eye.
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "fettle/config/calibration.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"

namespace fettle::vision::calibration {

/// A chessboard: `cols` x `rows` INNER corners, squares `square_mm` wide. The board frame
/// has its origin at the first inner corner, x along the columns, y along the rows, z
/// into the board (OpenCV's convention).
struct BoardSpec {
  int cols = 0;
  int rows = 0;
  double square_mm = 0.0;
};

/// Parses "COLSxROWS" (inner corners, e.g. "9x6"); throws UserError saying what is wrong.
BoardSpec parse_board(const std::string& text, double square_mm);

/// An 8-bit grey image, row-major (index = v * width_px + u).
struct GrayImage {
  std::string name;  ///< file name or label, used in reports
  int width_px = 0;
  int height_px = 0;
  std::vector<std::uint8_t> pixels;
};

/// Reads an image file as grey; an Error says why not.
Result<GrayImage> load_gray_image(const std::filesystem::path& file);
/// The image files of a directory (png, jpg, jpeg, bmp, tif, tiff, pgm, ppm), sorted by name.
std::vector<std::filesystem::path> list_images(const std::filesystem::path& dir);

struct DetectOptions {
  /// Views whose average chessboard edge width (10%..90% rise, cv::estimateChessboardSharpness)
  /// is above this are blurred and skipped.
  double max_edge_width_px = 4.0;
  /// Corners closer than this to the image border make a view "partial" (skipped).
  double border_margin_px = 4.0;
};

/// Board corners found in one image (row by row, cols per row), board frame points in mm.
struct BoardObservation {
  std::vector<Eigen::Vector2d> corners_px;
  double edge_width_px = 0.0;
};

/// The board's inner corners in the board frame (mm), in detection order.
std::vector<Eigen::Vector3d> board_points_mm(const BoardSpec& board);

/// Finds the board in an image. Error codes: "calibration.board_not_found" (absent, partly
/// outside the image or occluded), "calibration.partial_view", "calibration.blurred".
Result<BoardObservation> detect_board(const GrayImage& image, const BoardSpec& board, const DetectOptions& options = {});

/// A board pose seen by a calibrated camera (solvePnP), and its reprojection RMS.
struct BoardPose {
  Transform T_camera_board = Transform::Identity();
  double rms_px = 0.0;
};
Result<BoardPose> board_pose(const BoardObservation& observation, const BoardSpec& board,
                             const config::CameraIntrinsics& intrinsics);

struct IntrinsicsOptions {
  DetectOptions detect;
  std::size_t min_views = 5;  ///< fewer usable views is an error
  bool fix_k3 = true;         ///< estimate k1 k2 p1 p2 only (k3 = 0) unless the lens needs it
};

/// One input view and what became of it.
struct ViewReport {
  std::string name;
  bool used = false;
  std::string skip_reason;  ///< why it was skipped (empty when used)
  double rms_px = 0.0;      ///< reprojection RMS of this view (used views)
};

struct IntrinsicsResult {
  config::CameraIntrinsics intrinsics;  ///< K, distortion, image size, rms_px, views
  std::vector<ViewReport> views;        ///< every input view, in input order
};

/// Zhang's method (cv::calibrateCamera). Error "calibration.too_few_views" when fewer than
/// options.min_views views are usable (the message lists why each was skipped);
/// "calibration.image_size" when the images differ in size.
Result<IntrinsicsResult> calibrate_intrinsics(const std::vector<GrayImage>& images, const BoardSpec& board,
                                              const IntrinsicsOptions& options = {});

}  // namespace fettle::vision::calibration
