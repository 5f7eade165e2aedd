// Chessboard and ChArUco detection, board poses (solvePnP) and intrinsics (Zhang's method via
// OpenCV; ChArUco through the aruco module of OpenCV 4.6).
#include "fettle/vision/calibration/board.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <set>
#include <utility>

#include <opencv2/aruco.hpp>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/core/eigen.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"

namespace fettle::vision::calibration {

namespace {

std::string fmt(double v, int decimals = 2) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  return buf;
}

cv::Mat as_mat(const GrayImage& image) {
  // OpenCV only reads the pixels here.
  return cv::Mat(image.height_px, image.width_px, CV_8UC1,
                 const_cast<std::uint8_t*>(image.pixels.data()));  // NOLINT(cppcoreguidelines-pro-type-const-cast)
}

std::vector<cv::Point3f> to_cv(const std::vector<Eigen::Vector3d>& pts) {
  std::vector<cv::Point3f> out;
  out.reserve(pts.size());
  for (const auto& p : pts)
    out.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()), static_cast<float>(p.z()));
  return out;
}

std::vector<cv::Point2f> to_cv(const std::vector<Eigen::Vector2d>& pts) {
  std::vector<cv::Point2f> out;
  out.reserve(pts.size());
  for (const auto& p : pts) out.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()));
  return out;
}

const std::vector<std::pair<std::string, int>>& dictionaries() {
  static const std::vector<std::pair<std::string, int>> d = {
      {"DICT_4X4_50", cv::aruco::DICT_4X4_50},           {"DICT_4X4_100", cv::aruco::DICT_4X4_100},
      {"DICT_4X4_250", cv::aruco::DICT_4X4_250},         {"DICT_4X4_1000", cv::aruco::DICT_4X4_1000},
      {"DICT_5X5_50", cv::aruco::DICT_5X5_50},           {"DICT_5X5_100", cv::aruco::DICT_5X5_100},
      {"DICT_5X5_250", cv::aruco::DICT_5X5_250},         {"DICT_5X5_1000", cv::aruco::DICT_5X5_1000},
      {"DICT_6X6_50", cv::aruco::DICT_6X6_50},           {"DICT_6X6_100", cv::aruco::DICT_6X6_100},
      {"DICT_6X6_250", cv::aruco::DICT_6X6_250},         {"DICT_6X6_1000", cv::aruco::DICT_6X6_1000},
      {"DICT_7X7_50", cv::aruco::DICT_7X7_50},           {"DICT_7X7_100", cv::aruco::DICT_7X7_100},
      {"DICT_7X7_250", cv::aruco::DICT_7X7_250},         {"DICT_7X7_1000", cv::aruco::DICT_7X7_1000},
      {"DICT_ARUCO_ORIGINAL", cv::aruco::DICT_ARUCO_ORIGINAL},
      {"DICT_APRILTAG_16h5", cv::aruco::DICT_APRILTAG_16h5},
      {"DICT_APRILTAG_25h9", cv::aruco::DICT_APRILTAG_25h9},
      {"DICT_APRILTAG_36h10", cv::aruco::DICT_APRILTAG_36h10},
      {"DICT_APRILTAG_36h11", cv::aruco::DICT_APRILTAG_36h11}};
  return d;
}

cv::Ptr<cv::aruco::Dictionary> dictionary(const std::string& name) {
  for (const auto& [n, id] : dictionaries())
    if (n == name) return cv::aruco::getPredefinedDictionary(id);
  std::string known;
  for (const auto& [n, id] : dictionaries()) known += (known.empty() ? "" : ", ") + n;
  throw UserError("unknown ArUco dictionary \"" + name + "\" (known: " + known + ")");
}

cv::Ptr<cv::aruco::CharucoBoard> charuco(const BoardSpec& b) {
  return cv::aruco::CharucoBoard::create(b.cols, b.rows, static_cast<float>(b.square_mm),
                                         static_cast<float>(b.marker_mm), dictionary(b.dictionary));
}

cv::Matx33d camera_matrix(const config::CameraIntrinsics& k) {
  return {k.fx_px, k.skew, k.cx_px, 0.0, k.fy_px, k.cy_px, 0.0, 0.0, 1.0};
}

