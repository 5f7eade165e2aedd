// Eye-to-hand calibration on synthetic ground truth: board method (AX = YB) and sphere method.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>

#include <gtest/gtest.h>

#include "fettle/vision/calibration/hand_eye.hpp"
#include "synthetic.hpp"
#include "../support/draws.hpp"

using namespace fettle;                       // NOLINT
using namespace fettle::vision::calibration;  // NOLINT

namespace {

void expect_close(const Transform& got, const Transform& want, double tol_mm, double tol_deg) {
  EXPECT_LT(test::translation_error_mm(got, want), tol_mm);
  EXPECT_LT(test::rotation_error_deg(got, want), tol_deg);
}

}  // namespace

TEST(HandEyeBoard, ExactDataGivesTheTruth) {
  const auto truth = test::hand_eye_truth();
  const auto r = calibrate_hand_eye_board(test::hand_eye_samples(truth, 8, 0.0, 0.0, 1));
  ASSERT_TRUE(r.ok()) << r.error().message;
  expect_close(r->T_base_camera, truth.T_base_camera, 1e-6, 1e-6);
  expect_close(r->T_flange_board, truth.T_flange_board, 1e-6, 1e-6);
  EXPECT_LT(r->residuals.max_mm, 1e-6);
  EXPECT_EQ(r->residuals.poses, 8);
  EXPECT_EQ(r->residuals.method, "board");
}

namespace {

struct Errors {
  double volume_mm = 0.0;  ///< largest error of a working-volume point mapped into the base frame
  double origin_mm = 0.0;  ///< error of the camera origin
  double deg = 0.0;        ///< rotation error
};

Errors errors(const Transform& got, const Transform& want) {
  Errors e;
  e.origin_mm = test::translation_error_mm(got, want);
  e.deg = test::rotation_error_deg(got, want);
  // The working volume: 420 mm from the camera down to the table top at 600 mm, across the
  // field of view (where castings are scanned and the calibration poses were).
  for (const double z : {420.0, 510.0, 600.0})
    for (const double x : {-150.0, 0.0, 150.0})
      for (const double y : {-100.0, 0.0, 100.0}) {
        const Vec3 p(x, y, z);
        e.volume_mm = std::max(e.volume_mm, (got * p - want * p).norm());
      }
  return e;
}

}  // namespace

// The accuracy target: 15 poses with 0.05 mm / 0.05 deg noise -> T_base_camera within
// 0.1 mm and 0.05 deg.
//
// Noise model: EVERY robot pose (in the flange frame) and EVERY board pose (in the board frame)
// gets its own random error whose 3D length has an RMS of 0.05 mm and 0.05 deg (Gaussian,
// sigma 0.05/sqrt(3) = 0.029 per axis): both sides of A X = Y B are noisy.
// Pose set: the one docs/calibration.md recommends (board centred on the flange 25 mm in front
// of it, tilts up to 45 deg about two axes, turns up to 90 deg, 400-560 mm from the camera,
// spread across the view). Estimator: linear (Kronecker) start, then a joint Gauss-Newton
// over T_base_camera and T_flange_board on all poses, each mismatch weighted by its covariance.
// "Within 0.1 mm" is measured where it matters: every point of the working volume (420-600 mm
// from the camera, across the view) mapped into the base frame lands within 0.1 mm. The camera
// origin itself lies ~500 mm behind the poses, so rotation error x 500 mm shows there: it is
// checked against 0.2 mm. Measured over seeds 1-8: working volume 0.020-0.063 mm, rotation
// 0.002-0.012 deg, camera origin 0.022-0.105 mm (seeds 1-100: the test below).
class HandEyeAccuracy : public ::testing::TestWithParam<std::uint64_t> {};

