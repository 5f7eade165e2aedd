// Eye-to-hand calibration: board method (AX = YB) and sphere method (rigid fit of centres).
#include "fettle/vision/calibration/hand_eye.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <Eigen/SVD>

#include "fettle/core/log.hpp"

namespace fettle::vision::calibration {

namespace {

using Mat3 = Eigen::Matrix3d;
using Vec6 = Eigen::Matrix<double, 6, 1>;

std::string fmt(double v, int decimals = 2) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  return buf;
}

std::string vec_str(const Vec3& v) { return "[" + fmt(v.x()) + ", " + fmt(v.y()) + ", " + fmt(v.z()) + "]"; }

Mat3 nearest_rotation(const Mat3& M) {
  Eigen::JacobiSVD<Mat3> svd(M, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Mat3 D = Mat3::Identity();
  D(2, 2) = (svd.matrixU() * svd.matrixV().transpose()).determinant() < 0 ? -1.0 : 1.0;
  return svd.matrixU() * D * svd.matrixV().transpose();
}

Mat3 exp_so3(const Vec3& w) {
  const double a = w.norm();
  if (a < 1e-15) return Mat3::Identity();
  return Eigen::AngleAxisd(a, w / a).toRotationMatrix();
}

Vec3 log_so3(const Mat3& R) {
  const Eigen::AngleAxisd aa(R);
  return aa.angle() * aa.axis();
}

Transform exp_se3(const Vec6& d) {
  Transform T = Transform::Identity();
  T.linear() = exp_so3(d.head<3>());
  T.translation() = d.tail<3>();
  return T;
}

/// The mismatch of pose i in the board frame: (A X)^-1 (Y B).
Transform mismatch(const HandEyeSample& s, const Transform& X, const Transform& Y) {
  return (s.T_base_flange * X).inverse() * (Y * s.T_camera_board);
}

/// Linear solution of A_i X = Y B_i: rotations from the null space of the stacked
/// Kronecker system (I (x) R_A) vec(R_X) - (R_B^T (x) I) vec(R_Y) = 0, then translations
/// from R_A t_X - t_Y = R_Y t_B - t_A by least squares.
void solve_linear(const std::vector<HandEyeSample>& s, Transform& X, Transform& Y) {
  const auto n = static_cast<Eigen::Index>(s.size());
  Eigen::MatrixXd M(9 * n, 18);
  const Mat3 I = Mat3::Identity();
  for (Eigen::Index i = 0; i < n; ++i) {
    const Mat3 RA = s[static_cast<std::size_t>(i)].T_base_flange.rotation();
    const Mat3 RB = s[static_cast<std::size_t>(i)].T_camera_board.rotation();
    Eigen::Matrix<double, 9, 18> Mi;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) {
        Mi.block<3, 3>(3 * r, 3 * c) = I(r, c) * RA;               // I (x) R_A
        Mi.block<3, 3>(3 * r, 9 + 3 * c) = -RB(c, r) * I;          // -(R_B^T (x) I)
      }
    M.block<9, 18>(9 * i, 0) = Mi;
  }
  Eigen::JacobiSVD<Eigen::MatrixXd> svd(M, Eigen::ComputeThinV);
  const Eigen::VectorXd v = svd.matrixV().col(17);
  Mat3 RX = Eigen::Map<const Mat3>(v.data());
  Mat3 RY = Eigen::Map<const Mat3>(v.data() + 9);
  const double d = RX.determinant();
  const double scale = (d < 0 ? -1.0 : 1.0) / std::cbrt(std::abs(d));
  RX = nearest_rotation(RX * scale);
  RY = nearest_rotation(RY * scale);

  Eigen::MatrixXd C(3 * n, 6);
  Eigen::VectorXd b(3 * n);
  for (Eigen::Index i = 0; i < n; ++i) {
    const auto& si = s[static_cast<std::size_t>(i)];
    C.block<3, 3>(3 * i, 0) = si.T_base_flange.rotation();
    C.block<3, 3>(3 * i, 3) = -I;
    b.segment<3>(3 * i) = RY * si.T_camera_board.translation() - si.T_base_flange.translation();
  }
  const Eigen::VectorXd t = C.colPivHouseholderQr().solve(b);
  X.setIdentity();
  X.linear() = RX;
  X.translation() = t.head<3>();
  Y.setIdentity();
  Y.linear() = RY;
  Y.translation() = t.tail<3>();
}

using Mat6 = Eigen::Matrix<double, 6, 6>;

Mat3 skew(const Vec3& v) {
  Mat3 m;
  m << 0.0, -v.z(), v.y(), v.z(), 0.0, -v.x(), -v.y(), v.x(), 0.0;
  return m;
}

/// The whitening matrix L (L^T L = Sigma^-1) of a pose mismatch E = (A X)^-1 Y B, to first
/// order, when A and B carry right-multiplied noise (rotation w, translation t) with the given
/// sigmas: log E = [w_B - R_X^T w_A ; t_B - R_X^T t_A + R_X^T [t_X]x w_A]. The covariance is
/// the same for every pose; the lever arm t_X correlates rotation and translation.
Mat6 whitening(const Transform& X, const HandEyeOptions& o) {
  const Mat3 Rt = X.rotation().transpose();
  Mat6 J = Mat6::Zero();
  J.block<3, 3>(0, 0) = -Rt;
  J.block<3, 3>(3, 0) = Rt * skew(X.translation());
  J.block<3, 3>(3, 3) = -Rt;
  const auto var = [](double s) { return std::max(s * s, 1e-12); };
  Mat6 SA = Mat6::Zero(), SB = Mat6::Zero();
  SA.diagonal() << Vec3::Constant(var(deg_to_rad(o.robot_noise_deg))), Vec3::Constant(var(o.robot_noise_mm));
  SB.diagonal() << Vec3::Constant(var(deg_to_rad(o.board_noise_deg))), Vec3::Constant(var(o.board_noise_mm));
  const Mat6 info = (J * SA * J.transpose() + SB).inverse();
  return Eigen::LLT<Mat6>(0.5 * (info + info.transpose())).matrixU();
}

/// The whitened mismatch of every pose, scaled by the pose's robust weight `w` (sqrt).
Eigen::VectorXd residual_vector(const std::vector<HandEyeSample>& s, const Transform& X, const Transform& Y,
                                const Mat6& L, const std::vector<double>& w) {
  Eigen::VectorXd r(6 * static_cast<Eigen::Index>(s.size()));
  for (std::size_t i = 0; i < s.size(); ++i) {
    const Transform E = mismatch(s[i], X, Y);
    Vec6 e;
    e.head<3>() = log_so3(E.rotation());
    e.tail<3>() = E.translation();
    r.segment<6>(6 * static_cast<Eigen::Index>(i)) = w[i] * (L * e);
  }
  return r;
}

/// Levenberg-Marquardt over X and Y jointly (12 parameters, right-multiplied SE(3) updates) on
/// the whitened mismatches of all poses.
void refine_weighted(const std::vector<HandEyeSample>& s, Transform& X, Transform& Y, const Mat6& L,
                     const std::vector<double>& w) {
  double lambda = 1e-6;
  Eigen::VectorXd r = residual_vector(s, X, Y, L, w);
  double cost = r.squaredNorm();
  for (int iter = 0; iter < 50; ++iter) {
    Eigen::MatrixXd J(r.size(), 12);
    for (int k = 0; k < 12; ++k) {
      const double h = (k % 6) < 3 ? 1e-7 : 1e-5;  // rad, mm
      Vec6 d = Vec6::Zero();
      d(k % 6) = h;
      const Transform Xp = k < 6 ? Transform(X * exp_se3(d)) : X;
      const Transform Yp = k < 6 ? Y : Transform(Y * exp_se3(d));
      J.col(k) = (residual_vector(s, Xp, Yp, L, w) - r) / h;
    }
    Eigen::Matrix<double, 12, 12> H = J.transpose() * J;
    const Eigen::Matrix<double, 12, 1> g = J.transpose() * r;
    bool improved = false;
    for (int tries = 0; tries < 10 && !improved; ++tries) {
      Eigen::Matrix<double, 12, 12> Hd = H;
      Hd.diagonal() *= (1.0 + lambda);
      const Eigen::Matrix<double, 12, 1> step = -Hd.ldlt().solve(g);
      const Transform Xn = X * exp_se3(step.head<6>());
      const Transform Yn = Y * exp_se3(step.tail<6>());
      const Eigen::VectorXd rn = residual_vector(s, Xn, Yn, L, w);
      if (rn.squaredNorm() < cost) {
        X = Xn;
        Y = Yn;
        const double old = cost;
        r = rn;
        cost = rn.squaredNorm();
        lambda = std::max(lambda / 10.0, 1e-12);
        improved = true;
        if (old - cost < 1e-14 * std::max(1.0, old)) return;
      } else {
        lambda *= 10.0;
      }
    }
    if (!improved) return;
  }
}

/// The covariance depends on X (its lever arm), so it is recomputed between passes; each pass
/// also re-weights the poses with Huber's weights on their whitened mismatch (iteratively
/// re-weighted least squares), so that one grossly wrong pose cannot pull the solution far
/// enough to hide among the others before the outlier check. Poses that fit the noise model
/// (whitened mismatch below kHuber, nearly all of them) keep the weight 1.
void refine(const std::vector<HandEyeSample>& s, Transform& X, Transform& Y, const HandEyeOptions& o) {
  constexpr double kHuber = 5.0;  // whitened 6-vector norm (about 2.4 expected without outliers)
  std::vector<double> w(s.size(), 1.0);
  for (int pass = 0; pass < 4; ++pass) {
    const Mat6 L = whitening(X, o);
    refine_weighted(s, X, Y, L, w);
    for (std::size_t i = 0; i < s.size(); ++i) {
      const Transform E = mismatch(s[i], X, Y);
      Vec6 e;
      e.head<3>() = log_so3(E.rotation());
      e.tail<3>() = E.translation();
      const double n = (L * e).norm();
      w[i] = n <= kHuber ? 1.0 : std::sqrt(kHuber / n);
    }
  }
}

double median(std::vector<double> v) {
  if (v.empty()) return 0.0;
  const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

void summarize(config::HandEyeResiduals& r) {
  double sum_t = 0, sum_r = 0;
  r.max_mm = r.max_deg = 0.0;
  r.poses = 0;
  for (const auto& p : r.per_pose) {
    if (p.outlier) continue;
    ++r.poses;
    sum_t += p.translation_mm * p.translation_mm;
    sum_r += p.rotation_deg * p.rotation_deg;
    r.max_mm = std::max(r.max_mm, p.translation_mm);
    r.max_deg = std::max(r.max_deg, p.rotation_deg);
  }
  r.rms_mm = r.poses ? std::sqrt(sum_t / r.poses) : 0.0;
  r.rms_deg = r.poses ? std::sqrt(sum_r / r.poses) : 0.0;
}

/// Flags outliers among residuals (translation mm, rotation deg; rotation may be all 0).
std::vector<bool> flag_outliers(const std::vector<double>& t_mm, const std::vector<double>& r_deg,
                                const HandEyeOptions& o) {
  const double mt = median(t_mm), mr = median(r_deg);
  std::vector<bool> out(t_mm.size(), false);
  for (std::size_t i = 0; i < t_mm.size(); ++i)
    out[i] = (t_mm[i] > o.outlier_factor * mt && t_mm[i] > o.outlier_floor_mm) ||
             (r_deg[i] > o.outlier_factor * mr && r_deg[i] > o.outlier_floor_deg);
  return out;
}

Error too_few(std::size_t have, std::size_t need, const char* what) {
  return Error{"calibration.too_few_poses", "hand-eye calibration needs at least " + std::to_string(need) + " " +
                                                what + ", got " + std::to_string(have) +
                                                "; record more (10 to 20 spread over the working volume is good)"};
}

/// The base axis (x, y or z) most perpendicular to `a`.
const char* most_perpendicular_axis(const Vec3& a) {
  const Vec3 d = a.cwiseAbs();
  if (d.x() <= d.y() && d.x() <= d.z()) return "x";
  if (d.y() <= d.z()) return "y";
  return "z";
}

}  // namespace

Status check_pose_set(const std::vector<Transform>& T_base_flange, const HandEyeOptions& o) {
  if (T_base_flange.size() < std::max<std::size_t>(o.min_poses, 3)) return too_few(T_base_flange.size(), std::max<std::size_t>(o.min_poses, 3), "robot poses");
  // Axes of the relative rotations between every two poses (base frame), sign-free.
  Mat3 S = Mat3::Zero();
  int count = 0;
  double largest_deg = 0.0;
  const double min_pair_rad = deg_to_rad(std::max(2.0, 0.2 * o.min_rotation_deg));
  for (std::size_t i = 0; i < T_base_flange.size(); ++i)
    for (std::size_t j = i + 1; j < T_base_flange.size(); ++j) {
      const Eigen::AngleAxisd aa(Mat3(T_base_flange[j].rotation() * T_base_flange[i].rotation().transpose()));
      largest_deg = std::max(largest_deg, rad_to_deg(aa.angle()));
      if (aa.angle() < min_pair_rad) continue;
      S += aa.axis() * aa.axis().transpose();
      ++count;
    }
  if (largest_deg < o.min_rotation_deg || count == 0)
    return Error{"calibration.degenerate_poses",
                 "the robot poses barely rotate the flange (largest rotation between two poses " + fmt(largest_deg, 1) +
                     " deg, need at least " + fmt(o.min_rotation_deg, 0) +
                     "); add poses that tilt the flange by 15 to 30 deg about two different axes (e.g. about the base x "
                     "and y axes) besides moving it"};
  Eigen::SelfAdjointEigenSolver<Mat3> es(S / count);
  // Eigenvalues ascending: if all axes are within angle a of one direction, the second
  // largest eigenvalue is about sin^2(a)/2 or less.
  const double lambda2 = es.eigenvalues()(1);
  const double spread = std::sin(deg_to_rad(o.min_axis_spread_deg));
  if (lambda2 < 0.5 * spread * spread) {
    const Vec3 axis = es.eigenvectors().col(2);
    const char* other = most_perpendicular_axis(axis);
    return Error{"calibration.degenerate_poses",
                 "all rotations between the robot poses are about one axis (base-frame direction " + vec_str(axis) +
                     "): the rotation of the camera about that axis cannot be determined. Add poses where the flange "
                     "is also tilted about a different axis, e.g. 3 or more poses rotated by 15 to 30 deg about the "
                     "base " + std::string(other) + " axis"};
  }
  return {};
}

Result<HandEyeResult> calibrate_hand_eye_board(const std::vector<HandEyeSample>& samples, const HandEyeOptions& o) {
  auto logger = log::get("calibration");
  std::vector<Transform> poses;
  for (const auto& s : samples) poses.push_back(s.T_base_flange);
  if (auto st = check_pose_set(poses, o); !st.ok()) return st.error();

  std::vector<HandEyeSample> used = samples;
  std::vector<bool> outlier(samples.size(), false);
  Transform X, Y;
  for (int round = 0; round < 3; ++round) {
    solve_linear(used, X, Y);
    refine(used, X, Y, o);
    if (!o.drop_outliers) break;
    std::vector<double> t_mm, r_deg;
    for (const auto& s : samples) {
      const Transform E = mismatch(s, X, Y);
      t_mm.push_back(E.translation().norm());
      r_deg.push_back(rad_to_deg(rotation_angle_rad(E)));
    }
    const auto flagged = flag_outliers(t_mm, r_deg, o);
    if (flagged == outlier) break;
    outlier = flagged;
    used.clear();
    std::vector<Transform> kept;
    for (std::size_t i = 0; i < samples.size(); ++i)
      if (!outlier[i]) {
        used.push_back(samples[i]);
        kept.push_back(samples[i].T_base_flange);
      }
    logger->info("hand-eye: {} of {} poses flagged as outliers; solving again without them",
                 samples.size() - used.size(), samples.size());
    if (auto st = check_pose_set(kept, o); !st.ok())
      return Error{st.error().code, st.error().message + " (after leaving out " +
                                        std::to_string(samples.size() - kept.size()) + " outlier poses)"};
  }

  HandEyeResult result;
  result.T_base_camera = Y;
  result.T_flange_board = X;
  result.residuals.method = "board";
  for (std::size_t i = 0; i < samples.size(); ++i) {
    const Transform E = mismatch(samples[i], X, Y);
    result.residuals.per_pose.push_back(config::PoseResidual{
        samples[i].name, E.translation().norm(), rad_to_deg(rotation_angle_rad(E)), outlier[i]});
  }
  summarize(result.residuals);
  return result;
}

Result<HandEyeResult> calibrate_hand_eye_sphere(const std::vector<SphereSample>& samples, const HandEyeOptions& o) {
  const std::size_t need = std::max<std::size_t>(o.min_poses, 4);
  if (samples.size() < need) return too_few(samples.size(), need, "sphere positions");
  std::vector<bool> outlier(samples.size(), false);
  Transform T = Transform::Identity();
  for (int round = 0; round < 3; ++round) {
    std::vector<std::size_t> idx;
    for (std::size_t i = 0; i < samples.size(); ++i)
      if (!outlier[i]) idx.push_back(i);
    Eigen::Matrix3Xd cam(3, static_cast<Eigen::Index>(idx.size())), base(3, static_cast<Eigen::Index>(idx.size()));
    for (std::size_t k = 0; k < idx.size(); ++k) {
      cam.col(static_cast<Eigen::Index>(k)) = samples[idx[k]].center_camera_mm;
      base.col(static_cast<Eigen::Index>(k)) = samples[idx[k]].tcp_base_mm;
    }
    // The positions must span a volume, not a line: the second singular value of the
    // centred positions is the spread across the best line.
    const Eigen::Matrix3Xd centred = base.colwise() - base.rowwise().mean();
    const Eigen::Vector3d sv = Eigen::JacobiSVD<Eigen::Matrix3Xd>(centred).singularValues() /
                               std::sqrt(static_cast<double>(idx.size()));
    if (sv(1) < 10.0)
      return Error{"calibration.degenerate_poses",
                   "the sphere positions lie almost on a line (spread across it " + fmt(sv(1), 1) +
                       " mm); add positions spread over the camera's field of view and at 2 or more heights, at "
                       "least 50 mm apart"};
    const Eigen::Matrix4d M = Eigen::umeyama(cam, base, false);
    T.matrix() = M;
    if (!o.drop_outliers) break;
    std::vector<double> t_mm, zero(samples.size(), 0.0);
    for (const auto& s : samples) t_mm.push_back((T * s.center_camera_mm - s.tcp_base_mm).norm());
    const auto flagged = flag_outliers(t_mm, zero, o);
    if (flagged == outlier) break;
    outlier = flagged;
    std::size_t left = 0;
    for (const bool b : outlier) left += b ? 0 : 1;
    if (left < need) return too_few(left, need, "sphere positions (after leaving out outliers)");
  }
  HandEyeResult result;
  result.T_base_camera = T;
  result.residuals.method = "sphere";
  for (std::size_t i = 0; i < samples.size(); ++i)
    result.residuals.per_pose.push_back(config::PoseResidual{
        samples[i].name, (T * samples[i].center_camera_mm - samples[i].tcp_base_mm).norm(), 0.0, outlier[i]});
  summarize(result.residuals);
  return result;
}

}  // namespace fettle::vision::calibration
