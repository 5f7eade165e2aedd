// Intrinsics (Zhang's method) from chessboard images rendered through a known camera.
#include <array>
#include <cmath>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "fettle/vision/calibration/board.hpp"
#include "synthetic.hpp"

using namespace fettle;                       // NOLINT
using namespace fettle::vision::calibration;  // NOLINT

namespace {

const BoardSpec kBoard{9, 6, 20.0};

struct ViewSpec {
  double distance, dx, dy, tilt_x_deg, tilt_y_deg, spin_deg;
};

// Tilted views covering the image, as docs/calibration.md asks an integrator for.
const std::vector<ViewSpec> kViews = {
    {420, 0, 0, 0, 0, 0},        {450, -90, -60, 25, -20, 5},  {450, 90, -60, 20, 25, -5},
    {450, -90, 60, -25, -20, 10}, {450, 90, 60, -20, 25, -10}, {500, 0, 0, 35, 0, 0},
    {500, 0, 0, 0, -35, 0},      {380, -40, 20, 15, 15, 30},   {550, 60, -30, -30, 10, -20},
    {480, -110, 0, 0, 30, 3},    {480, 110, 0, 0, -30, -3},    {520, 0, -40, 25, 0, 20},
};

std::vector<GrayImage> render_views(const config::CameraIntrinsics& cam, std::size_t count) {
  std::vector<GrayImage> images;
  for (std::size_t i = 0; i < count; ++i) {
    const auto& v = kViews[i];
    const Transform T = test::board_pose_facing_camera(kBoard, v.distance, v.dx, v.dy, deg_to_rad(v.tilt_x_deg),
                                                       deg_to_rad(v.tilt_y_deg), deg_to_rad(v.spin_deg));
    images.push_back(test::to_gray_image(test::render_board(kBoard, cam, T, 0.0, 1.0, static_cast<unsigned>(i + 1)),
                                         "view" + std::to_string(i + 1) + ".png"));
  }
  return images;
}

}  // namespace

TEST(Board, ParseBoardChecksItsInput) {
  const auto b = parse_board("9x6", 25.0);
  EXPECT_EQ(b.cols, 9);
  EXPECT_EQ(b.rows, 6);
  EXPECT_THROW(parse_board("9*6", 25.0), UserError);
  EXPECT_THROW(parse_board("9x6x", 25.0), UserError);
  EXPECT_THROW(parse_board("7x7", 25.0), UserError);
  EXPECT_THROW(parse_board("9x6", 0.0), UserError);
}

TEST(Board, DetectsCornersAndThePoseOfARenderedBoard) {
  const auto cam = test::test_camera();
  const Transform T = test::board_pose_facing_camera(kBoard, 450, 30, -20, deg_to_rad(20), deg_to_rad(-15), 0.3);
  const auto img = test::to_gray_image(test::render_board(kBoard, cam, T), "v");
  const auto obs = detect_board(img, kBoard);
  ASSERT_TRUE(obs.ok()) << obs.error().message;
  EXPECT_EQ(obs->corners_px.size(), 54u);
  EXPECT_LT(obs->edge_width_px, 4.0);
  const auto pose = board_pose(*obs, kBoard, cam);
  ASSERT_TRUE(pose.ok()) << pose.error().message;
  EXPECT_LT(test::translation_error_mm(pose->T_camera_board, T), 0.5);
  EXPECT_LT(test::rotation_error_deg(pose->T_camera_board, T), 0.1);
  EXPECT_LT(pose->rms_px, 0.2);
}

