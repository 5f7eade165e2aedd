// Camera-projector extrinsics on synthetic correspondences with a known R, T.
#include <random>

#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>

#include "fettle/vision/calibration/stereo.hpp"
#include "synthetic.hpp"
#include "../support/draws.hpp"

using namespace fettle;                       // NOLINT
using namespace fettle::vision::calibration;  // NOLINT

namespace {

std::vector<Eigen::Vector2d> project(const std::vector<Eigen::Vector3d>& pts_cam, const config::CameraIntrinsics& k,
                                     std::mt19937_64& rng, double noise_px) {
  std::vector<cv::Point3d> p;
  for (const auto& q : pts_cam) p.emplace_back(q.x(), q.y(), q.z());
  const cv::Mat K = (cv::Mat_<double>(3, 3) << k.fx_px, 0, k.cx_px, 0, k.fy_px, k.cy_px, 0, 0, 1);
  std::vector<cv::Point2d> px;
  cv::projectPoints(p, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K, cv::Mat(k.distortion, true), px);
  std::normal_distribution<double> n(0.0, noise_px);
  std::vector<Eigen::Vector2d> out;
  for (const auto& q : px) {
    const auto e = fettle::test::draws<2>(n, rng);
    out.emplace_back(q.x + e[0], q.y + e[1]);
  }
  return out;
}

config::CameraIntrinsics test_projector() {
  config::CameraIntrinsics k;
  k.width_px = 1280;
  k.height_px = 800;
  k.fx_px = 1500.0;
  k.fy_px = 1500.0;
  k.cx_px = 640.0;
  k.cy_px = 760.0;  // projectors usually project upwards: principal point near the bottom
  k.distortion = {0.02, 0.0, 0.0, 0.0, 0.0};
  return k;
}

struct Setup {
  Transform T_camera_projector;
  std::vector<StereoView> views;
};

Setup make(double noise_px, std::uint64_t seed) {
  Setup s;
  // The projector sits 180 mm to the side of the camera, toed in by 12 deg.
  s.T_camera_projector = Transform::Identity();
  s.T_camera_projector.linear() =
      (Eigen::AngleAxisd(deg_to_rad(-12.0), Vec3::UnitY()) * Eigen::AngleAxisd(deg_to_rad(1.0), Vec3::UnitX()))
          .toRotationMatrix();
  s.T_camera_projector.translation() = Vec3(180.0, 5.0, 10.0);
  const vision::calibration::BoardSpec board{9, 6, 20.0};
  const auto pts = board_points_mm(board);
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int i = 0; i < 8; ++i) {
    const auto a = fettle::test::draws<6>(u, rng);
    const Transform T_camera_board =
        test::board_pose_facing_camera(board, 500 + 50 * a[0], 60 + 60 * a[1], 60 * a[2], deg_to_rad(25 * a[3]),
                                       deg_to_rad(25 * a[4]), deg_to_rad(30 * a[5]));
    std::vector<Eigen::Vector3d> in_cam, in_proj;
    for (const auto& p : pts) {
      in_cam.push_back(T_camera_board * p);
      in_proj.push_back(s.T_camera_projector.inverse() * in_cam.back());
    }
    StereoView v;
    v.board_points_mm = pts;
    v.camera_px = project(in_cam, test::test_camera(), rng, noise_px);
    v.projector_px = project(in_proj, test_projector(), rng, noise_px);
    s.views.push_back(v);
  }
  return s;
}

}  // namespace

TEST(CameraProjector, RecoversKnownExtrinsicsWithFixedIntrinsics) {
  const auto s = make(0.05, 1);
  const auto r = calibrate_camera_projector(s.views, test::test_camera(), test_projector());
  ASSERT_TRUE(r.ok()) << r.error().message;
  EXPECT_LT(test::translation_error_mm(r->T_camera_projector, s.T_camera_projector), 0.2);
  EXPECT_LT(test::rotation_error_deg(r->T_camera_projector, s.T_camera_projector), 0.02);
  EXPECT_LT(r->rms_px, 0.1);
  EXPECT_GT(r->rms_px, 0.01);
}

TEST(CameraProjector, RefinesIntrinsicsFromAnInitialGuess) {
  const auto s = make(0.05, 2);
  auto guess = test_projector();
  guess.fx_px *= 1.03;
  guess.fy_px *= 1.03;
  guess.cx_px += 15.0;
  StereoOptions o;
  o.fix_intrinsics = false;
  const auto r = calibrate_camera_projector(s.views, test::test_camera(), guess, o);
  ASSERT_TRUE(r.ok()) << r.error().message;
  EXPECT_NEAR(r->projector.fx_px, 1500.0, 5.0);
  EXPECT_LT(test::translation_error_mm(r->T_camera_projector, s.T_camera_projector), 1.0);
  EXPECT_LT(test::rotation_error_deg(r->T_camera_projector, s.T_camera_projector), 0.1);
}

TEST(CameraProjector, TooFewOrInconsistentViewsAreErrors) {
  auto s = make(0.0, 3);
  std::vector<StereoView> two(s.views.begin(), s.views.begin() + 2);
  auto r = calibrate_camera_projector(two, test::test_camera(), test_projector());
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "calibration.too_few_views");
  s.views[1].projector_px.pop_back();
  r = calibrate_camera_projector(s.views, test::test_camera(), test_projector());
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "calibration.bad_views");
}
