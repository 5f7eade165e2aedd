#include "synthetic.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <stdexcept>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include "../support/draws.hpp"

namespace fettle::test {

config::CameraIntrinsics test_camera(bool distorted) {
  config::CameraIntrinsics k;
  k.width_px = 1032;
  k.height_px = 772;
  k.fx_px = 1200.0;
  k.fy_px = 1200.0;
  k.cx_px = 520.0;
  k.cy_px = 380.0;
  k.distortion = distorted ? std::vector<double>{-0.12, 0.08, 0.0005, -0.0003, 0.0} : std::vector<double>(5, 0.0);
  return k;
}

namespace {

/// The undistorted normalized ray of every pixel of the camera (computed once per camera: the
/// same for every view, and the slow part of rendering).
const std::vector<cv::Point2f>& pixel_rays(const config::CameraIntrinsics& k) {
  static std::vector<double> key;
  static std::vector<cv::Point2f> rays;
  std::vector<double> this_key{
      static_cast<double>(k.width_px), static_cast<double>(k.height_px), k.fx_px, k.fy_px, k.cx_px, k.cy_px};
  this_key.insert(this_key.end(), k.distortion.begin(), k.distortion.end());
  if (this_key == key) return rays;
  std::vector<cv::Point2f> px;
  px.reserve(static_cast<std::size_t>(k.width_px) * static_cast<std::size_t>(k.height_px));
  for (int v = 0; v < k.height_px; ++v)
    for (int u = 0; u < k.width_px; ++u) px.emplace_back(static_cast<float>(u), static_cast<float>(v));
  const cv::Mat K = (cv::Mat_<double>(3, 3) << k.fx_px, 0, k.cx_px, 0, k.fy_px, k.cy_px, 0, 0, 1);
  cv::undistortPoints(px, rays, K, cv::Mat(k.distortion, true), cv::noArray(), cv::noArray(),
                      cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 30, 1e-12));
  key = this_key;
  return rays;
}

/// Renders a planar texture (CV_32FC1) lying in the board plane at T_camera_board:
/// texel = board_to_tex * (x_mm, y_mm, 1).
cv::Mat render_texture(const cv::Mat& tex, const Eigen::Matrix<double, 2, 3>& board_to_tex,
                       const config::CameraIntrinsics& k, const Transform& T, double blur_sigma_px, double noise_grey,
                       unsigned seed) {
  // Every image pixel: undistorted normalized ray -> board plane -> texture coordinate.
  const auto& norm = pixel_rays(k);
  Eigen::Matrix3d G;
  G.col(0) = T.linear().col(0);
  G.col(1) = T.linear().col(1);
  G.col(2) = T.translation();
  const Eigen::Matrix3d Gi = G.inverse();
  cv::Mat mapx(k.height_px, k.width_px, CV_32FC1), mapy(k.height_px, k.width_px, CV_32FC1);
  for (int v = 0; v < k.height_px; ++v)
    for (int u = 0; u < k.width_px; ++u) {
      const auto& n =
          norm[static_cast<std::size_t>(v) * static_cast<std::size_t>(k.width_px) + static_cast<std::size_t>(u)];
      const Eigen::Vector3d b = Gi * Eigen::Vector3d(n.x, n.y, 1.0);
      float tx = -1000.f, ty = -1000.f;
      if (b.z() > 0) {  // in front of the camera
        const Eigen::Vector2d t = board_to_tex * Eigen::Vector3d(b.x() / b.z(), b.y() / b.z(), 1.0);
        tx = static_cast<float>(t.x());
        ty = static_cast<float>(t.y());
      }
      mapx.at<float>(v, u) = tx;
      mapy.at<float>(v, u) = ty;
    }
  cv::Mat img;
  cv::remap(tex, img, mapx, mapy, cv::INTER_AREA, cv::BORDER_CONSTANT, cv::Scalar(120.0));
  cv::GaussianBlur(img, img, cv::Size(0, 0), blur_sigma_px > 0 ? blur_sigma_px : 0.5);
  cv::Mat n(img.size(), CV_32FC1);
  cv::RNG rng(seed);
  rng.fill(n, cv::RNG::NORMAL, 0.0, noise_grey);
  img += n;
  cv::Mat out;
  img.convertTo(out, CV_8UC1);
  return out;
}

}  // namespace

