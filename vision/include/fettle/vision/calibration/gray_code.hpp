#pragma once
// Camera-projector correspondences from Gray-code patterns (paper Eqs. 4-6; Moreno & Taubin
// 2012, "Simple, accurate, and robust projector-camera calibration"):
//  1. gray_code_patterns(): the images the projector shows, in a fixed order;
//  2. decode_gray_code(): per camera pixel, the projector column and row it sees (pixels in
//     shadow, on dark or glossy spots, or at stripe edges too blurred to tell are invalid);
//  3. projector_corners(): the projector coordinates of the board corners the camera found,
//     each from a homography fitted to the decoded pixels around the corner;
//  4. decode_stereo_view(): 1-3 for one board pose -> a StereoView for
//     calibrate_camera_projector().
#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "fettle/config/calibration.hpp"
#include "fettle/core/result.hpp"
#include "fettle/vision/calibration/board.hpp"
#include "fettle/vision/calibration/stereo.hpp"

namespace fettle::vision::calibration {

/// The Gray-code pattern sequence of a projector of width_px x height_px. Order (and names):
///   0 "white", 1 "black",
///   then for every column bit b = 0 .. column_bits-1, most significant first:
///     "col_bb" (pattern), "col_bb_inv" (its inverse),
///   then the same for the row bits: "row_bb", "row_bb_inv".
/// Column pattern b is white at projector column c when bit (column_bits-1-b) of gray(c) is 1,
/// gray(c) = c ^ (c >> 1); rows likewise. Projector pixel c covers x in [c-0.5, c+0.5) (OpenCV).
struct GrayCodeLayout {
  int width_px = 0;
  int height_px = 0;
  int column_bits = 0;  ///< ceil(log2(width_px))
  int row_bits = 0;     ///< ceil(log2(height_px))

  static GrayCodeLayout for_projector(int width_px, int height_px);
  std::size_t image_count() const { return 2 + 2 * static_cast<std::size_t>(column_bits + row_bits); }
  /// The names above, in order (file stems for the CLI).
  std::vector<std::string> names() const;
};

/// The pattern images (8-bit, 0 or 255), in GrayCodeLayout order.
std::vector<GrayImage> gray_code_patterns(const GrayCodeLayout& layout);

struct GrayDecodeOptions {
  /// A pixel is invalid (shadow, dark or far surface) when white - black is below this.
  double min_contrast_grey = 15.0;
  /// A bit is undecidable, and the pixel invalid, when |pattern - inverse| is below this
  /// (stripe edges blurred together, noise) ...
  double min_bit_margin_grey = 4.0;
  /// ... or below this fraction of the pixel's white - black contrast.
  double min_bit_margin_fraction = 0.08;
};

/// Per camera pixel: the projector column and row it sees, or -1 (invalid).
struct ProjectorMap {
  int width_px = 0;  ///< camera image size
  int height_px = 0;
  std::vector<std::int32_t> column;  ///< row-major, index = v * width_px + u
  std::vector<std::int32_t> row;
  std::size_t valid_pixels = 0;
  std::size_t low_contrast_pixels = 0;  ///< invalid: white - black too small
  std::size_t undecided_pixels = 0;     ///< invalid: a bit too close to call, or a code outside the projector
  bool valid(int u, int v) const { return column[index(u, v)] >= 0; }
  std::size_t index(int u, int v) const {
    return static_cast<std::size_t>(v) * static_cast<std::size_t>(width_px) + static_cast<std::size_t>(u);
  }
};

/// Decodes the camera images of one board pose, given in GrayCodeLayout order. Errors:
/// "calibration.pattern_count" (not layout.image_count() images), "calibration.image_size"
/// (an image of another size than the first; the message names it).
Result<ProjectorMap> decode_gray_code(const std::vector<GrayImage>& camera_images, const GrayCodeLayout& layout,
                                      const GrayDecodeOptions& options = {});

struct ProjectorCornerOptions {
  /// Decoded pixels within this many camera pixels (square window) of a corner are used.
  int window_radius_px = 20;
  /// A corner needs at least this many valid decoded pixels in its window.
  std::size_t min_pixels = 60;
  /// Fitted pixels further than this from the homography (projector px) are dropped and the
  /// fit repeated once (stray decode errors, e.g. at an inter-reflection).
  double max_pixel_error_px = 1.5;
};

/// The projector coordinates of every camera corner: a homography camera px -> projector px
/// fitted (least squares, normalized DLT, then Gauss-Newton on the projector-side error) to the
/// valid decoded pixels in the window around it, evaluated at the corner.
struct ProjectorCorners {
  std::vector<Eigen::Vector2d> projector_px;  ///< one per camera corner (unset where !found)
  std::vector<bool> found;
  std::vector<std::size_t> pixels_used;
  std::vector<double> fit_rms_px;  ///< RMS of the fitted pixels about the homography (projector px)
  std::size_t found_count() const;
};
ProjectorCorners projector_corners(const ProjectorMap& map, const std::vector<Eigen::Vector2d>& camera_corners_px,
                                   const ProjectorCornerOptions& options = {});

struct StructuredLightOptions {
  DetectOptions detect;  ///< the board is found in the "white" image
  GrayDecodeOptions decode;
  ProjectorCornerOptions corners;
  /// A view needs at least this fraction of the board's corners decoded.
  double min_corner_fraction = 0.5;
};

struct StructuredLightView {
  StereoView view;  ///< the corners found in both camera and projector
  ProjectorMap map;
  std::size_t corners_total = 0;
  std::size_t corners_decoded = 0;
};

/// One board pose: finds the board in the "white" image, decodes the patterns and gives the
/// projector coordinates of its corners. Errors: those of decode_gray_code and detect_board
/// (the message names the white image), "calibration.too_few_corners" (fewer decoded corners
/// than min_corner_fraction of the board's: says how many and why, e.g. shadow).
Result<StructuredLightView> decode_stereo_view(const std::vector<GrayImage>& camera_images, const BoardSpec& board,
                                               const GrayCodeLayout& layout,
                                               const StructuredLightOptions& options = {});

}  // namespace fettle::vision::calibration