double rms(const std::vector<cv::Point2f>& a, const std::vector<cv::Point2f>& b) {
  double ss = 0.0;
  for (std::size_t i = 0; i < a.size(); ++i) ss += cv::norm(a[i] - b[i]) * cv::norm(a[i] - b[i]);
  return a.empty() ? 0.0 : std::sqrt(ss / static_cast<double>(a.size()));
}

}  // namespace

BoardSpec parse_board(const std::string& text, double square_mm) {
  int cols = 0, rows = 0;
  char x = 0, extra = 0;
  if (std::sscanf(text.c_str(), "%d%c%d%c", &cols, &x, &rows, &extra) != 3 || (x != 'x' && x != 'X'))
    throw UserError("board \"" + text + "\" is not COLSxROWS (inner corners, e.g. 9x6)");
  if (cols < 3 || rows < 3 || cols > 100 || rows > 100)
    throw UserError("board \"" + text + "\": need 3 to 100 inner corners in each direction");
  if (cols == rows)
    throw UserError("board \"" + text +
                    "\": a square board's orientation is ambiguous; use one with different inner corner counts "
                    "(e.g. 9x6)");
  if (!(square_mm > 0.0) || square_mm > 1000.0)
    throw UserError("square size " + fmt(square_mm) + " mm is out of range (allowed: above 0 to 1000 mm)");
  return BoardSpec{cols, rows, square_mm};
}

BoardSpec parse_charuco_board(const std::string& text, double square_mm, double marker_mm,
                              const std::string& dict) {
  int cols = 0, rows = 0;
  char x = 0, extra = 0;
  if (std::sscanf(text.c_str(), "%d%c%d%c", &cols, &x, &rows, &extra) != 3 || (x != 'x' && x != 'X'))
    throw UserError("ChArUco board \"" + text + "\" is not COLSxROWS (squares, e.g. 7x5)");
  if (cols < 3 || rows < 3 || cols > 100 || rows > 100)
    throw UserError("ChArUco board \"" + text + "\": need 3 to 100 squares in each direction");
  if (!(square_mm > 0.0) || square_mm > 1000.0)
    throw UserError("square size " + fmt(square_mm) + " mm is out of range (allowed: above 0 to 1000 mm)");
  if (!(marker_mm > 0.0) || marker_mm >= square_mm)
    throw UserError("marker size " + fmt(marker_mm) + " mm must be above 0 and smaller than the square (" +
                    fmt(square_mm) + " mm); give --marker-mm");
  const auto d = dictionary(dict);
  const int markers = (cols * rows + 1) / 2;  // at most; OpenCV puts one in every other square
  if (d->bytesList.rows < markers)
    throw UserError("ChArUco board \"" + text + "\" needs " + std::to_string(markers) + " markers, dictionary " + dict +
                    " has only " + std::to_string(d->bytesList.rows) + "; use a larger dictionary");
  BoardSpec b{cols, rows, square_mm, BoardType::charuco, marker_mm, dict};
  return b;
}

std::string describe(const BoardSpec& b) {
  if (b.type == BoardType::charuco)
    return std::to_string(b.cols) + "x" + std::to_string(b.rows) + " ChArUco (squares), " + fmt(b.square_mm) +
           " mm squares, " + fmt(b.marker_mm) + " mm " + b.dictionary + " markers";
  return std::to_string(b.cols) + "x" + std::to_string(b.rows) + " chessboard (inner corners), " + fmt(b.square_mm) +
         " mm squares";
}

Result<GrayImage> load_gray_image(const std::filesystem::path& file) {
  const cv::Mat m = cv::imread(file.string(), cv::IMREAD_GRAYSCALE);
  if (m.empty())
    return Error{"calibration.bad_image", file.string() + ": cannot be read as an image (missing, unreadable or not "
                                                          "an image format OpenCV knows)"};
  GrayImage img;
  img.name = file.filename().string();
  img.width_px = m.cols;
  img.height_px = m.rows;
  img.pixels.resize(static_cast<std::size_t>(m.cols) * static_cast<std::size_t>(m.rows));
  for (int v = 0; v < m.rows; ++v)
    std::copy(m.ptr<std::uint8_t>(v), m.ptr<std::uint8_t>(v) + m.cols,
              img.pixels.begin() + static_cast<std::ptrdiff_t>(v) * m.cols);
  return img;
}