cv::Mat render_board(const vision::calibration::BoardSpec& board, const config::CameraIntrinsics& k, const Transform& T,
                     double blur_sigma_px, double noise_grey, unsigned seed) {
  // Texture: (cols + 1) x (rows + 1) squares plus a one-square white margin, S texels per square.
  constexpr int S = 60;
  const int sq_x = board.cols + 3, sq_y = board.rows + 3;
  cv::Mat tex(sq_y * S, sq_x * S, CV_32FC1, cv::Scalar(230.0));
  for (int j = 1; j < sq_y - 1; ++j)
    for (int i = 1; i < sq_x - 1; ++i)
      if ((i + j) % 2 == 0) tex(cv::Rect(i * S, j * S, S, S)).setTo(cv::Scalar(25.0));
  Eigen::Matrix<double, 2, 3> board_to_tex;
  board_to_tex << S / board.square_mm, 0.0, 2.0 * S - 0.5, 0.0, S / board.square_mm, 2.0 * S - 0.5;
  return render_texture(tex, board_to_tex, k, T, blur_sigma_px, noise_grey, seed);
}

cv::Mat render_board_image(const vision::calibration::BoardImage& board, const config::CameraIntrinsics& k,
                           const Transform& T, double blur_sigma_px, double noise_grey, unsigned seed) {
  const auto& im = board.image;
  cv::Mat tex8(im.height_px, im.width_px, CV_8UC1, const_cast<std::uint8_t*>(im.pixels.data()));  // NOLINT
  cv::Mat tex;
  tex8.convertTo(tex, CV_32FC1, (230.0 - 25.0) / 255.0, 25.0);  // print contrast: black 25, white 230
  return render_texture(tex, board.board_to_px, k, T, blur_sigma_px, noise_grey, seed);
}

vision::calibration::GrayImage to_gray_image(const cv::Mat& m, const std::string& name) {
  vision::calibration::GrayImage g;
  g.name = name;
  g.width_px = m.cols;
  g.height_px = m.rows;
  g.pixels.assign(m.data, m.data + m.total());
  return g;
}

Transform board_pose_facing_camera(const vision::calibration::BoardSpec& board, double distance_mm, double dx_mm,
                                   double dy_mm, double tilt_x, double tilt_y, double spin_z) {
  // Rotate about the board centre, then place the centre at (dx, dy, distance).
  const Vec3 centre(0.5 * (board.cols - 1) * board.square_mm, 0.5 * (board.rows - 1) * board.square_mm, 0.0);
  const Eigen::Matrix3d R = (Eigen::AngleAxisd(tilt_x, Vec3::UnitX()) * Eigen::AngleAxisd(tilt_y, Vec3::UnitY()) *
                             Eigen::AngleAxisd(spin_z, Vec3::UnitZ()))
                                .toRotationMatrix();
  Transform T = Transform::Identity();
  T.linear() = R;
  T.translation() = Vec3(dx_mm, dy_mm, distance_mm) - R * centre;
  return T;
}

Transform noise(std::mt19937_64& rng, double sigma_mm, double sigma_deg) {
  std::normal_distribution<double> nt(0.0, sigma_mm), nr(0.0, deg_to_rad(sigma_deg));
  const Vec3 w = fettle::test::draw3<Vec3>(nr, rng);
  Transform T = Transform::Identity();
  if (w.norm() > 0) T.linear() = Eigen::AngleAxisd(w.norm(), w.normalized()).toRotationMatrix();
  T.translation() = fettle::test::draw3<Vec3>(nt, rng);
  return T;
}

