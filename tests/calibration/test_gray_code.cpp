// Gray-code camera-projector calibration on rendered images: pattern generation, per-pixel
// decode, projector coordinates of board corners (local homographies) and the stereo
// calibration they feed, against a known camera, projector and T_camera_projector.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include "fettle/vision/calibration/gray_code.hpp"
#include "fettle/vision/calibration/stereo.hpp"
#include "synthetic.hpp"

using namespace fettle;                       // NOLINT
using namespace fettle::vision::calibration;  // NOLINT

namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace

TEST(GrayCode, PatternsComeInTheDocumentedOrderAndDecodeThemselves) {
  const auto layout = GrayCodeLayout::for_projector(1280, 800);
  EXPECT_EQ(layout.column_bits, 11);
  EXPECT_EQ(layout.row_bits, 10);
  ASSERT_EQ(layout.image_count(), 44u);
  const auto names = layout.names();
  EXPECT_EQ(names[0], "white");
  EXPECT_EQ(names[1], "black");
  EXPECT_EQ(names[2], "col_00");
  EXPECT_EQ(names[3], "col_00_inv");
  EXPECT_EQ(names[24], "row_00");
  EXPECT_EQ(names[43], "row_09_inv");
  const auto patterns = gray_code_patterns(layout);
  ASSERT_EQ(patterns.size(), 44u);
  // Neighbouring columns differ in exactly one pattern (the Gray code's point: a camera pixel
  // on a stripe edge is off by at most one column).
  for (int c = 0; c + 1 < 1280; c += 37) {
    int differ = 0;
    for (std::size_t k = 2; k < 24; k += 2)
      differ += patterns[k].pixels[static_cast<std::size_t>(c)] != patterns[k].pixels[static_cast<std::size_t>(c) + 1];
    EXPECT_EQ(differ, 1) << "columns " << c << ", " << c + 1;
  }
  // A camera that sees the projector's image pixel for pixel decodes every pixel to itself.
  const auto map = decode_gray_code(patterns, layout);
  ASSERT_TRUE(map.ok()) << map.error().message;
  ASSERT_EQ(map->valid_pixels, 1280u * 800u);
  for (int v = 0; v < 800; v += 7)
    for (int u = 0; u < 1280; u += 3) {
      ASSERT_EQ(map->column[map->index(u, v)], u);
      ASSERT_EQ(map->row[map->index(u, v)], v);
    }
}

// Noise-free plane, each pixel sampled at its centre, no blur: every camera pixel that sees
// the lit board decodes to exactly the projector pixel lighting its centre (black squares
// included), and every other pixel (beyond the board, on the board outside the projected
// image) is invalid.
TEST(GrayCode, DecodeIsExactOnANoiseFreePlane) {
  auto s = test::structured_light_scene();
  s.supersample = 1;
  s.T_camera_board = test::board_pose_facing_camera(s.board, 520, 40, -20, deg_to_rad(15), deg_to_rad(-20), 0.2);
  const auto layout = GrayCodeLayout::for_projector(s.projector.width_px, s.projector.height_px);
  const auto r = test::render_structured_light(s, layout);
  const auto map = decode_gray_code(r.images, layout);
  ASSERT_TRUE(map.ok()) << map.error().message;
  std::size_t lit = 0, wrong = 0, missed = 0, spurious = 0;
  for (int v = 0; v < map->height_px; ++v)
    for (int u = 0; u < map->width_px; ++u) {
      const int tc = r.true_column.at<std::int32_t>(v, u), tr = r.true_row.at<std::int32_t>(v, u);
      const std::size_t i = map->index(u, v);
      if (!r.lit.at<std::uint8_t>(v, u)) {
        spurious += map->column[i] >= 0;
        continue;
      }
      ++lit;
      if (map->column[i] < 0)
        ++missed;
      else if (map->column[i] != tc || map->row[i] != tr)
        ++wrong;
    }
  std::printf("noise-free plane: %zu lit pixels, %zu valid, %zu wrong, %zu missed, %zu spurious\n", lit,
              map->valid_pixels, wrong, missed, spurious);
  EXPECT_GT(lit, 100000u);
  EXPECT_EQ(wrong, 0u);
  EXPECT_EQ(missed, 0u);
  EXPECT_EQ(spurious, 0u);
}