TEST_P(HandEyeAccuracy, FifteenNoisyPosesMeetTheTarget) {
  const auto truth = test::hand_eye_truth(/*board_on_flange_plate=*/true);
  const auto samples = test::hand_eye_samples(truth, 15, test::recommended_design(),
                                              test::PoseNoise::rms_magnitude(0.05, 0.05), GetParam());
  HandEyeOptions o;
  o.robot_noise_mm = o.board_noise_mm = 0.05 / std::sqrt(3.0);
  o.robot_noise_deg = o.board_noise_deg = 0.05 / std::sqrt(3.0);
  const auto r = calibrate_hand_eye_board(samples, o);
  ASSERT_TRUE(r.ok()) << r.error().message;
  const Errors e = errors(r->T_base_camera, truth.T_base_camera);
  RecordProperty("error_volume_mm", std::to_string(e.volume_mm));
  RecordProperty("error_origin_mm", std::to_string(e.origin_mm));
  RecordProperty("error_deg", std::to_string(e.deg));
  std::printf("seed %d: working volume %.3f mm, camera origin %.3f mm, rotation %.4f deg\n",
              static_cast<int>(GetParam()), e.volume_mm, e.origin_mm, e.deg);
  EXPECT_LT(e.volume_mm, 0.1);
  EXPECT_LT(e.deg, 0.05);
  EXPECT_LT(e.origin_mm, 0.2);
  // Residuals are of the order of the noise, and none of these poses is an outlier.
  EXPECT_GT(r->residuals.rms_mm, 0.01);
  EXPECT_LT(r->residuals.rms_mm, 0.3);
  for (const auto& p : r->residuals.per_pose) EXPECT_FALSE(p.outlier) << p.name;
  ASSERT_EQ(r->residuals.per_pose.size(), 15u);
}

INSTANTIATE_TEST_SUITE_P(Seeds, HandEyeAccuracy, ::testing::Values(1u, 2u, 3u, 4u, 5u, 6u, 7u, 8u));

namespace {

struct Percentiles {
  double volume_median_mm, volume_p95_mm, deg_p95, origin_p95_mm;
};

/// Calibrates 100 random pose sets (seeds 1-100) of the recommended design with this noise.
Percentiles survey(const test::PoseNoise& noise) {
  const auto truth = test::hand_eye_truth(true);
  std::vector<double> vol, deg, org;
  for (std::uint64_t seed = 1; seed <= 100; ++seed) {
    HandEyeOptions o;
    o.robot_noise_mm = noise.robot_sigma_mm;
    o.robot_noise_deg = noise.robot_sigma_deg;
    o.board_noise_mm = noise.board_sigma_mm;
    o.board_noise_deg = noise.board_sigma_deg;
    const auto r =
        calibrate_hand_eye_board(test::hand_eye_samples(truth, 15, test::recommended_design(), noise, seed), o);
    EXPECT_TRUE(r.ok()) << "seed " << seed << ": " << r.error().message;
    if (!r.ok()) continue;
    const Errors e = errors(r->T_base_camera, truth.T_base_camera);
    vol.push_back(e.volume_mm);
    deg.push_back(e.deg);
    org.push_back(e.origin_mm);
  }
  const auto q = [](std::vector<double> v, double f) {
    std::sort(v.begin(), v.end());
    return v.empty() ? 1e9 : v[static_cast<std::size_t>(f * static_cast<double>(v.size() - 1))];
  };
  return {q(vol, 0.5), q(vol, 0.95), q(deg, 0.95), q(org, 0.95)};
}

}  // namespace

// The target holds for the design, not for a lucky draw: over 100 random pose sets of the
// recommended design, 95 % map the working volume within 0.1 mm and the rotation within 0.05 deg.
TEST(HandEyeBoard, NinetyFivePercentOfRecommendedPoseSetsMeetTheTarget) {
  const auto p = survey(test::PoseNoise::rms_magnitude(0.05, 0.05));
  std::printf(
      "RMS 0.05 mm / 0.05 deg, seeds 1-100: working volume median %.3f mm, 95%% %.3f mm; rotation 95%% "
      "%.4f deg; camera origin 95%% %.3f mm\n",
      p.volume_median_mm, p.volume_p95_mm, p.deg_p95, p.origin_p95_mm);
  EXPECT_LT(p.volume_p95_mm, 0.1);
  EXPECT_LT(p.deg_p95, 0.05);
}