HandEyeTruth hand_eye_truth(bool board_on_flange_plate) {
  HandEyeTruth t;
  t.T_base_camera = Transform::Identity();
  t.T_base_camera.linear() =
      (Eigen::AngleAxisd(deg_to_rad(180.0), Vec3::UnitX()) * Eigen::AngleAxisd(deg_to_rad(1.5), Vec3::UnitY()) *
       Eigen::AngleAxisd(deg_to_rad(-2.0), Vec3::UnitZ()))
          .toRotationMatrix();
  t.T_base_camera.translation() = Vec3(12.0, -7.0, 600.0);
  t.T_flange_board = Transform::Identity();
  t.T_flange_board.linear() =
      (Eigen::AngleAxisd(deg_to_rad(3.0), Vec3::UnitZ()) * Eigen::AngleAxisd(deg_to_rad(-1.0), Vec3::UnitX()))
          .toRotationMatrix();
  // The board frame's origin is its first inner corner; the 9x6 x 20 mm board's centre is at
  // (80, 50) mm in it.
  t.T_flange_board.translation() = Vec3(-80.0, -50.0, board_on_flange_plate ? 25.0 : 80.0);
  return t;
}

PoseDesign recommended_design() {
  PoseDesign d;
  d.depth_mm = 80.0;
  d.tilt_deg = 45.0;
  d.min_tilt_deg = 30.0;
  d.spin_deg = 90.0;
  d.designed = true;
  return d;
}

PoseNoise PoseNoise::rms_magnitude(double magnitude_mm, double magnitude_deg) {
  return per_axis(magnitude_mm / std::sqrt(3.0), magnitude_deg / std::sqrt(3.0));
}

PoseNoise PoseNoise::per_axis(double sigma_mm, double sigma_deg) {
  return PoseNoise{sigma_mm, sigma_deg, sigma_mm, sigma_deg};
}

std::vector<vision::calibration::HandEyeSample> hand_eye_samples(const HandEyeTruth& truth, int n, const PoseDesign& d,
                                                                 const PoseNoise& nz, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const vision::calibration::BoardSpec board{9, 6, 20.0};
  std::vector<vision::calibration::HandEyeSample> out;
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  for (int i = 0; i < n; ++i) {
    if (d.designed) {
      const double sx = (i % 2 == 0 ? 1.0 : -1.0) * (0.8 + 0.2 * u01(rng));
      const double sy = ((i / 2) % 2 == 0 ? 1.0 : -1.0) * (0.8 + 0.2 * u01(rng));
      const double depth = d.depth_mm * static_cast<double>(i % 3 - 1);
      const double tilt = deg_to_rad(d.min_tilt_deg + (d.tilt_deg - d.min_tilt_deg) * u01(rng));
      const double azimuth = 2.0 * std::numbers::pi * u01(rng);
      const double spin = deg_to_rad(d.spin_deg * u(rng));
      const Transform B =
          board_pose_facing_camera(board, d.distance_mm + depth, d.lateral_x_mm * sx, d.lateral_y_mm * sy,
                                   tilt * std::cos(azimuth), tilt * std::sin(azimuth), spin);
      const Transform A = truth.T_base_camera * B * truth.T_flange_board.inverse();
      vision::calibration::HandEyeSample s;
      s.name = "pose" + std::to_string(i + 1);
      s.T_base_flange = A * noise(rng, nz.robot_sigma_mm, nz.robot_sigma_deg);
      s.T_camera_board = B * noise(rng, nz.board_sigma_mm, nz.board_sigma_deg);
      out.push_back(s);
      continue;
    }
    const double tilt_x = d.single_axis ? 0.0 : deg_to_rad(d.tilt_deg * u(rng));
    const double tilt_y = d.single_axis ? 0.0 : deg_to_rad(d.tilt_deg * u(rng));
    const double spin = deg_to_rad(d.spin_deg * u(rng));
    const auto a = fettle::test::draws<3>(u, rng);
    const Transform B = board_pose_facing_camera(board, d.distance_mm + d.depth_mm * a[0], d.lateral_x_mm * a[1],
                                                 d.lateral_y_mm * a[2], tilt_x, tilt_y, spin);
    const Transform A = truth.T_base_camera * B * truth.T_flange_board.inverse();
    vision::calibration::HandEyeSample s;
    s.name = "pose" + std::to_string(i + 1);
    s.T_base_flange = A * noise(rng, nz.robot_sigma_mm, nz.robot_sigma_deg);
    s.T_camera_board = B * noise(rng, nz.board_sigma_mm, nz.board_sigma_deg);
    out.push_back(s);
  }
  return out;
}