// A shadow (an object between projector and board) and a dark stain: their pixels are reported
// invalid; no valid pixel anywhere (blur, noise, black squares, stripe edges) decodes to a
// projector pixel more than 2 away from the one lighting its centre.
TEST(GrayCode, ShadowedAndLowContrastPixelsAreInvalidNotWrong) {
  auto s = test::structured_light_scene();
  s.blur_sigma_px = 0.8;
  s.noise_grey = 1.5;
  s.T_camera_board = test::board_pose_facing_camera(s.board, 520, 40, -20, deg_to_rad(-10), deg_to_rad(20), -0.3);
  s.shadow_centre_mm = Eigen::Vector2d(40.0, 40.0);
  s.shadow_radius_mm = 25.0;
  s.stain_centre_mm = Eigen::Vector2d(130.0, 70.0);
  s.stain_radius_mm = 15.0;
  const auto layout = GrayCodeLayout::for_projector(s.projector.width_px, s.projector.height_px);
  const auto r = test::render_structured_light(s, layout);
  const auto map = decode_gray_code(r.images, layout);
  ASSERT_TRUE(map.ok()) << map.error().message;
  // The shadow and stain without their 3-pixel rim (blur mixes the rim with its surroundings).
  cv::Mat inside;
  cv::erode(r.shadow_or_stain, inside, cv::Mat::ones(7, 7, CV_8UC1));
  std::size_t inside_n = 0, inside_valid = 0, valid = 0, within1 = 0, wrong = 0, lit = 0;
  std::vector<std::size_t> histogram(6, 0);  // valid pixels by error 0, 1, 2, 3, 4, more (projector px)
  for (int v = 0; v < map->height_px; ++v)
    for (int u = 0; u < map->width_px; ++u) {
      const std::size_t i = map->index(u, v);
      const int tc = r.true_column.at<std::int32_t>(v, u), tr = r.true_row.at<std::int32_t>(v, u);
      lit += r.lit.at<std::uint8_t>(v, u) != 0;
      if (inside.at<std::uint8_t>(v, u)) {
        ++inside_n;
        inside_valid += map->column[i] >= 0;
      }
      if (map->column[i] < 0) continue;
      ++valid;
      const int e = std::max(std::abs(map->column[i] - tc), std::abs(map->row[i] - tr));
      ++histogram[static_cast<std::size_t>(std::min(e, 5))];
      if (e <= 1) ++within1;
      if (e > 2) ++wrong;
    }
  std::printf(
      "shadow + stain, blur 0.8 px, noise 1.5 grey: %zu lit pixels, %zu valid (%zu within 1 px), %zu wrong; "
      "%zu inside shadow/stain, %zu of them valid; invalid: %zu low contrast, %zu undecided\n",
      lit, valid, within1, wrong, inside_n, inside_valid, map->low_contrast_pixels, map->undecided_pixels);
  std::printf("valid pixels by error 0/1/2/3/4/more px: %zu %zu %zu %zu %zu %zu\n", histogram[0], histogram[1],
              histogram[2], histogram[3], histogram[4], histogram[5]);
  EXPECT_GT(inside_n, 2000u);
  EXPECT_EQ(inside_valid, 0u);
  EXPECT_EQ(wrong, 0u);
  EXPECT_GT(static_cast<double>(valid), 0.5 * static_cast<double>(lit));
  EXPECT_GT(static_cast<double>(within1), 0.99 * static_cast<double>(valid));
}