TEST(Intrinsics, RecoversTheCameraAndSkipsBlurredAndPartialViews) {
  const auto cam = test::test_camera();
  auto images = render_views(cam, kViews.size());
  // View 4 is out of focus; view 9 shows the board half outside the image.
  {
    const auto& v = kViews[3];
    const Transform T = test::board_pose_facing_camera(kBoard, v.distance, v.dx, v.dy, deg_to_rad(v.tilt_x_deg),
                                                       deg_to_rad(v.tilt_y_deg), deg_to_rad(v.spin_deg));
    images[3] = test::to_gray_image(test::render_board(kBoard, cam, T, /*blur_sigma_px=*/3.0), "blurred.png");
    const Transform P = test::board_pose_facing_camera(kBoard, 450, 330, 0, 0, 0, 0);
    images[8] = test::to_gray_image(test::render_board(kBoard, cam, P), "partial.png");
  }
  const auto r = calibrate_intrinsics(images, kBoard);
  ASSERT_TRUE(r.ok()) << r.error().message;
  const auto& k = r->intrinsics;
  EXPECT_EQ(k.views, 10);
  EXPECT_NEAR(k.fx_px, cam.fx_px, 0.003 * cam.fx_px);
  EXPECT_NEAR(k.fy_px, cam.fy_px, 0.003 * cam.fy_px);
  EXPECT_NEAR(k.cx_px, cam.cx_px, 3.0);
  EXPECT_NEAR(k.cy_px, cam.cy_px, 3.0);
  ASSERT_GE(k.distortion.size(), 4u);
  EXPECT_NEAR(k.distortion[0], cam.distortion[0], 0.02);
  EXPECT_NEAR(k.distortion[1], cam.distortion[1], 0.06);
  EXPECT_LT(k.rms_px, 0.3);
  EXPECT_EQ(k.width_px, 1032);
  EXPECT_EQ(k.height_px, 772);
  ASSERT_EQ(r->views.size(), images.size());
  EXPECT_FALSE(r->views[3].used);
  EXPECT_NE(r->views[3].skip_reason.find("blur"), std::string::npos) << r->views[3].skip_reason;
  EXPECT_FALSE(r->views[8].used);
  EXPECT_NE(r->views[8].skip_reason.find("outside"), std::string::npos) << r->views[8].skip_reason;
  for (std::size_t i = 0; i < r->views.size(); ++i) {
    if (i == 3 || i == 8) continue;
    EXPECT_TRUE(r->views[i].used) << r->views[i].name << ": " << r->views[i].skip_reason;
    EXPECT_GT(r->views[i].rms_px, 0.0);
    EXPECT_LT(r->views[i].rms_px, 0.5);
  }
}

TEST(Intrinsics, TooFewUsableViewsIsAnErrorThatListsTheReasons) {
  const auto cam = test::test_camera();
  auto images = render_views(cam, 4);
  images.push_back(test::to_gray_image(cv::Mat(772, 1032, CV_8UC1, cv::Scalar(128)), "grey.png"));
  const auto r = calibrate_intrinsics(images, kBoard);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "calibration.too_few_views");
  EXPECT_NE(r.error().message.find("only 4 of 5"), std::string::npos) << r.error().message;
  EXPECT_NE(r.error().message.find("grey.png"), std::string::npos) << r.error().message;
}

TEST(Intrinsics, ImagesOfDifferentSizesAreAnError) {
  const auto cam = test::test_camera();
  auto images = render_views(cam, 5);
  images.push_back(test::to_gray_image(cv::Mat(100, 100, CV_8UC1, cv::Scalar(128)), "small.png"));
  const auto r = calibrate_intrinsics(images, kBoard);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "calibration.image_size");
}

// --- ChArUco ---------------------------------------------------------------------------

namespace {

// 7 x 5 squares of 30 mm, 22 mm DICT_5X5_100 markers: 6 x 4 = 24 inner corners.
BoardSpec charuco_board() { return parse_charuco_board("7x5", 30.0, 22.0, "DICT_5X5_100"); }

/// A ChArUco pose facing the camera: the board centre at (dx, dy, distance), tilted (deg).
Transform charuco_pose(const BoardSpec& b, double distance, double dx, double dy, double tilt_x, double tilt_y,
                       double spin) {
  // board_pose_facing_camera turns about the centre of an inner-corner grid; a grid of
  // cols+1 x rows+1 corners has the ChArUco board's centre.
  return test::board_pose_facing_camera(BoardSpec{b.cols + 1, b.rows + 1, b.square_mm}, distance, dx, dy,
                                        deg_to_rad(tilt_x), deg_to_rad(tilt_y), deg_to_rad(spin));
}

}  // namespace

TEST(Charuco, ParseChecksItsInput) {
  const auto b = charuco_board();
  EXPECT_EQ(b.type, BoardType::charuco);
  EXPECT_EQ(board_points_mm(b).size(), 24u);
  EXPECT_NO_THROW(parse_charuco_board("5x5", 30.0, 22.0, "DICT_4X4_50"));  // square boards are fine: markers orient them
  EXPECT_THROW(parse_charuco_board("7x5", 30.0, 30.0, "DICT_5X5_100"), UserError);   // marker not smaller
  EXPECT_THROW(parse_charuco_board("7x5", 30.0, 22.0, "DICT_5X5_999"), UserError);   // unknown dictionary
  EXPECT_THROW(parse_charuco_board("20x20", 30.0, 22.0, "DICT_4X4_50"), UserError);  // 200 markers > 50
  EXPECT_THROW(parse_charuco_board("7-5", 30.0, 22.0, "DICT_5X5_100"), UserError);
}

