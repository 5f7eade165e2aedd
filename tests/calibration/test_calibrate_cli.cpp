// `fettle calibrate` as an integrator runs it, on rendered images, poses and scans with a
// known ground truth.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>
#include <string>

#include <opencv2/imgcodecs.hpp>

#include "fettle/config/calibration.hpp"
#include "synthetic.hpp"
#include "../support/draws.hpp"

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using namespace fettle;  // NOLINT

namespace {

struct CliRun {
  int exit_code;
  std::string output;  // stdout and stderr
};

CliRun run_fettle(const std::string& args) {
  const std::string cmd = std::string(FETTLE_BIN_DIR) + "/fettle " + args + " 2>&1";
  FILE* pipe = ::popen(cmd.c_str(), "r");
  EXPECT_NE(pipe, nullptr);
  std::string out;
  std::array<char, 4096> buf{};
  while (std::fgets(buf.data(), buf.size(), pipe) != nullptr) out += buf.data();
  const int status = ::pclose(pipe);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

class CalibrateCli : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("fettle-calibrate-" + std::to_string(::getpid()) + "-" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override {
    if (!HasFailure()) fs::remove_all(dir_);
  }
  fs::path dir_;
  const vision::calibration::BoardSpec board_{9, 6, 20.0};
};

std::string csv_row(const std::string& name, const Transform& T) {
  const Pose p = Pose::from_transform(T);
  char buf[256];
  std::snprintf(buf, sizeof buf, "%s,%.6f,%.6f,%.6f,%.12f,%.12f,%.12f,%.12f\n", name.c_str(), p.position_mm.x(),
                p.position_mm.y(), p.position_mm.z(), p.orientation.w(), p.orientation.x(), p.orientation.y(),
                p.orientation.z());
  return buf;
}

/// Board poses in view of the test camera, tilted about several axes.
std::vector<Transform> board_poses(const vision::calibration::BoardSpec& board, int n, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<Transform> out;
  for (int i = 0; i < n; ++i) {
    const auto a = fettle::test::draws<6>(u, rng);
    out.push_back(test::board_pose_facing_camera(board, 470 + 40 * a[0], 60 * a[1], 40 * a[2], deg_to_rad(25 * a[3]),
                                                 deg_to_rad(25 * a[4]), deg_to_rad(40 * a[5])));
  }
  return out;
}

}  // namespace

TEST_F(CalibrateCli, IntrinsicsFromImagesWritesACalibrationFile) {
  const auto cam = test::test_camera();
  const auto poses = board_poses(board_, 9, 1);
  for (std::size_t i = 0; i < poses.size(); ++i)
    cv::imwrite((dir_ / ("view" + std::to_string(i + 10) + ".png")).string(),
                test::render_board(board_, cam, poses[i], 0.0, 1.0, static_cast<unsigned>(i + 1)));
  cv::imwrite((dir_ / "view99-blurred.png").string(), test::render_board(board_, cam, poses[0], 3.5));
  const auto out = dir_ / "cal.toml";
  const auto r = run_fettle("calibrate intrinsics --images " + dir_.string() + " --board 9x6 --square-mm 20 --out " +
                            out.string() + " --id test-intrinsics");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_THAT(r.output, HasSubstr("SKIPPED  view99-blurred.png  blurred"));
  EXPECT_THAT(r.output, HasSubstr("9 views used"));
  const auto c = config::load_calibration(out);
  EXPECT_EQ(c.id, "test-intrinsics");
  EXPECT_FALSE(c.date.empty());
  ASSERT_TRUE(c.intrinsics);
  EXPECT_NEAR(c.intrinsics->fx_px, cam.fx_px, 0.005 * cam.fx_px);
  EXPECT_NEAR(c.intrinsics->cx_px, cam.cx_px, 5.0);
  EXPECT_EQ(c.intrinsics->views, 9);
  EXPECT_GT(c.intrinsics->rms_px, 0.0);
}

TEST_F(CalibrateCli, TooFewViewsExitsOneWithTheReasons) {
  const auto cam = test::test_camera();
  const auto poses = board_poses(board_, 2, 2);
  for (std::size_t i = 0; i < poses.size(); ++i)
    cv::imwrite((dir_ / ("v" + std::to_string(i) + ".png")).string(), test::render_board(board_, cam, poses[i]));
  cv::imwrite((dir_ / "empty.png").string(), cv::Mat(772, 1032, CV_8UC1, cv::Scalar(90)));
  const auto r = run_fettle("calibrate intrinsics --images " + dir_.string() + " --board 9x6 --square-mm 20 --out " +
                            (dir_ / "cal.toml").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_THAT(r.output, HasSubstr("only 2 of 3 views are usable"));
  EXPECT_THAT(r.output, HasSubstr("empty.png: no complete 9x6 chessboard found"));
  EXPECT_FALSE(fs::exists(dir_ / "cal.toml"));
}

TEST_F(CalibrateCli, BadBoardIsAUserError) {
  const auto r = run_fettle("calibrate intrinsics --images " + dir_.string() + " --board 9by6 --square-mm 20 --out " +
                            (dir_ / "c.toml").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_THAT(r.output, HasSubstr("is not COLSxROWS"));
}

// The end-to-end runs of --live are in test_calibrate_live.cpp (simulated robot and camera).
TEST_F(CalibrateCli, LiveHandEyeSaysWhatItNeeds) {
  const auto r = run_fettle("calibrate hand-eye --live --out " + (dir_ / "c.toml").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_THAT(r.output, HasSubstr("--live needs --config CELL.toml"));
  const auto r2 = run_fettle("calibrate hand-eye --live --config x.toml --out " + (dir_ / "c.toml").string());
  EXPECT_EQ(r2.exit_code, 1) << r2.output;
  EXPECT_THAT(r2.output, HasSubstr("exactly one of --poses FILE or --auto N"));
}

TEST_F(CalibrateCli, HandEyeFromImagesFindsTBaseCamera) {
  const auto truth = test::hand_eye_truth();
  const auto cam = test::test_camera();
  config::CalibrationFile intr;
  intr.id = "intr";
  intr.date = "2026-11-22";
  intr.intrinsics = cam;
  config::write_calibration(dir_ / "intrinsics.toml", intr);
  fs::create_directories(dir_ / "img");
  std::ofstream csv(dir_ / "robot.csv");
  csv << "name,x_mm,y_mm,z_mm,qw,qx,qy,qz\n";
  const auto poses = board_poses(board_, 12, 3);
  for (std::size_t i = 0; i < poses.size(); ++i) {
    const std::string name = "pose" + std::to_string(i + 1) + ".png";
    cv::imwrite((dir_ / "img" / name).string(),
                test::render_board(board_, cam, poses[i], 0.0, 1.0, static_cast<unsigned>(i + 7)));
    csv << csv_row(name, truth.T_base_camera * poses[i] * truth.T_flange_board.inverse());
  }
  csv.close();
  const auto out = dir_ / "cal.toml";
  const auto r = run_fettle("calibrate hand-eye --robot-poses " + (dir_ / "robot.csv").string() + " --images " +
                            (dir_ / "img").string() + " --calibration " + (dir_ / "intrinsics.toml").string() +
                            " --board 9x6 --square-mm 20 --out " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_THAT(r.output, HasSubstr("12 poses used"));
  const auto c = config::load_calibration(out);
  ASSERT_TRUE(c.T_base_camera);
  ASSERT_TRUE(c.intrinsics);  // kept from --calibration
  EXPECT_LT(test::translation_error_mm(*c.T_base_camera, truth.T_base_camera), 1.0) << r.output;
  EXPECT_LT(test::rotation_error_deg(*c.T_base_camera, truth.T_base_camera), 0.1) << r.output;
  ASSERT_TRUE(c.hand_eye);
  EXPECT_EQ(c.hand_eye->method, "board");
  EXPECT_EQ(c.hand_eye->per_pose.size(), 12u);
}

TEST_F(CalibrateCli, HandEyeFromBoardPosesAndDegenerateAdvice) {
  const auto truth = test::hand_eye_truth();
  for (const bool single_axis : {false, true}) {
    const auto samples = test::hand_eye_samples(truth, 10, 0.0, 0.0, 9, single_axis);
    std::ofstream robot(dir_ / "robot.csv"), seen(dir_ / "board.csv");
    for (const auto& s : samples) {
      robot << csv_row(s.name, s.T_base_flange);
      seen << csv_row(s.name, s.T_camera_board);
    }
    robot.close();
    seen.close();
    const auto out = dir_ / "cal.toml";
    const auto r = run_fettle("calibrate hand-eye --robot-poses " + (dir_ / "robot.csv").string() + " --board-poses " +
                              (dir_ / "board.csv").string() + " --out " + out.string() + " --id he-test");
    if (single_axis) {
      EXPECT_EQ(r.exit_code, 1) << r.output;
      EXPECT_THAT(r.output, HasSubstr("about one axis"));
      EXPECT_THAT(r.output, HasSubstr("Add poses"));
    } else {
      ASSERT_EQ(r.exit_code, 0) << r.output;
      const auto c = config::load_calibration(out);
      ASSERT_TRUE(c.T_base_camera);
      EXPECT_LT(test::translation_error_mm(*c.T_base_camera, truth.T_base_camera), 1e-3);
      EXPECT_EQ(c.id, "he-test");
      const auto show = run_fettle("calibrate show " + out.string());
      EXPECT_EQ(show.exit_code, 0) << show.output;
      EXPECT_THAT(show.output, HasSubstr("id he-test"));
    }
  }
}

TEST_F(CalibrateCli, HandEyeFromSphereScans) {
  const auto truth = test::hand_eye_truth();
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::normal_distribution<double> n(0.0, 0.05);
  std::ofstream csv(dir_ / "tcp.csv");
  for (int i = 0; i < 10; ++i) {
    const auto a = fettle::test::draws<3>(u, rng);
    const Vec3 tcp(150 * a[0], 120 * a[1], 60 + 60 * a[2]);
    const Vec3 c = truth.T_base_camera.inverse() * tcp;
    // Every other scan as a PCD file (read through vision::load_cloud), the rest as .xyz text.
    const std::string name = "s" + std::to_string(i) + (i % 2 ? ".pcd" : ".xyz");
    std::ostringstream points;
    int count = 0;
    for (int k = 0; k < 1500; ++k) {
      Vec3 d = fettle::test::draw3<Vec3>(u, rng);
      if (d.norm() > 1.0 || d.norm() < 0.01) continue;
      d.normalize();
      if (d.z() > -0.2) continue;  // the half facing the camera (camera looks along +z)
      const Vec3 p = c + (25.0 + n(rng)) * d;
      points << p.x() << " " << p.y() << " " << p.z() << "\n";
      ++count;
    }
    std::ofstream cloud(dir_ / name);
    if (i % 2)
      cloud << "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH " << count
            << "\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS " << count << "\nDATA ascii\n";
    cloud << points.str();
    csv << name << "," << tcp.x() << "," << tcp.y() << "," << tcp.z() << "\n";
  }
  csv.close();
  const auto out = dir_ / "cal.toml";
  const auto r = run_fettle("calibrate hand-eye --robot-poses " + (dir_ / "tcp.csv").string() + " --clouds " +
                            dir_.string() + " --sphere-radius-mm 25 --out " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto c = config::load_calibration(out);
  ASSERT_TRUE(c.T_base_camera);
  EXPECT_LT(test::translation_error_mm(*c.T_base_camera, truth.T_base_camera), 0.3) << r.output;
  EXPECT_LT(test::rotation_error_deg(*c.T_base_camera, truth.T_base_camera), 0.05) << r.output;
  ASSERT_TRUE(c.hand_eye);
  EXPECT_EQ(c.hand_eye->method, "sphere");
}

TEST_F(CalibrateCli, ShowChecksTheShippedSimulatorFile) {
  const auto r = run_fettle("calibrate show " + std::string(FETTLE_SOURCE_DIR) + "/config/calibration.sim.toml");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  EXPECT_THAT(r.output, HasSubstr("id sim-nominal-1"));
}

// `fettle calibrate projector` on rendered Gray-code images of 5 board poses (the documented
// layout: one directory per pose, white, black, col_00, col_00_inv, ... as .pgm): the
// projector's intrinsics are estimated from the decoded corners, then T_camera_projector.
// With 5 poses the estimated principal point is the weak part; this pose set gives 0.59 mm and
// 0.08 deg, the tolerance is 1.5 mm and 0.5 deg; a wrong decode is off by far more.
TEST_F(CalibrateCli, ProjectorFromGrayCodeImages) {
  auto scene = test::structured_light_scene();
  scene.blur_sigma_px = 0.8;
  scene.noise_grey = 1.5;
  const auto layout = vision::calibration::GrayCodeLayout::for_projector(1280, 800);
  config::CalibrationFile intr;
  intr.id = "intr";
  intr.date = "2026-11-22";
  intr.intrinsics = scene.camera;
  config::write_calibration(dir_ / "intrinsics.toml", intr);
  const auto poses = test::structured_light_board_poses(scene, 5, 11);
  ASSERT_EQ(poses.size(), 5u);
  for (std::size_t i = 0; i < poses.size(); ++i) {
    scene.T_camera_board = poses[i];
    scene.seed = static_cast<unsigned>(i + 1);
    const fs::path pose_dir = dir_ / "img" / ("pose0" + std::to_string(i + 1));
    fs::create_directories(pose_dir);
    for (const auto& im : test::render_structured_light(scene, layout).images) {
      const cv::Mat m(im.height_px, im.width_px, CV_8UC1, const_cast<std::uint8_t*>(im.pixels.data()));  // NOLINT
      cv::imwrite((pose_dir / (im.name + ".pgm")).string(), m);  // any image type; PGM is fast
    }
  }
  const std::string args = "calibrate projector --images " + (dir_ / "img").string() + " --board 9x6 --square-mm 20 " +
                           "--projector 1280x800 --camera-intrinsics " + (dir_ / "intrinsics.toml").string() +
                           " --out " + (dir_ / "cal.toml").string();
  auto r = run_fettle(args);
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_THAT(r.output, HasSubstr("used     pose03  54 of 54 corners decoded"));
  const auto c = config::load_calibration(dir_ / "cal.toml");
  ASSERT_TRUE(c.T_camera_projector);
  ASSERT_TRUE(c.intrinsics);  // kept from --camera-intrinsics
  const auto truth = test::structured_light_T_camera_projector();
  const double t_mm = test::translation_error_mm(*c.T_camera_projector, truth);
  const double r_deg = test::rotation_error_deg(*c.T_camera_projector, truth);
  std::printf("fettle calibrate projector, 5 poses: T_camera_projector error %.3f mm, %.4f deg, stereo rms %.3f px\n",
              t_mm, r_deg, c.stereo_rms_px);
  EXPECT_LT(t_mm, 1.5) << r.output;
  EXPECT_LT(r_deg, 0.5) << r.output;
  EXPECT_GT(c.stereo_rms_px, 0.0);
  EXPECT_LT(c.stereo_rms_px, 0.3);

  // A pattern image missing: the error names the directory and the image.
  fs::remove(dir_ / "img" / "pose02" / "col_03_inv.pgm");
  r = run_fettle(args);
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_THAT(r.output, HasSubstr("pose02: no image named col_03_inv"));
  // An image of another size: the error names the file and both sizes.
  cv::imwrite((dir_ / "img" / "pose02" / "col_03_inv.pgm").string(), cv::Mat(400, 600, CV_8UC1, cv::Scalar(0)));
  r = run_fettle(args);
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_THAT(r.output, HasSubstr("col_03_inv.pgm: 600x400 px, but"));
  // Too few usable poses (all but two without the projector's light): each skip says why.
  for (const auto* pose : {"pose02", "pose03", "pose04"})
    for (const auto* name : {"white", "col_00", "col_00_inv", "col_03_inv"}) {
      const auto black = cv::imread((dir_ / "img" / pose / "black.pgm").string(), cv::IMREAD_GRAYSCALE);
      cv::imwrite((dir_ / "img" / pose / (std::string(name) + ".pgm")).string(), black);
    }
  r = run_fettle(args);
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_THAT(r.output, HasSubstr("only 2 of 5 board poses usable, need 3"));
  EXPECT_THAT(r.output, HasSubstr("SKIPPED  pose03"));
}

TEST_F(CalibrateCli, ProjectorPatternsAreWrittenInTheDocumentedNames) {
  const auto r = run_fettle("calibrate projector-patterns --projector 640x480 --out " + (dir_ / "p").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_THAT(r.output, HasSubstr("wrote 40 pattern images (640x480 px)"));
  const auto first = cv::imread((dir_ / "p" / "col_00.png").string(), cv::IMREAD_GRAYSCALE);
  ASSERT_EQ(first.cols, 640);
  EXPECT_EQ(first.at<std::uint8_t>(0, 0), 0);      // column 0: Gray code 0
  EXPECT_EQ(first.at<std::uint8_t>(0, 639), 255);  // the most significant bit is set in the right half
  EXPECT_TRUE(fs::exists(dir_ / "p" / "row_08_inv.png"));
  EXPECT_FALSE(fs::exists(dir_ / "p" / "row_09.png"));
}