std::vector<std::filesystem::path> list_images(const std::filesystem::path& dir) {
  static const std::set<std::string> kExt{".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm"};
  std::vector<std::filesystem::path> files;
  for (const auto& e : std::filesystem::directory_iterator(dir)) {
    if (!e.is_regular_file()) continue;
    std::string ext = e.path().extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    if (kExt.contains(ext)) files.push_back(e.path());
  }
  std::sort(files.begin(), files.end());
  return files;
}

std::vector<Eigen::Vector3d> board_points_mm(const BoardSpec& board) {
  std::vector<Eigen::Vector3d> pts;
  if (board.type == BoardType::charuco) {
    const auto b = charuco(board);  // keep the board alive while its corners are read
    for (const auto& p : b->chessboardCorners) pts.emplace_back(p.x, p.y, p.z);
    return pts;
  }
  for (int r = 0; r < board.rows; ++r)
    for (int c = 0; c < board.cols; ++c) pts.emplace_back(c * board.square_mm, r * board.square_mm, 0.0);
  return pts;
}

std::vector<Eigen::Vector3d> observed_points_mm(const BoardSpec& board, const BoardObservation& obs) {
  auto all = board_points_mm(board);
  if (obs.ids.empty()) return all;
  std::vector<Eigen::Vector3d> pts;
  for (const int id : obs.ids)
    if (id >= 0 && static_cast<std::size_t>(id) < all.size()) pts.push_back(all[static_cast<std::size_t>(id)]);
  return pts;
}

BoardImage draw_board(const BoardSpec& board, int pps, int margin) {
  BoardImage out;
  const double s = pps / board.square_mm;
  cv::Mat img;
  if (board.type == BoardType::charuco) {
    charuco(board)->draw(cv::Size(board.cols * pps + 2 * margin, board.rows * pps + 2 * margin), img, margin, 1);
    // Debian's OpenCV 4.6 draws the board frame's origin at the board's top-left corner, y down.
    out.board_to_px << s, 0.0, margin, 0.0, s, margin;
  } else {
    const int sx = board.cols + 1, sy = board.rows + 1;
    img = cv::Mat(sy * pps + 2 * margin, sx * pps + 2 * margin, CV_8UC1, cv::Scalar(255));
    for (int j = 0; j < sy; ++j)
      for (int i = 0; i < sx; ++i)
        if ((i + j) % 2 == 0) img(cv::Rect(margin + i * pps, margin + j * pps, pps, pps)).setTo(cv::Scalar(0));
    out.board_to_px << s, 0.0, margin + pps, 0.0, s, margin + pps;
  }
  // Pixel centres are at integer coordinates: a board point on a square edge lies between two
  // pixels, half a pixel before the edge's index.
  out.board_to_px(0, 2) -= 0.5;
  out.board_to_px(1, 2) -= 0.5;
  out.image.name = describe(board);
  out.image.width_px = img.cols;
  out.image.height_px = img.rows;
  out.image.pixels.assign(img.data, img.data + img.total());
  return out;
}