std::vector<vision::calibration::HandEyeSample> hand_eye_samples(const HandEyeTruth& truth, int n, double sigma_mm,
                                                                 double sigma_deg, std::uint64_t seed,
                                                                 bool single_axis) {
  PoseDesign d;
  d.single_axis = single_axis;
  return hand_eye_samples(truth, n, d, PoseNoise::per_axis(sigma_mm, sigma_deg), seed);
}

Eigen::Vector2d project_point(const config::CameraIntrinsics& k, const Vec3& p) {
  const double x = p.x() / p.z(), y = p.y() / p.z();
  const auto d = [&](std::size_t i) { return i < k.distortion.size() ? k.distortion[i] : 0.0; };
  const double r2 = x * x + y * y;
  const double radial = 1.0 + d(0) * r2 + d(1) * r2 * r2 + d(4) * r2 * r2 * r2;
  const double xd = x * radial + 2.0 * d(2) * x * y + d(3) * (r2 + 2.0 * x * x);
  const double yd = y * radial + d(2) * (r2 + 2.0 * y * y) + 2.0 * d(3) * x * y;
  return {k.fx_px * xd + k.skew * yd + k.cx_px, k.fy_px * yd + k.cy_px};
}

namespace {

/// What a point of the camera image sees: the board's albedo there (< 0: beyond the board) and
/// the projector pixel lighting it (-1: none).
struct Sample {
  float albedo = -1.0f;
  std::int32_t projector_index = -1;
  std::int32_t column = -1, row = -1;  ///< may lie outside the projector's image
  bool in_projector = false;
  bool shadow_or_stain = false;
};

/// Every projector pixel's patterns as one bit each (pattern m white: bit m), computed once
/// per layout.
const std::vector<std::uint64_t>& pattern_codes(const vision::calibration::GrayCodeLayout& layout) {
  static std::pair<int, int> key{0, 0};
  static std::vector<std::uint64_t> code;
  if (key == std::pair<int, int>{layout.width_px, layout.height_px}) return code;
  const auto patterns = vision::calibration::gray_code_patterns(layout);
  if (patterns.size() > 64) throw std::invalid_argument("render_structured_light: more than 64 patterns");
  code.assign(patterns[0].pixels.size(), 0);
  for (std::size_t m = 0; m < patterns.size(); ++m)
    for (std::size_t i = 0; i < code.size(); ++i)
      if (patterns[m].pixels[i] > 127) code[i] |= std::uint64_t{1} << m;
  key = {layout.width_px, layout.height_px};
  return code;
}

/// `with_truth`: the projector pixel also where the plane is not the board (the true maps).
Sample sample(const StructuredLightScene& s, const Eigen::Matrix3d& Gi, const Transform& T_projector_camera,
              const cv::Point2f& ray, bool with_truth) {
  Sample out;
  const Eigen::Vector3d b = Gi * Eigen::Vector3d(ray.x, ray.y, 1.0);
  if (b.z() <= 0) return out;
  const double x = b.x() / b.z(), y = b.y() / b.z(), S = s.board.square_mm;
  // Squares as render_board draws them: square i covers x in [(i-2) S, (i-1) S), i = 0 and
  // i = cols + 2 are the white margin; black where (i + j) is even.
  const int i = static_cast<int>(std::floor(x / S)) + 2, j = static_cast<int>(std::floor(y / S)) + 2;
  const bool on_board = i >= 0 && j >= 0 && i <= s.board.cols + 2 && j <= s.board.rows + 2;
  if (!on_board && !with_truth) return out;
  // The projector pixel of the plane point (whether the board, a shadow or nothing is there).
  const Vec3 q = T_projector_camera * (s.T_camera_board * Vec3(x, y, 0.0));
  if (q.z() > 0) {
    const Eigen::Vector2d px = project_point(s.projector, q);
    // Projector pixel c covers [c - 0.5, c + 0.5) (OpenCV's pixel centres).
    const auto c = static_cast<std::int32_t>(std::floor(px.x() + 0.5));
    const auto r = static_cast<std::int32_t>(std::floor(px.y() + 0.5));
    out.column = c;
    out.row = r;
    out.in_projector = c >= 0 && r >= 0 && c < s.projector.width_px && r < s.projector.height_px;
  }
  if (!on_board) return out;
  const bool margin = i == 0 || j == 0 || i == s.board.cols + 2 || j == s.board.rows + 2;
  out.albedo = static_cast<float>(!margin && (i + j) % 2 == 0 ? s.black_albedo : s.white_albedo);
  const Eigen::Vector2d xy(x, y);
  if (s.stain_radius_mm > 0 && (xy - s.stain_centre_mm).norm() < s.stain_radius_mm) {
    out.albedo = static_cast<float>(s.stain_albedo);
    out.shadow_or_stain = true;
  }
  if (s.shadow_radius_mm > 0 && (xy - s.shadow_centre_mm).norm() < s.shadow_radius_mm) {
    out.shadow_or_stain = true;
    return out;
  }
  if (out.in_projector) out.projector_index = out.row * s.projector.width_px + out.column;
  return out;
}

}  // namespace