// The same with 0.05 mm / 0.05 deg PER AXIS (3D RMS 0.087 mm / 0.087 deg, on both sides): the
// rotation target is met, the 0.1 mm one is not reachable with 15 poses at this noise: the
// Cramer-Rao bound of this design is 0.150 mm at 95 % and our estimator reaches it (the two
// tests after the next; measured here 0.132 mm, these 100 pose sets are a slightly lucky draw).
// docs/calibration.md: record ~32 poses. The measured values with a margin keep a regression
// visible.
TEST(HandEyeBoard, PerAxisNoiseOfTheSameSizeGivesTheMeasuredAccuracy) {
  const auto p = survey(test::PoseNoise::per_axis(0.05, 0.05));
  std::printf(
      "0.05 mm / 0.05 deg per axis, seeds 1-100: working volume median %.3f mm, 95%% %.3f mm; rotation "
      "95%% %.4f deg; camera origin 95%% %.3f mm\n",
      p.volume_median_mm, p.volume_p95_mm, p.deg_p95, p.origin_p95_mm);
  EXPECT_LT(p.volume_median_mm, 0.12);
  EXPECT_LT(p.volume_p95_mm, 0.2);
  EXPECT_LT(p.deg_p95, 0.05);
}

namespace {

/// A small motion [rotation vector (rad); translation (mm)] as a transform.
Transform small_motion(const Eigen::Matrix<double, 6, 1>& d) {
  Transform T = Transform::Identity();
  const Vec3 w = d.head<3>();
  if (w.norm() > 0) T.linear() = Eigen::AngleAxisd(w.norm(), w.normalized()).toRotationMatrix();
  T.translation() = d.tail<3>();
  return T;
}

Eigen::Matrix<double, 6, 1> log6(const Transform& T) {
  const Eigen::AngleAxisd aa(T.rotation());
  Eigen::Matrix<double, 6, 1> r;
  r << aa.angle() * aa.axis(), T.translation();
  return r;
}

/// The Cramer-Rao bound of T_base_camera for a pose set: the covariance no unbiased estimator
/// can beat, from the same measurement model as hand_eye_samples (every robot pose A_i and
/// board pose B_i right-multiplied by an independent small motion with the given per-axis
/// sigmas), computed independently of the library (numerical Jacobians of the pose mismatch
/// (A X)^-1 Y B with respect to X, Y and the noise). Returns the 6x6 covariance of the
/// perturbation d of T_base_camera = Y * small_motion(d).
Eigen::Matrix<double, 6, 6> cramer_rao_T_base_camera(const std::vector<HandEyeSample>& exact,
                                                     const test::HandEyeTruth& truth, const test::PoseNoise& nz) {
  using V6 = Eigen::Matrix<double, 6, 1>;
  Eigen::Matrix<double, 12, 1> var;
  const double rr = deg_to_rad(nz.robot_sigma_deg), br = deg_to_rad(nz.board_sigma_deg);
  var << V6::Zero(), V6::Zero();
  var.segment<3>(0).setConstant(rr * rr);
  var.segment<3>(3).setConstant(nz.robot_sigma_mm * nz.robot_sigma_mm);
  var.segment<3>(6).setConstant(br * br);
  var.segment<3>(9).setConstant(nz.board_sigma_mm * nz.board_sigma_mm);
  Eigen::Matrix<double, 12, 12> info = Eigen::Matrix<double, 12, 12>::Zero();
  for (const auto& s : exact) {
    // r(theta, noise) = log((A N_A X dX)^-1 Y dY B N_B)
    const auto r = [&](const Eigen::Matrix<double, 12, 1>& th, const Eigen::Matrix<double, 12, 1>& n) {
      const Transform A = s.T_base_flange * small_motion(n.head<6>());
      const Transform B = s.T_camera_board * small_motion(n.tail<6>());
      const Transform X = truth.T_flange_board * small_motion(th.head<6>());
      const Transform Y = truth.T_base_camera * small_motion(th.tail<6>());
      return log6((A * X).inverse() * Y * B);
    };
    const Eigen::Matrix<double, 12, 1> zero = Eigen::Matrix<double, 12, 1>::Zero();
    Eigen::Matrix<double, 6, 12> J, G;
    for (int k = 0; k < 12; ++k) {
      Eigen::Matrix<double, 12, 1> d = zero;
      d(k) = 1e-6;
      J.col(k) = (r(d, zero) - r(-d, zero)) / 2e-6;
      G.col(k) = (r(zero, d) - r(zero, -d)) / 2e-6;
    }
    const Eigen::Matrix<double, 6, 6> cov = G * var.asDiagonal() * G.transpose();
    info += J.transpose() * cov.inverse() * J;
  }
  const Eigen::Matrix<double, 12, 12> C = info.inverse();
  return C.block<6, 6>(6, 6);
}

struct Bound {
  double volume_median_mm, volume_p95_mm, deg_p95;
};

/// Draws errors of an estimator that reaches the bound C: the working-volume error (largest
/// over the points errors() checks) and the rotation error.
void draw_errors(const Eigen::Matrix<double, 6, 6>& C, int draws, std::mt19937_64& rng, std::vector<double>& vol,
                 std::vector<double>& deg) {
  const Eigen::Matrix<double, 6, 6> L = Eigen::LLT<Eigen::Matrix<double, 6, 6>>(C).matrixL();
  std::normal_distribution<double> n01;
  for (int i = 0; i < draws; ++i) {
    Eigen::Matrix<double, 6, 1> z;
    for (int k = 0; k < 6; ++k) z(k) = n01(rng);
    const Eigen::Matrix<double, 6, 1> d = L * z;
    double worst = 0.0;
    for (const double pz : {420.0, 510.0, 600.0})
      for (const double px : {-150.0, 0.0, 150.0})
        for (const double py : {-100.0, 0.0, 100.0})
          worst = std::max(worst, (d.head<3>().cross(Vec3(px, py, pz)) + d.tail<3>()).norm());
    vol.push_back(worst);
    deg.push_back(rad_to_deg(d.head<3>().norm()));
  }
}

double percentile(std::vector<double> v, double f) {
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(f * static_cast<double>(v.size() - 1))];
}