namespace {

Result<BoardObservation> detect_charuco(const GrayImage& image, const BoardSpec& board, const DetectOptions& o) {
  const cv::Mat m = as_mat(image);
  const auto b = charuco(board);
  std::vector<int> marker_ids;
  std::vector<std::vector<cv::Point2f>> marker_corners, rejected;
  auto params = cv::aruco::DetectorParameters::create();
  params->cornerRefinementMethod = cv::aruco::CORNER_REFINE_NONE;
  cv::aruco::detectMarkers(m, b->dictionary, marker_corners, marker_ids, params, rejected);
  if (!marker_ids.empty())
    cv::aruco::refineDetectedMarkers(m, b, marker_corners, marker_ids, rejected);
  std::vector<cv::Point2f> corners;
  std::vector<int> ids;
  if (!marker_ids.empty()) cv::aruco::interpolateCornersCharuco(marker_corners, marker_ids, m, b, corners, ids);
  BoardObservation obs;
  for (std::size_t i = 0; i < corners.size(); ++i) {
    const auto& c = corners[i];
    if (c.x < o.border_margin_px || c.y < o.border_margin_px || c.x > image.width_px - 1 - o.border_margin_px ||
        c.y > image.height_px - 1 - o.border_margin_px)
      continue;
    obs.corners_px.emplace_back(c.x, c.y);
    obs.ids.push_back(ids[i]);
  }
  const std::size_t total = b->chessboardCorners.size();
  if (obs.ids.size() < std::max<std::size_t>(o.min_charuco_corners, 6))
    return Error{"calibration.board_not_found",
                 std::to_string(marker_ids.size()) + " markers and " + std::to_string(obs.ids.size()) + " of " +
                     std::to_string(total) + " ChArUco corners identified, need " +
                     std::to_string(std::max<std::size_t>(o.min_charuco_corners, 6)) +
                     " (board not in view, too blurred, a different board or dictionary)"};
  if (cv::aruco::testCharucoCornersCollinear(b, obs.ids))
    return Error{"calibration.board_not_found", "the " + std::to_string(obs.ids.size()) +
                                                    " ChArUco corners identified lie on one line; show more of the "
                                                    "board"};
  // No blur check: OpenCV's sharpness measure assumes a plain chessboard, and the markers next
  // to the square edges skew it. A badly blurred view loses its markers and is skipped above.
  return obs;
}

}  // namespace

Result<BoardObservation> detect_board(const GrayImage& image, const BoardSpec& board, const DetectOptions& o) {
  if (board.type == BoardType::charuco) return detect_charuco(image, board, o);
  const cv::Mat m = as_mat(image);
  const cv::Size pattern(board.cols, board.rows);
  std::vector<cv::Point2f> corners;
  const bool found = cv::findChessboardCorners(
      m, pattern, corners, cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE | cv::CALIB_CB_FAST_CHECK);
  if (!found)
    return Error{"calibration.board_not_found",
                 "no complete " + std::to_string(board.cols) + "x" + std::to_string(board.rows) +
                     " chessboard found (board partly outside the image, occluded, too blurred, or a different "
                     "board size)"};
  cv::cornerSubPix(m, corners, cv::Size(5, 5), cv::Size(-1, -1),
                   cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 50, 0.001));
  for (const auto& c : corners) {
    if (c.x < o.border_margin_px || c.y < o.border_margin_px || c.x > image.width_px - 1 - o.border_margin_px ||
        c.y > image.height_px - 1 - o.border_margin_px)
      return Error{"calibration.partial_view", "board corner at (" + fmt(c.x, 0) + ", " + fmt(c.y, 0) +
                                                   ") px is at the image border: the board is partly outside the "
                                                   "view"};
  }
  const cv::Scalar sharp = cv::estimateChessboardSharpness(m, pattern, corners);
  BoardObservation obs;
  obs.edge_width_px = sharp[0];
  if (!(sharp[0] <= o.max_edge_width_px))
    return Error{"calibration.blurred", "blurred: board edges are " + fmt(sharp[0], 1) + " px wide (limit " +
                                            fmt(o.max_edge_width_px, 1) +
                                            " px); refocus or hold the board still and retake"};
  for (const auto& c : corners) obs.corners_px.emplace_back(c.x, c.y);
  return obs;
}

Result<BoardPose> board_pose(const BoardObservation& obs, const BoardSpec& board,
                             const config::CameraIntrinsics& k) {
  const auto obj = to_cv(observed_points_mm(board, obs));
  if (obs.corners_px.size() != obj.size() || obj.size() < 4)
    return Error{"calibration.bad_view", "the observation has " + std::to_string(obs.corners_px.size()) +
                                             " corners, the board " + std::to_string(obj.size()) +
                                             " matching points (need 4 or more)"};
  const std::vector<cv::Point2f> img = to_cv(obs.corners_px);
  const cv::Mat K(camera_matrix(k));
  const cv::Mat dist(k.distortion, true);
  cv::Vec3d rvec, tvec;
  if (!cv::solvePnP(obj, img, K, dist, rvec, tvec, false, cv::SOLVEPNP_IPPE))
    return Error{"calibration.pnp_failed", "the board pose could not be computed from the corners"};
  cv::solvePnPRefineLM(obj, img, K, dist, rvec, tvec);
  std::vector<cv::Point2f> proj;
  cv::projectPoints(obj, rvec, tvec, K, dist, proj);
  cv::Matx33d R;
  cv::Rodrigues(rvec, R);
  BoardPose p;
  Eigen::Matrix3d Re;
  cv::cv2eigen(cv::Mat(R), Re);
  p.T_camera_board.linear() = Re;
  p.T_camera_board.translation() = Vec3(tvec[0], tvec[1], tvec[2]);
  p.rms_px = rms(img, proj);
  return p;
}