StructuredLightRender render_structured_light(const StructuredLightScene& s,
                                              const vision::calibration::GrayCodeLayout& layout) {
  const auto& k = s.camera;
  const auto& rays = pixel_rays(k);
  Eigen::Matrix3d G;
  G.col(0) = s.T_camera_board.linear().col(0);
  G.col(1) = s.T_camera_board.linear().col(1);
  G.col(2) = s.T_camera_board.translation();
  const Eigen::Matrix3d Gi = G.inverse();
  const Transform T_projector_camera = s.T_camera_projector.inverse();
  const int W = k.width_px, H = k.height_px;
  const auto ray_at = [&](double u, double v) {
    // Rays between pixel centres, bilinearly: the distortion is smooth at this scale.
    u = std::clamp(u, 0.0, W - 1.0);
    v = std::clamp(v, 0.0, H - 1.0);
    const int u0 = std::min(static_cast<int>(u), W - 2), v0 = std::min(static_cast<int>(v), H - 2);
    const auto fu = static_cast<float>(u - u0), fv = static_cast<float>(v - v0);
    const auto at = [&](int uu, int vv) {
      return rays[static_cast<std::size_t>(vv) * static_cast<std::size_t>(W) + static_cast<std::size_t>(uu)];
    };
    return (at(u0, v0) * (1 - fu) + at(u0 + 1, v0) * fu) * (1 - fv) +
           (at(u0, v0 + 1) * (1 - fu) + at(u0 + 1, v0 + 1) * fu) * fv;
  };
  StructuredLightRender out;
  out.true_column = cv::Mat(H, W, CV_32SC1, cv::Scalar(-1));
  out.true_row = cv::Mat(H, W, CV_32SC1, cv::Scalar(-1));
  out.shadow_or_stain = cv::Mat(H, W, CV_8UC1, cv::Scalar(0));
  out.lit = cv::Mat(H, W, CV_8UC1, cv::Scalar(0));
  const auto names = layout.names();
  const std::size_t n_img = names.size();
  const std::vector<std::uint64_t>& code = pattern_codes(layout);
  std::vector<cv::Mat> acc(n_img);
  for (auto& a : acc) a = cv::Mat(H, W, CV_32FC1, cv::Scalar(s.background_grey));
  const int ss = std::max(1, s.supersample);
  const float per_sample = 1.0f / static_cast<float>(ss * ss);
  const auto ambient = static_cast<float>(s.ambient_grey), gain = static_cast<float>(s.projector_grey / 255.0);
  // Only the board's neighbourhood in the image is sampled (its outer corners projected, plus
  // 12 px); elsewhere the image is background and the true maps are -1.
  int u_lo = W, u_hi = -1, v_lo = H, v_hi = -1;
  const double S = s.board.square_mm;
  for (const double x : {-2.0 * S, (s.board.cols + 1.0) * S})
    for (const double y : {-2.0 * S, (s.board.rows + 1.0) * S}) {
      const Vec3 p = s.T_camera_board * Vec3(x, y, 0.0);
      if (p.z() <= 0) continue;
      const Eigen::Vector2d px = project_point(k, p);
      u_lo = std::min(u_lo, static_cast<int>(px.x()) - 12);
      u_hi = std::max(u_hi, static_cast<int>(px.x()) + 12);
      v_lo = std::min(v_lo, static_cast<int>(px.y()) - 12);
      v_hi = std::max(v_hi, static_cast<int>(px.y()) + 12);
    }
  u_lo = std::max(u_lo, 0), v_lo = std::max(v_lo, 0), u_hi = std::min(u_hi, W - 1), v_hi = std::min(v_hi, H - 1);
  const auto background = static_cast<float>(s.background_grey) * per_sample;
  std::vector<std::pair<std::uint64_t, float>> lit_codes;  // per pixel: distinct pattern codes, light weight
  for (int v = v_lo; v <= v_hi; ++v)
    for (int u = u_lo; u <= u_hi; ++u) {
      const Sample centre =
          sample(s, Gi, T_projector_camera,
                 rays[static_cast<std::size_t>(v) * static_cast<std::size_t>(W) + static_cast<std::size_t>(u)], true);
      out.true_column.at<std::int32_t>(v, u) = centre.column;
      out.true_row.at<std::int32_t>(v, u) = centre.row;
      out.lit.at<std::uint8_t>(v, u) = centre.albedo >= 0 && centre.projector_index >= 0 ? 255 : 0;
      out.shadow_or_stain.at<std::uint8_t>(v, u) = centre.shadow_or_stain ? 255 : 0;
      // value[m] = base + sum over lit samples of their weight x pattern m (0 or 255).
      float base = 0.0f;
      bool any = false;
      lit_codes.clear();
      for (int a = 0; a < ss; ++a)
        for (int b = 0; b < ss; ++b) {
          const Sample p = ss == 1 ? centre
                                   : sample(s, Gi, T_projector_camera,
                                            ray_at(u + (b + 0.5) / ss - 0.5, v + (a + 0.5) / ss - 0.5), false);
          if (p.albedo < 0) {
            base += background;
            continue;
          }
          any = true;
          base += p.albedo * ambient * per_sample;
          if (p.projector_index < 0) continue;
          const float lit = p.albedo * gain * per_sample * 255.0f;
          const std::uint64_t bits = code[static_cast<std::size_t>(p.projector_index)];
          auto it = std::find_if(lit_codes.begin(), lit_codes.end(), [&](const auto& c) { return c.first == bits; });
          if (it == lit_codes.end())
            lit_codes.emplace_back(bits, lit);
          else
            it->second += lit;
        }
      if (!any) continue;
      for (std::size_t m = 0; m < n_img; ++m) {
        float x = base;
        for (const auto& [bits, w] : lit_codes)
          if (((bits >> m) & 1U) != 0) x += w;
        acc[m].at<float>(v, u) = x;
      }
    }
  // Blur and noise only where the board is (the rest is a flat background nothing decodes).
  cv::RNG rng(s.seed);
  const cv::Rect roi =
      u_hi < u_lo || v_hi < v_lo ? cv::Rect(0, 0, 1, 1) : cv::Rect(u_lo, v_lo, u_hi - u_lo + 1, v_hi - v_lo + 1);
  for (std::size_t m = 0; m < n_img; ++m) {
    cv::Mat img = acc[m];
    cv::Mat part = img(roi);
    if (s.blur_sigma_px > 0) cv::GaussianBlur(part, part, cv::Size(0, 0), s.blur_sigma_px);
    if (s.noise_grey > 0) {
      cv::Mat nz(part.size(), CV_32FC1);
      rng.fill(nz, cv::RNG::NORMAL, 0.0, s.noise_grey);
      part += nz;
    }
    cv::Mat out8;
    img.convertTo(out8, CV_8UC1);
    out.images.push_back(to_gray_image(out8, names[m]));
  }
  return out;
}