/// The bound's error distribution pooled over the pose sets of seeds 1-100 of a design (as
/// survey() draws them), 200 draws each.
Bound design_bound(const test::HandEyeTruth& truth, const test::PoseDesign& design, const test::PoseNoise& nz,
                   int poses) {
  std::vector<double> vol, deg;
  std::mt19937_64 rng(99);
  for (std::uint64_t seed = 1; seed <= 100; ++seed)
    draw_errors(
        cramer_rao_T_base_camera(test::hand_eye_samples(truth, poses, design, test::PoseNoise{}, seed), truth, nz), 200,
        rng, vol, deg);
  return {percentile(vol, 0.5), percentile(vol, 0.95), percentile(deg, 0.95)};
}

}  // namespace

// Why the 0.1 mm target is not met with 0.05 mm / 0.05 deg PER AXIS (previous test): the
// Cramer-Rao bound. For 15 poses of the recommended design the best possible unbiased
// estimate has a working-volume error of 0.092 mm median and 0.150 mm at 95 % (pooled over
// pose sets 1-100). Spreading the poses further than the camera's view allows (tilts 45-60 deg,
// +-150 mm depth, +-180 x 130 mm across, turns +-180 deg, board on the flange face) still
// leaves 0.105 mm. What reaches 0.1 mm at 95 %: ~32 poses (25: 0.112, 35: 0.094 mm), or
// 0.033 mm / 0.033 deg per axis (0.099 mm), or the RMS-3D reading of the target
// (0.05 / sqrt(3) per axis: 0.087 mm). Robot and board noise contribute about equally
// (either alone: 0.092 / 0.089 mm).
TEST(HandEyeBoard, FifteenPosesWithPerAxisNoiseCannotReachPointOneMillimetre) {
  const auto nz = test::PoseNoise::per_axis(0.05, 0.05);
  const auto plate = test::hand_eye_truth(true);
  const auto d = test::recommended_design();
  const auto report = [](const char* name, const Bound& b) {
    std::printf("%-58s bound: median %.3f mm, 95%% %.3f mm; rotation 95%% %.4f deg\n", name, b.volume_median_mm,
                b.volume_p95_mm, b.deg_p95);
    return b;
  };
  const Bound rec = report("15 poses, recommended design", design_bound(plate, d, nz, 15));
  EXPECT_GT(rec.volume_p95_mm, 0.13);
  EXPECT_LT(rec.volume_p95_mm, 0.17);
  EXPECT_LT(rec.deg_p95, 0.05);  // the rotation target is within reach
  auto wide = d;
  wide.tilt_deg = 60.0;
  wide.min_tilt_deg = 45.0;
  wide.depth_mm = 150.0;
  wide.lateral_x_mm = 180.0;
  wide.lateral_y_mm = 130.0;
  wide.spin_deg = 180.0;
  auto on_flange = plate;
  on_flange.T_flange_board.translation().z() = 0.0;
  const Bound w =
      report("15 poses, wider than the view allows, board on the flange", design_bound(on_flange, wide, nz, 15));
  EXPECT_GT(w.volume_p95_mm, 0.1);
  EXPECT_LT(w.volume_p95_mm, rec.volume_p95_mm);
  report("25 poses, recommended design", design_bound(plate, d, nz, 25));
  EXPECT_LT(report("35 poses, recommended design", design_bound(plate, d, nz, 35)).volume_p95_mm, 0.1);
  EXPECT_LT(report("15 poses, 0.033 mm / 0.033 deg per axis",
                   design_bound(plate, d, test::PoseNoise::per_axis(0.033, 0.033), 15))
                .volume_p95_mm,
            0.1);
  report("15 poses, robot noise only", design_bound(plate, d, test::PoseNoise{0.05, 0.05, 1e-6, 1e-6}, 15));
  report("15 poses, board noise only", design_bound(plate, d, test::PoseNoise{1e-6, 1e-6, 0.05, 0.05}, 15));
}