Result<IntrinsicsResult> calibrate_intrinsics(const std::vector<GrayImage>& images, const BoardSpec& board,
                                              const IntrinsicsOptions& o) {
  auto logger = log::get("calibration");
  IntrinsicsResult result;
  std::vector<std::vector<cv::Point3f>> obj;
  std::vector<std::vector<cv::Point2f>> img;
  std::vector<std::vector<int>> ids;
  std::vector<std::size_t> used_index;
  cv::Size size(0, 0);
  for (std::size_t i = 0; i < images.size(); ++i) {
    const auto& im = images[i];
    ViewReport view;
    view.name = im.name;
    if (size.width == 0) size = cv::Size(im.width_px, im.height_px);
    if (im.width_px != size.width || im.height_px != size.height)
      return Error{"calibration.image_size", im.name + ": image is " + std::to_string(im.width_px) + "x" +
                                                 std::to_string(im.height_px) + " px, the first image " +
                                                 std::to_string(size.width) + "x" + std::to_string(size.height) +
                                                 "; all views must come from the same camera and mode"};
    auto obs = detect_board(im, board, o.detect);
    if (!obs) {
      view.skip_reason = obs.error().message;
      logger->info("view {}/{} {}: skipped: {}", i + 1, images.size(), im.name, view.skip_reason);
    } else {
      img.push_back(to_cv(obs->corners_px));
      obj.push_back(to_cv(observed_points_mm(board, *obs)));
      ids.push_back(obs->ids);
      used_index.push_back(i);
      view.used = true;
      logger->info("view {}/{} {}: board found ({} corners, edge width {:.1f} px)", i + 1, images.size(), im.name,
                   obs->corners_px.size(), obs->edge_width_px);
    }
    result.views.push_back(view);
  }
  if (img.size() < o.min_views) {
    std::string msg = "only " + std::to_string(img.size()) + " of " + std::to_string(images.size()) +
                      " views are usable, need at least " + std::to_string(o.min_views) +
                      "; take more views of the whole board, tilted up to 30-45 deg and covering the image corners.";
    for (const auto& v : result.views)
      if (!v.used) msg += "\n  " + v.name + ": " + v.skip_reason;
    return Error{"calibration.too_few_views", msg};
  }
  cv::Mat K, dist;
  std::vector<cv::Mat> rvecs, tvecs;
  int flags = 0;
  if (o.fix_k3) flags |= cv::CALIB_FIX_K3;
  const double rms_px = board.type == BoardType::charuco
                            ? cv::aruco::calibrateCameraCharuco(img, ids, charuco(board), size, K, dist, rvecs,
                                                                tvecs, flags)
                            : cv::calibrateCamera(obj, img, size, K, dist, rvecs, tvecs, flags);
  for (std::size_t k = 0; k < used_index.size(); ++k) {
    std::vector<cv::Point2f> proj;
    cv::projectPoints(obj[k], rvecs[k], tvecs[k], K, dist, proj);
    result.views[used_index[k]].rms_px = rms(img[k], proj);
  }
  auto& in = result.intrinsics;
  in.width_px = size.width;
  in.height_px = size.height;
  in.fx_px = K.at<double>(0, 0);
  in.fy_px = K.at<double>(1, 1);
  in.cx_px = K.at<double>(0, 2);
  in.cy_px = K.at<double>(1, 2);
  in.skew = K.at<double>(0, 1);
  in.distortion.assign(dist.begin<double>(), dist.end<double>());
  in.rms_px = rms_px;
  in.views = static_cast<int>(img.size());
  return result;
}

}  // namespace fettle::vision::calibration