TEST(Charuco, DrawnBoardIsDetectedWhereItsMappingSays) {
  const auto b = charuco_board();
  const auto drawn = draw_board(b, 80, 40);
  const auto obs = detect_board(drawn.image, b);
  ASSERT_TRUE(obs.ok()) << obs.error().message;
  ASSERT_EQ(obs->ids.size(), 24u);
  const auto pts = observed_points_mm(b, *obs);
  for (std::size_t i = 0; i < pts.size(); ++i) {
    const Eigen::Vector2d want = drawn.board_to_px * Eigen::Vector3d(pts[i].x(), pts[i].y(), 1.0);
    // A drawn board has ideal step edges, on which corner refinement lands up to ~0.8 px off;
    // a wrong mapping is off by whole squares (80 px).
    EXPECT_LT((obs->corners_px[i] - want).norm(), 1.0) << "corner id " << obs->ids[i];
  }
}

TEST(Charuco, PoseOfARenderedPartialView) {
  const auto cam = test::test_camera();
  const auto b = charuco_board();
  const auto drawn = draw_board(b, 60, 60);
  // Half the board is outside the image: a chessboard would be lost, ChArUco keeps the rest.
  const Transform T = charuco_pose(b, 450, 190, 40, 15, -10, 8);
  const auto img = test::to_gray_image(test::render_board_image(drawn, cam, T), "partial");
  const auto obs = detect_board(img, b);
  ASSERT_TRUE(obs.ok()) << obs.error().message;
  EXPECT_GE(obs->ids.size(), 8u);
  EXPECT_LT(obs->ids.size(), 24u);
  const auto pose = board_pose(*obs, b, cam);
  ASSERT_TRUE(pose.ok()) << pose.error().message;
  EXPECT_LT(test::translation_error_mm(pose->T_camera_board, T), 1.0);
  EXPECT_LT(test::rotation_error_deg(pose->T_camera_board, T), 0.2);
  EXPECT_LT(pose->rms_px, 0.3);
}

TEST(Charuco, IntrinsicsFromRenderedViewsIncludingPartialOnes) {
  const auto cam = test::test_camera();
  const auto b = charuco_board();
  const auto drawn = draw_board(b, 60, 60);
  // Tilted views over the image; views 3, 6 and 9 push the board partly out of the image (its
  // corners and edges are where the distortion is largest, and where ChArUco still sees).
  const std::vector<std::array<double, 6>> views = {
      {480, 0, 0, 0, 0, 0},        {500, -120, -80, 25, -20, 5},  {460, 150, -70, 20, 25, -5},
      {500, -120, 80, -25, -20, 10}, {500, 120, 80, -20, 25, -10}, {470, -160, 80, 10, 20, 0},
      {560, 0, 0, 35, 0, 0},       {560, 0, 0, 0, -35, 0},       {450, 180, 120, -15, -15, 30},
      {430, -60, 30, 15, 15, 30},  {540, 80, -40, -30, 10, -20}, {520, 0, -60, 25, 0, 20}};
  std::vector<GrayImage> images;
  for (std::size_t i = 0; i < views.size(); ++i) {
    const auto& v = views[i];
    images.push_back(test::to_gray_image(
        test::render_board_image(drawn, cam, charuco_pose(b, v[0], v[1], v[2], v[3], v[4], v[5]), 0.0, 1.0,
                                 static_cast<unsigned>(i + 1)),
        "charuco" + std::to_string(i + 1) + ".png"));
  }
  // One view without the board at all.
  images.push_back(test::to_gray_image(cv::Mat(772, 1032, CV_8UC1, cv::Scalar(128)), "empty.png"));
  const auto r = calibrate_intrinsics(images, b);
  ASSERT_TRUE(r.ok()) << r.error().message;
  const auto& k = r->intrinsics;
  EXPECT_EQ(k.views, 12);
  EXPECT_NEAR(k.fx_px, cam.fx_px, 0.005 * cam.fx_px);
  EXPECT_NEAR(k.fy_px, cam.fy_px, 0.005 * cam.fy_px);
  EXPECT_NEAR(k.cx_px, cam.cx_px, 4.0);
  EXPECT_NEAR(k.cy_px, cam.cy_px, 4.0);
  ASSERT_GE(k.distortion.size(), 4u);
  EXPECT_NEAR(k.distortion[0], cam.distortion[0], 0.03);
  EXPECT_LT(k.rms_px, 0.3);
  for (const std::size_t partial : {2u, 5u, 8u}) EXPECT_TRUE(r->views[partial].used) << r->views[partial].skip_reason;
  EXPECT_FALSE(r->views.back().used);
  EXPECT_NE(r->views.back().skip_reason.find("ChArUco corners"), std::string::npos) << r->views.back().skip_reason;
}