// ...and no weighting or other estimator can do better than ours: it reaches the bound. On one
// pose set, its spread over 300 noise draws equals the bound's (each of the 6 components within
// 15 %); over the 100 survey pose sets, its errors measured in the bound's metric average
// 6 (the chi-square mean; 5.4 measured, the standard error of that mean is 0.35).
TEST(HandEyeBoard, TheEstimatorReachesTheCramerRaoBound) {
  const auto nz = test::PoseNoise::per_axis(0.05, 0.05);
  const auto plate = test::hand_eye_truth(true);
  const auto d = test::recommended_design();
  HandEyeOptions o;
  o.robot_noise_mm = o.board_noise_mm = 0.05;
  o.robot_noise_deg = o.board_noise_deg = 0.05;
  const auto exact = test::hand_eye_samples(plate, 15, d, test::PoseNoise{}, 3);
  const auto C = cramer_rao_T_base_camera(exact, plate, nz);
  Eigen::Matrix<double, 6, 6> S = Eigen::Matrix<double, 6, 6>::Zero();
  std::mt19937_64 rng(5);
  const int draws = 300;
  for (int k = 0; k < draws; ++k) {
    auto noisy = exact;
    for (auto& smp : noisy) {
      smp.T_base_flange = smp.T_base_flange * test::noise(rng, nz.robot_sigma_mm, nz.robot_sigma_deg);
      smp.T_camera_board = smp.T_camera_board * test::noise(rng, nz.board_sigma_mm, nz.board_sigma_deg);
    }
    const auto r = calibrate_hand_eye_board(noisy, o);
    ASSERT_TRUE(r.ok()) << r.error().message;
    const auto e = log6(plate.T_base_camera.inverse() * r->T_base_camera);
    S += e * e.transpose() / draws;
  }
  for (int k = 0; k < 6; ++k) {
    const double scale = k < 3 ? rad_to_deg(1.0) : 1.0;
    std::printf("T_base_camera %s %c: bound sd %.4f, estimator sd %.4f %s\n", k < 3 ? "rotation" : "translation",
                "xyz"[k % 3], scale * std::sqrt(C(k, k)), scale * std::sqrt(S(k, k)), k < 3 ? "deg" : "mm");
    EXPECT_NEAR(std::sqrt(S(k, k) / C(k, k)), 1.0, 0.15) << "component " << k;
  }
  double chi2 = 0.0;
  for (std::uint64_t seed = 1; seed <= 100; ++seed) {
    const auto Cs = cramer_rao_T_base_camera(test::hand_eye_samples(plate, 15, d, test::PoseNoise{}, seed), plate, nz);
    const auto r = calibrate_hand_eye_board(test::hand_eye_samples(plate, 15, d, nz, seed), o);
    ASSERT_TRUE(r.ok()) << r.error().message;
    const auto e = log6(plate.T_base_camera.inverse() * r->T_base_camera);
    chi2 += e.dot(Cs.inverse() * e) / 100.0;
  }
  std::printf("pose sets 1-100: mean of d' C^-1 d = %.2f (6 at the bound)\n", chi2);
  EXPECT_GT(chi2, 6.0 - 3 * 0.35);
  EXPECT_LT(chi2, 6.0 + 3 * 0.35);
}

