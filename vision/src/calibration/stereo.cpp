// Camera-projector extrinsics by stereo calibration (paper Eqs. 4-6).
#include "fettle/vision/calibration/stereo.hpp"

#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

namespace fettle::vision::calibration {

namespace {

cv::Mat camera_matrix(const config::CameraIntrinsics& k) {
  return (cv::Mat_<double>(3, 3) << k.fx_px, k.skew, k.cx_px, 0.0, k.fy_px, k.cy_px, 0.0, 0.0, 1.0);
}

cv::Mat distortion(const config::CameraIntrinsics& k) {
  std::vector<double> d = k.distortion;
  if (d.empty()) d.assign(5, 0.0);
  return cv::Mat(d, true);
}

void store(const cv::Mat& K, const cv::Mat& dist, config::CameraIntrinsics& k) {
  k.fx_px = K.at<double>(0, 0);
  k.fy_px = K.at<double>(1, 1);
  k.cx_px = K.at<double>(0, 2);
  k.cy_px = K.at<double>(1, 2);
  k.skew = K.at<double>(0, 1);
  k.distortion.assign(dist.begin<double>(), dist.end<double>());
}

}  // namespace

Result<config::CameraIntrinsics> calibrate_projector_intrinsics(const std::vector<StereoView>& views, int width_px,
                                                                int height_px) {
  if (views.size() < 3)
    return Error{"calibration.too_few_views", "projector intrinsics need at least 3 board poses, got " +
                                                  std::to_string(views.size()) +
                                                  "; record the board at several tilted poses"};
  std::vector<std::vector<cv::Point3f>> obj;
  std::vector<std::vector<cv::Point2f>> proj;
  for (std::size_t i = 0; i < views.size(); ++i) {
    const auto& v = views[i];
    if (v.board_points_mm.size() < 6 || v.projector_px.size() != v.board_points_mm.size())
      return Error{"calibration.bad_views", "view " + std::to_string(i + 1) +
                                                ": needs 6 or more board points with one projector pixel each (got " +
                                                std::to_string(v.board_points_mm.size()) + ", " +
                                                std::to_string(v.projector_px.size()) + ")"};
    obj.emplace_back();
    proj.emplace_back();
    for (std::size_t k = 0; k < v.board_points_mm.size(); ++k) {
      const auto& p = v.board_points_mm[k];
      obj.back().emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()), static_cast<float>(p.z()));
      proj.back().emplace_back(static_cast<float>(v.projector_px[k].x()), static_cast<float>(v.projector_px[k].y()));
    }
  }
  cv::Mat K, dist;
  std::vector<cv::Mat> rvecs, tvecs;
  const double rms =
      cv::calibrateCamera(obj, proj, cv::Size(width_px, height_px), K, dist, rvecs, tvecs, cv::CALIB_FIX_K3,
                          cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 100, 1e-12));
  config::CameraIntrinsics k;
  k.width_px = width_px;
  k.height_px = height_px;
  store(K, dist, k);
  k.rms_px = rms;
  k.views = static_cast<int>(views.size());
  return k;
}

Result<StereoResult> calibrate_camera_projector(const std::vector<StereoView>& views,
                                                const config::CameraIntrinsics& camera,
                                                const config::CameraIntrinsics& projector, const StereoOptions& o) {
  if (views.size() < o.min_views)
    return Error{"calibration.too_few_views",
                 "camera-projector calibration needs at least " + std::to_string(o.min_views) + " board poses, got " +
                     std::to_string(views.size()) + "; record the board at several tilted poses"};
  std::vector<std::vector<cv::Point3f>> obj;
  std::vector<std::vector<cv::Point2f>> cam, proj;
  for (std::size_t i = 0; i < views.size(); ++i) {
    const auto& v = views[i];
    if (v.board_points_mm.size() < 6 || v.camera_px.size() != v.board_points_mm.size() ||
        v.projector_px.size() != v.board_points_mm.size())
      return Error{"calibration.bad_views", "view " + std::to_string(i + 1) +
                                                ": needs 6 or more board points with "
                                                "one camera and one projector pixel "
                                                "each (got " +
                                                std::to_string(v.board_points_mm.size()) + ", " +
                                                std::to_string(v.camera_px.size()) + ", " +
                                                std::to_string(v.projector_px.size()) + ")"};
    std::vector<cv::Point3f> o3;
    std::vector<cv::Point2f> c2, p2;
    for (std::size_t k = 0; k < v.board_points_mm.size(); ++k) {
      const auto& p = v.board_points_mm[k];
      o3.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()), static_cast<float>(p.z()));
      c2.emplace_back(static_cast<float>(v.camera_px[k].x()), static_cast<float>(v.camera_px[k].y()));
      p2.emplace_back(static_cast<float>(v.projector_px[k].x()), static_cast<float>(v.projector_px[k].y()));
    }
    obj.push_back(o3);
    cam.push_back(c2);
    proj.push_back(p2);
  }
  cv::Mat Kc = camera_matrix(camera), dc = distortion(camera);
  cv::Mat Kp = camera_matrix(projector), dp = distortion(projector);
  cv::Mat R, T, E, F;
  const int flags = o.fix_intrinsics ? cv::CALIB_FIX_INTRINSIC : (cv::CALIB_USE_INTRINSIC_GUESS | cv::CALIB_FIX_K3);
  // cv::stereoCalibrate's R, T map points from the first camera (ours) into the second
  // (the projector): that is T_projector_camera.
  const double rms =
      cv::stereoCalibrate(obj, cam, proj, Kc, dc, Kp, dp, cv::Size(camera.width_px, camera.height_px), R, T, E, F,
                          flags, cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 100, 1e-9));
  Transform T_projector_camera = Transform::Identity();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) T_projector_camera.linear()(r, c) = R.at<double>(r, c);
    T_projector_camera.translation()(r) = T.at<double>(r);
  }
  StereoResult result;
  result.T_camera_projector = T_projector_camera.inverse();
  result.camera = camera;
  result.projector = projector;
  store(Kc, dc, result.camera);
  store(Kp, dp, result.projector);
  result.rms_px = rms;
  return result;
}

}  // namespace fettle::vision::calibration
