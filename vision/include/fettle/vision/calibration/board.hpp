#pragma once
// Camera intrinsics from chessboard or ChArUco images (Zhang's method through OpenCV), board
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

enum class BoardType { chessboard, charuco };

/// A calibration board.
///  - chessboard: `cols` x `rows` INNER corners, squares `square_mm` wide. The board frame has
///    its origin at the first inner corner, x along the columns, y along the rows, z into the
///    board (OpenCV's convention).
///  - charuco (ChArUco): `cols` x `rows` SQUARES (as board generators and OpenCV count them),
///    squares `square_mm` wide, ArUco markers `marker_mm` wide from `dictionary` in the white
///    squares. Its (cols-1) x (rows-1) inner corners are identified by the markers next to
///    them, so a view that shows only part of the board still counts. Board frame as OpenCV's
///    CharucoBoard: origin at the outer corner of the first square (top left as draw_board
///    draws it), x along the columns, y along the rows, z into the board.
struct BoardSpec {
  int cols = 0;
  int rows = 0;
  double square_mm = 0.0;
  BoardType type = BoardType::chessboard;
  double marker_mm = 0.0;                 ///< charuco only
  std::string dictionary = "DICT_5X5_100";  ///< charuco only: an OpenCV predefined dictionary name
};

/// Parses "COLSxROWS" (inner corners, e.g. "9x6"); throws UserError saying what is wrong.
BoardSpec parse_board(const std::string& text, double square_mm);
/// Parses a ChArUco board: "COLSxROWS" SQUARES (e.g. "7x5"), square and marker size, and the
/// dictionary name (DICT_4X4_50 ... DICT_7X7_1000, DICT_ARUCO_ORIGINAL, DICT_APRILTAG_16h5 ...);
/// throws UserError saying what is wrong (marker not smaller than the square, a dictionary
/// with fewer markers than the board needs, ...).
BoardSpec parse_charuco_board(const std::string& text, double square_mm, double marker_mm,
                              const std::string& dictionary);
/// The board as a person reads it, e.g. "9x6 chessboard (inner corners), 20.00 mm squares".
std::string describe(const BoardSpec& board);

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
  /// Corners closer than this to the image border make a view "partial" (skipped; for ChArUco
  /// those corners are dropped and the rest of the view is used).
  double border_margin_px = 4.0;
  /// ChArUco: views with fewer identified corners than this are skipped.
  std::size_t min_charuco_corners = 8;
};

/// Board corners found in one image. Chessboard: every inner corner, row by row (ids empty).
/// ChArUco: the corners identified, with their ids (index into board_points_mm).
struct BoardObservation {
  std::vector<Eigen::Vector2d> corners_px;
  std::vector<int> ids;
  double edge_width_px = 0.0;  ///< 0 when not measured (ChArUco)
};

/// The board's inner corners in the board frame (mm): chessboard in detection order, ChArUco
/// by corner id.
std::vector<Eigen::Vector3d> board_points_mm(const BoardSpec& board);
/// The board frame points of an observation's corners, in its order.
std::vector<Eigen::Vector3d> observed_points_mm(const BoardSpec& board, const BoardObservation& observation);

/// A printable image of the board (ChArUco: OpenCV's drawing) and where board points are in
/// it: pixel = board_to_px * (x_mm, y_mm, 1).
struct BoardImage {
  GrayImage image;
  Eigen::Matrix<double, 2, 3> board_to_px = Eigen::Matrix<double, 2, 3>::Zero();
};
/// Draws the board with `px_per_square` pixels per square and a white margin of `margin_px`.
BoardImage draw_board(const BoardSpec& board, int px_per_square, int margin_px);

/// Finds the board in an image. Error codes: "calibration.board_not_found" (absent, partly
/// outside the image or occluded; ChArUco: fewer than min_charuco_corners corners identified),
/// "calibration.partial_view" (chessboard), "calibration.blurred".
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

/// Zhang's method (cv::calibrateCamera; ChArUco: cv::aruco::calibrateCameraCharuco). Error "calibration.too_few_views" when fewer than
/// options.min_views views are usable (the message lists why each was skipped);
/// "calibration.image_size" when the images differ in size.
Result<IntrinsicsResult> calibrate_intrinsics(const std::vector<GrayImage>& images, const BoardSpec& board,
                                              const IntrinsicsOptions& options = {});

}  // namespace fettle::vision::calibration