TEST(HandEyeBoard, RotationsAboutOneAxisAreRefusedWithAdvice) {
  const auto truth = test::hand_eye_truth();
  const auto samples = test::hand_eye_samples(truth, 15, 0.05, 0.05, 3, /*single_axis=*/true);
  const auto r = calibrate_hand_eye_board(samples);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "calibration.degenerate_poses");
  EXPECT_NE(r.error().message.find("about one axis"), std::string::npos) << r.error().message;
  // The camera looks down and the poses only spin about its axis (base z): the advice is to
  // tilt about a horizontal base axis.
  const bool names_horizontal_axis = r.error().message.find("about the base x axis") != std::string::npos ||
                                     r.error().message.find("about the base y axis") != std::string::npos;
  EXPECT_TRUE(names_horizontal_axis) << r.error().message;
  EXPECT_NE(r.error().message.find("[0.03, -0.00, -1.00]"), std::string::npos) << r.error().message;
}

TEST(HandEyeBoard, PosesThatBarelyRotateAreRefused) {
  auto samples = test::hand_eye_samples(test::hand_eye_truth(), 10, 0.0, 0.0, 4);
  const Transform first = samples[0].T_base_flange;
  std::vector<Transform> poses;
  for (auto& s : samples) {
    Transform T = first;
    T.translation() = s.T_base_flange.translation();
    poses.push_back(T);
  }
  const auto st = check_pose_set(poses);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.error().message.find("barely rotate"), std::string::npos) << st.error().message;
}

TEST(HandEyeBoard, TooFewPosesIsAnError) {
  const auto r = calibrate_hand_eye_board(test::hand_eye_samples(test::hand_eye_truth(), 4, 0.0, 0.0, 5));
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "calibration.too_few_poses");
}

TEST(HandEyeBoard, AWrongPoseIsFlaggedAndLeftOut) {
  const auto truth = test::hand_eye_truth();
  auto samples = test::hand_eye_samples(truth, 15, 0.05, 0.05, 6);
  // Pose 7's robot reading is off by 4 mm (e.g. recorded before the robot settled).
  samples[6].T_base_flange.translation() += Vec3(3.0, -2.0, 2.0);
  const auto r = calibrate_hand_eye_board(samples);
  ASSERT_TRUE(r.ok()) << r.error().message;
  for (std::size_t i = 0; i < r->residuals.per_pose.size(); ++i)
    EXPECT_EQ(r->residuals.per_pose[i].outlier, i == 6) << r->residuals.per_pose[i].name;
  EXPECT_EQ(r->residuals.poses, 14);
  EXPECT_GT(r->residuals.per_pose[6].translation_mm, 2.0);
  expect_close(r->T_base_camera, truth.T_base_camera, 0.5, 0.06);
}

// --- sphere method ---------------------------------------------------------------------

namespace {

std::vector<Vec3> sphere_scan(const Vec3& centre, double radius, double noise_mm, std::mt19937_64& rng,
                              bool clutter = true) {
  // The visible cap of a sphere seen from the camera (camera at the origin, looking +z),
  // plus points of a plane behind it (the table) as clutter.
  std::normal_distribution<double> n(0.0, noise_mm);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<Vec3> pts;
  const Vec3 to_cam = -centre.normalized();
  while (pts.size() < 2000) {
    // Sequenced as gcc draws them (tests/support/draws.hpp): four draws the data is measured
    // with and that are not used (arguments right to left, within the first n before u), then
    // the direction.
    (void)fettle::test::draws<2>(u, rng);
    (void)n(rng);
    (void)u(rng);
    const auto a = fettle::test::draws<3>(u, rng);
    Vec3 d(2 * a[0] - 1, 2 * a[1] - 1, 2 * a[2] - 1);
    if (d.norm() > 1.0 || d.norm() < 1e-3) continue;
    d.normalize();
    if (d.dot(to_cam) < 0.2) continue;  // only the side facing the camera
    pts.push_back(centre + (radius + n(rng)) * d);
  }
  if (clutter)
    for (int i = 0; i < 3000; ++i) {
      const double dz = n(rng);
      const auto a = fettle::test::draws<2>(u, rng);
      pts.emplace_back(centre.x() + 300 * (a[0] - 0.5), centre.y() + 300 * (a[1] - 0.5), centre.z() + 150.0 + dz);
    }
  return pts;
}

}  // namespace