// The whole chain on rendered images: 8 board poses, each 44 camera images of the board under
// the patterns (area-sampled 3x3 per pixel, blurred 0.8 px, noise 1.5 grey) -> board corners in
// the white image, projector coordinates by local homographies -> stereo calibration with the
// known intrinsics.
//
// Tolerance 0.2 mm and 0.02 deg, about twice the worst of pose sets 1-8 (measured: 0.008-0.088 mm,
// 0.0006-0.0086 deg; this one, set 7: 0.024 mm, 0.0010 deg). Why that size: a corner's projector
// coordinates from the ~1000 decoded pixels around it (each quantised to a whole projector pixel,
// sigma 0.29 px) are good to 0.02 px when the camera corner is exact (checked < 0.05 px); the
// error that remains is the camera corner's (0.07-0.09 px RMS from cornerSubPix on these images),
// carried into projector pixels by the local homography (x 1.17 = 1400 / 1200 px focal lengths):
// 0.08-0.11 px RMS on both sides. At 500 mm, 0.1 px is ~0.04 mm on the board; with 432 corners
// over 8 poses, the 180 mm baseline's depth-translation coupling leaves a few hundredths of a
// millimetre, up to 0.09 mm for a less favourable pose set. A decode that is off by one
// projector pixel at the corners (e.g. a half-pixel convention error) moves the corners 0.5-1 px
// and fails the corner check and, through it, the tolerance.
TEST(CameraProjector, RecoversKnownExtrinsicsFromRenderedGrayCodes) {
  auto s = test::structured_light_scene();
  s.blur_sigma_px = 0.8;
  s.noise_grey = 1.5;
  const auto layout = GrayCodeLayout::for_projector(s.projector.width_px, s.projector.height_px);
  const std::uint64_t pose_seed = 7;
  const auto poses = test::structured_light_board_poses(s, 8, pose_seed);
  ASSERT_EQ(poses.size(), 8u);
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<StereoView> views;
  double sum2 = 0.0, cam2 = 0.0, decode2 = 0.0;
  std::size_t n = 0;
  const Transform T_projector_camera = s.T_camera_projector.inverse();
  for (std::size_t i = 0; i < poses.size(); ++i) {
    s.T_camera_board = poses[i];
    s.seed = static_cast<unsigned>(i + 1 + 100 * pose_seed);
    const auto r = test::render_structured_light(s, layout);
    const auto v = decode_stereo_view(r.images, s.board, layout);
    ASSERT_TRUE(v.ok()) << "pose " << i + 1 << ": " << v.error().message;
    EXPECT_EQ(v->corners_decoded, v->corners_total) << "pose " << i + 1;
    // The decode's own error: projector coordinates from the true camera corners.
    std::vector<Eigen::Vector2d> true_camera_px;
    for (const auto& b : v->view.board_points_mm) true_camera_px.push_back(test::project_point(s.camera, poses[i] * b));
    const auto from_truth = projector_corners(v->map, true_camera_px);
    for (std::size_t k = 0; k < v->view.projector_px.size(); ++k) {
      const Vec3 p = poses[i] * v->view.board_points_mm[k];
      const Eigen::Vector2d truth = test::project_point(s.projector, T_projector_camera * p);
      sum2 += (v->view.projector_px[k] - truth).squaredNorm();
      cam2 += (v->view.camera_px[k] - true_camera_px[k]).squaredNorm();
      ASSERT_TRUE(from_truth.found[k]);
      decode2 += (from_truth.projector_px[k] - truth).squaredNorm();
      ++n;
    }
    views.push_back(v->view);
  }
  const double corner_rms_px = std::sqrt(sum2 / static_cast<double>(n));
  const double camera_rms_px = std::sqrt(cam2 / static_cast<double>(n));
  const double decode_rms_px = std::sqrt(decode2 / static_cast<double>(n));
  const auto r = calibrate_camera_projector(views, s.camera, s.projector);
  ASSERT_TRUE(r.ok()) << r.error().message;
  const double t_mm = test::translation_error_mm(r->T_camera_projector, s.T_camera_projector);
  const double r_deg = test::rotation_error_deg(r->T_camera_projector, s.T_camera_projector);
  std::printf(
      "8 rendered poses (%.1f s): projector corners RMS %.4f px (from the true camera corners %.4f px), "
      "camera corners RMS %.4f px, %zu corners; stereo RMS %.3f px; T_camera_projector error %.3f mm, "
      "%.4f deg\n",
      seconds_since(t0), corner_rms_px, decode_rms_px, camera_rms_px, n, r->rms_px, t_mm, r_deg);
  RecordProperty("projector_corner_rms_px", std::to_string(corner_rms_px));
  RecordProperty("error_mm", std::to_string(t_mm));
  RecordProperty("error_deg", std::to_string(r_deg));
  EXPECT_LT(decode_rms_px, 0.05);
  EXPECT_LT(corner_rms_px, 0.15);
  EXPECT_LT(t_mm, 0.2);
  EXPECT_LT(r_deg, 0.02);
  EXPECT_LT(r->rms_px, 0.15);

  // The operator's route (`fettle calibrate projector`): the projector's intrinsics unknown,
  // estimated from the same views as an inverse camera, then the stereo calibration with them.
  // Pose sets 1-4 and 7: fx within 1.3 px, principal point within 4.1 px, T_camera_projector
  // within 0.14-0.40 mm and 0.02-0.16 deg (an error in the principal point tilts the projector's
  // frame); tolerances 3 px, 8 px, 1 mm, 0.3 deg.
  const auto kp = calibrate_projector_intrinsics(views, s.projector.width_px, s.projector.height_px);
  ASSERT_TRUE(kp.ok()) << kp.error().message;
  const auto r2 = calibrate_camera_projector(views, s.camera, *kp);
  ASSERT_TRUE(r2.ok()) << r2.error().message;
  const double t2_mm = test::translation_error_mm(r2->T_camera_projector, s.T_camera_projector);
  const double r2_deg = test::rotation_error_deg(r2->T_camera_projector, s.T_camera_projector);
  std::printf(
      "projector intrinsics from the views: fx %.2f fy %.2f cx %.2f cy %.2f px (true 1400 1400 640 560), "
      "rms %.3f px; T_camera_projector error %.3f mm, %.4f deg\n",
      kp->fx_px, kp->fy_px, kp->cx_px, kp->cy_px, kp->rms_px, t2_mm, r2_deg);
  EXPECT_NEAR(kp->fx_px, s.projector.fx_px, 3.0);
  EXPECT_NEAR(kp->cx_px, s.projector.cx_px, 8.0);
  EXPECT_NEAR(kp->cy_px, s.projector.cy_px, 8.0);
  EXPECT_LT(t2_mm, 1.0);
  EXPECT_LT(r2_deg, 0.3);
}