config::CameraIntrinsics structured_light_projector() {
  config::CameraIntrinsics k;
  k.width_px = 1280;
  k.height_px = 800;
  k.fx_px = 1400.0;
  k.fy_px = 1400.0;
  k.cx_px = 640.0;
  k.cy_px = 560.0;  // projecting somewhat upwards, as projectors do
  k.distortion = {0.02, 0.0, 0.0, 0.0, 0.0};
  return k;
}

/// The projector 180 mm to the right of the camera, toed in by 12 deg.
Transform structured_light_T_camera_projector() {
  Transform T = Transform::Identity();
  T.linear() = (Eigen::AngleAxisd(deg_to_rad(-12.0), Vec3::UnitY()) * Eigen::AngleAxisd(deg_to_rad(1.0), Vec3::UnitX()))
                   .toRotationMatrix();
  T.translation() = Vec3(180.0, 5.0, 10.0);
  return T;
}

StructuredLightScene structured_light_scene() {
  StructuredLightScene s;
  s.camera = test_camera();
  s.projector = structured_light_projector();
  s.T_camera_projector = structured_light_T_camera_projector();
  return s;
}

namespace {

/// True when the whole board (with its white margin) and a few pixels around it is inside
/// both the camera's and the projector's image.
bool board_fits(const StructuredLightScene& s, const Transform& T_camera_board) {
  const double S = s.board.square_mm;
  const Transform T_projector_camera = s.T_camera_projector.inverse();
  for (const double x : {-2.5 * S, (s.board.cols + 1.5) * S})
    for (const double y : {-2.5 * S, (s.board.rows + 1.5) * S}) {
      const Vec3 p = T_camera_board * Vec3(x, y, 0.0);
      const Eigen::Vector2d c = project_point(s.camera, p), q = project_point(s.projector, T_projector_camera * p);
      if (c.x() < 10 || c.y() < 10 || c.x() > s.camera.width_px - 10 || c.y() > s.camera.height_px - 10) return false;
      if (q.x() < 5 || q.y() < 5 || q.x() > s.projector.width_px - 5 || q.y() > s.projector.height_px - 5) return false;
    }
  return true;
}

}  // namespace

/// `n` board poses 430-570 mm from the camera, tilted up to 30 deg about two axes and turned
/// up to 30 deg, that fit both images.
std::vector<Transform> structured_light_board_poses(const StructuredLightScene& s, int n, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<Transform> out;
  for (int tries = 0; tries < 2000 && static_cast<int>(out.size()) < n; ++tries) {
    const auto a = fettle::test::draws<6>(u, rng);
    const Transform T =
        test::board_pose_facing_camera(s.board, 500 + 70 * a[0], 40 + 50 * a[1], -20 + 40 * a[2], deg_to_rad(30 * a[3]),
                                       deg_to_rad(30 * a[4]), deg_to_rad(30 * a[5]));
    if (board_fits(s, T)) out.push_back(T);
  }
  return out;
}

double rotation_error_deg(const Transform& a, const Transform& b) {
  return rad_to_deg(rotation_angle_rad(a.inverse() * b));
}

double translation_error_mm(const Transform& a, const Transform& b) {
  return (a.translation() - b.translation()).norm();
}

}  // namespace fettle::test