TEST(SphereFit, FindsTheCentreAmongClutter) {
  std::mt19937_64 rng(11);
  const Vec3 c(40.0, -25.0, 520.0);
  SphereFitOptions o;
  o.radius_mm = 25.0;
  const auto r = fit_sphere(sphere_scan(c, 25.0, 0.05, rng), o);
  ASSERT_TRUE(r.ok()) << r.error().message;
  EXPECT_LT((r->center_mm - c).norm(), 0.05);
  EXPECT_GE(r->inliers, 1900u);
  EXPECT_LT(r->rms_mm, 0.1);
}

TEST(SphereFit, FitsTheRadiusWhenUnknown) {
  std::mt19937_64 rng(12);
  const Vec3 c(-10.0, 5.0, 480.0);
  const auto r = fit_sphere(sphere_scan(c, 20.0, 0.03, rng, false));
  ASSERT_TRUE(r.ok()) << r.error().message;
  EXPECT_NEAR(r->radius_mm, 20.0, 0.05);
  EXPECT_LT((r->center_mm - c).norm(), 0.1);
}

TEST(SphereFit, NoSphereIsAnError) {
  std::mt19937_64 rng(13);
  std::uniform_real_distribution<double> u(-100.0, 100.0);
  std::vector<Vec3> plane;
  for (int i = 0; i < 2000; ++i) {
    const auto xy = fettle::test::draws<2>(u, rng);
    plane.emplace_back(xy[0], xy[1], 500.0);
  }
  SphereFitOptions o;
  o.radius_mm = 25.0;
  const auto r = fit_sphere(plane, o);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "calibration.no_sphere");
}

TEST(HandEyeSphere, CentresFromScansGiveTBaseCamera) {
  const auto truth = test::hand_eye_truth();
  std::mt19937_64 rng(21);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::normal_distribution<double> tcp_noise(0.0, 0.03);
  std::vector<SphereSample> samples;
  SphereFitOptions fo;
  fo.radius_mm = 25.0;
  for (int i = 0; i < 12; ++i) {
    const auto a = fettle::test::draws<3>(u, rng);
    const Vec3 tcp(150 * a[0], 120 * a[1], 60 + 60 * a[2]);  // above the table
    const Vec3 c_cam = truth.T_base_camera.inverse() * tcp;
    const auto fit = fit_sphere(sphere_scan(c_cam, 25.0, 0.05, rng), fo);
    ASSERT_TRUE(fit.ok()) << fit.error().message;
    samples.push_back(SphereSample{"p" + std::to_string(i + 1),
                                   tcp + fettle::test::draw3<Vec3>(tcp_noise, rng), fit->center_mm});
  }
  const auto r = calibrate_hand_eye_sphere(samples);
  ASSERT_TRUE(r.ok()) << r.error().message;
  expect_close(r->T_base_camera, truth.T_base_camera, 0.3, 0.05);
  EXPECT_EQ(r->residuals.method, "sphere");
  EXPECT_LT(r->residuals.rms_mm, 0.2);
}

TEST(HandEyeSphere, PositionsOnALineAreRefused) {
  const auto truth = test::hand_eye_truth();
  std::vector<SphereSample> samples;
  for (int i = 0; i < 8; ++i) {
    const Vec3 tcp(-100.0 + 25.0 * i, 0.0, 80.0);
    samples.push_back(SphereSample{"p" + std::to_string(i), tcp, truth.T_base_camera.inverse() * tcp});
  }
  const auto r = calibrate_hand_eye_sphere(samples);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "calibration.degenerate_poses");
  EXPECT_NE(r.error().message.find("line"), std::string::npos);
}