TEST(GrayCode, MissingOrMisSizedImagesAreErrorsNamingTheImage) {
  const auto layout = GrayCodeLayout::for_projector(64, 32);
  auto images = gray_code_patterns(layout);
  ASSERT_EQ(images.size(), 2u + 2u * (6u + 5u));
  auto missing = images;
  missing.pop_back();
  auto r = decode_gray_code(missing, layout);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "calibration.pattern_count");
  EXPECT_NE(r.error().message.find("needs 24 images"), std::string::npos) << r.error().message;
  images[5].width_px = 32;
  images[5].pixels.resize(32 * 32);
  r = decode_gray_code(images, layout);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "calibration.image_size");
  EXPECT_NE(r.error().message.find("col_01_inv: 32x32 px"), std::string::npos) << r.error().message;
}

// A projector too dim for the room light (or the exposure set for the room): the board is
// found in the white image, but no corner has decoded pixels around it. An error that says how
// many corners were decoded and why, not a calibration from a handful of corners.
TEST(GrayCode, TooFewDecodedCornersIsAnError) {
  auto s = test::structured_light_scene();
  s.supersample = 1;
  s.T_camera_board = test::board_pose_facing_camera(s.board, 520, 40, -20, deg_to_rad(10), deg_to_rad(-10), 0.1);
  s.ambient_grey = 150.0;
  s.projector_grey = 14.0;  // white - black: 12.6 grey on the white squares, below the 15 needed
  const auto layout = GrayCodeLayout::for_projector(s.projector.width_px, s.projector.height_px);
  const auto r = test::render_structured_light(s, layout);
  const auto v = decode_stereo_view(r.images, s.board, layout);
  ASSERT_FALSE(v.ok());
  EXPECT_EQ(v.error().code, "calibration.too_few_corners");
  EXPECT_NE(v.error().message.find("white: only 0 of 54 board corners"), std::string::npos) << v.error().message;
  EXPECT_NE(v.error().message.find("too little contrast"), std::string::npos) << v.error().message;
  // The same scene with the projector at full power decodes every corner.
  s.projector_grey = 220.0;
  s.ambient_grey = 12.0;
  const auto ok = decode_stereo_view(test::render_structured_light(s, layout).images, s.board, layout);
  ASSERT_TRUE(ok.ok()) << ok.error().message;
  EXPECT_EQ(ok->corners_decoded, 54u);
}
