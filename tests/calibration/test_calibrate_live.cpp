// `fettle calibrate hand-eye --live` end to end: the CLI drives the simulated robot controller
// (robot protocol on 127.0.0.1, ephemeral port) through poses, scans the sphere it holds with
// the simulated GigE Vision camera (UDP 3956 on 127.0.0.1) and solves T_base_camera, which is
// compared with the simulator's truth (deliberately off the nominal calibration the cell names).
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <mutex>
#include <regex>
#include <sstream>
#include <string>
#include <thread>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>

#include "fettle/config/calibration.hpp"
#include "fettle/sim/camera.hpp"
#include "fettle/sim/robot.hpp"

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using namespace fettle;  // NOLINT

namespace {

struct CliRun {
  int exit_code;
  std::string output;
};

CliRun run_fettle(const std::string& args) {
  const std::string cmd = std::string(FETTLE_BIN_DIR) + "/fettle " + args + " 2>&1";
  FILE* pipe = ::popen(cmd.c_str(), "r");
  EXPECT_NE(pipe, nullptr);
  std::string out;
  std::array<char, 4096> buf{};
  while (pipe != nullptr && std::fgets(buf.data(), buf.size(), pipe) != nullptr) out += buf.data();
  const int status = pipe != nullptr ? ::pclose(pipe) : -1;
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

std::string read_text(const fs::path& p) {
  std::ifstream in(p);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

/// The simulator's camera 600 mm above the table looking down (config/calibration.sim.toml),
/// plus a mounting error the calibration has to find: 2.5 mm and 0.6 deg.
Transform true_T_base_camera() {
  Transform T = Transform::Identity();
  T.linear() = (Eigen::AngleAxisd(deg_to_rad(0.6), Vec3(0.3, -0.8, 0.5).normalized()) *
                Eigen::AngleAxisd(deg_to_rad(180.0), Vec3::UnitX()))
                   .toRotationMatrix();
  T.translation() = Vec3(1.5, -1.2, 601.5);
  return T;
}

/// A smaller range camera than the real one (fast to render and send), same field of view.
sim::RangeImageModel model() {
  sim::RangeImageModel m;
  m.width = 1032;
  m.height = 772;
  m.focal_px = 1200.0;
  m.cx_px = 515.5;
  m.cy_px = 385.5;
  return m;
}

constexpr double kSphereRadiusMm = 25.0;

/// The simulated cell: a robot controller holding a sphere at its TCP, and a camera that sees it.
class LiveCell {
 public:
  LiveCell() {
    sim::RobotSimOptions ro;
    ro.speedup = 0.0;  // moves complete at once
    robot_ = std::make_unique<sim::RobotSim>(io_, ro);
    robot_->start();
    sim::RangeImageSource src;
    src.model = model();
    src.description = "table and a sphere held by the simulated robot";
    src.render = [this](double slide_mm, std::vector<std::uint16_t>& range) {
      sim::SyntheticScene scene;
      {
        const std::lock_guard lock(mutex_);
        scene = scene_;
      }
      sim::synthetic_range_source(model(), scene).render(slide_mm, range);
    };
    {
      const std::lock_guard lock(mutex_);
      scene_.plane_z_mm = 600.0;                 // the table top
      scene_.sphere_center_mm[2] = 5000.0;       // not in view until the robot brings it
      scene_.sphere_radius_mm = kSphereRadiusMm;
    }
    camera_ = std::make_unique<sim::SimulatedCamera>(sim::SimulatedCameraOptions{}, std::move(src));
    // The sphere follows the robot's TCP; the camera re-renders before the robot reports DONE.
    robot_->on_arrived([this](const Trajectory& t) {
      if (t.points.empty()) return;
      const Vec3 c = true_T_base_camera().inverse() * t.points.back().T_base_tool.position_mm;
      {
        const std::lock_guard lock(mutex_);
        for (int k = 0; k < 3; ++k) scene_.sphere_center_mm[k] = c[k];
        ++moves_;
      }
      camera_->set_slide_position_mm(0.0);
    });
    thread_ = std::thread([this] { io_.run(); });
  }
  ~LiveCell() {
    work_.reset();
    io_.stop();
    thread_.join();
  }
  LiveCell(const LiveCell&) = delete;
  LiveCell& operator=(const LiveCell&) = delete;

  [[nodiscard]] int robot_port() const { return robot_->port(); }
  int moves() {
    const std::lock_guard lock(mutex_);
    return moves_;
  }

 private:
  boost::asio::io_context io_;
  boost::asio::executor_work_guard<boost::asio::io_context::executor_type> work_ =
      boost::asio::make_work_guard(io_);
  std::unique_ptr<sim::RobotSim> robot_;
  std::unique_ptr<sim::SimulatedCamera> camera_;
  std::mutex mutex_;
  sim::SyntheticScene scene_;
  int moves_ = 0;
  std::thread thread_;
};

class CalibrateLive : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("fettle-calibrate-live-" + std::to_string(::getpid()) + "-" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override {
    if (!HasFailure()) fs::remove_all(dir_);
  }

  /// The simulator's cell file with the robot on `robot_port`, absolute paths, and the
  /// simulator's nominal calibration file.
  fs::path write_cell(int robot_port) {
    const fs::path src = fs::path(FETTLE_SOURCE_DIR) / "config";
    std::string cell = read_text(src / "cell.sim.toml");
    cell = std::regex_replace(cell, std::regex(R"(port = 30100)"), "port = " + std::to_string(robot_port));
    cell = std::regex_replace(cell, std::regex(R"("parts/pump-body.toml")"),
                              "\"" + (src / "parts/pump-body.toml").string() + "\"");
    cell = std::regex_replace(cell, std::regex(R"("calibration.sim.toml")"),
                              "\"" + (src / "calibration.sim.toml").string() + "\"");
    cell = std::regex_replace(cell, std::regex(R"("\.\./var/fettle/fettled.sock")"),
                              "\"" + (dir_ / "fettled.sock").string() + "\"");
    cell = std::regex_replace(cell, std::regex(R"("\.\./var/fettle")"), "\"" + (dir_ / "var").string() + "\"");
    const fs::path out = dir_ / "cell.toml";
    std::ofstream(out) << cell;
    return out;
  }

  fs::path dir_;
};

}  // namespace

TEST_F(CalibrateLive, AutoPosesFindTheSimulatorsCameraPose) {
  LiveCell cell;
  const fs::path cfg = write_cell(cell.robot_port());
  const fs::path out = dir_ / "cal.toml";
  const auto r = run_fettle("calibrate hand-eye --live --config " + cfg.string() +
                            " --auto 10 --sphere-radius-mm 25 --settle-ms 0 --out " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(cell.moves(), 10);
  EXPECT_THAT(r.output, HasSubstr("pose 10/10"));
  EXPECT_THAT(r.output, HasSubstr("10 poses used"));
  const auto c = config::load_calibration(out);
  ASSERT_TRUE(c.T_base_camera.has_value());
  ASSERT_TRUE(c.hand_eye.has_value());
  EXPECT_EQ(c.hand_eye->method, "sphere");
  ASSERT_TRUE(c.intrinsics.has_value());  // carried over from the cell's calibration file
  const Transform truth = true_T_base_camera();
  // The nominal file is 2.5 mm / 0.6 deg off; the scans must find the truth.
  const double e_deg = rad_to_deg(rotation_angle_rad(c.T_base_camera->inverse() * truth));
  double e_volume_mm = 0.0;
  for (const double z : {450.0, 520.0, 600.0})
    for (const double x : {-150.0, 0.0, 150.0})
      for (const double y : {-100.0, 0.0, 100.0}) {
        const Vec3 p(x, y, z);
        e_volume_mm = std::max(e_volume_mm, (*c.T_base_camera * p - truth * p).norm());
      }
  const double e_origin_mm = (c.T_base_camera->translation() - truth.translation()).norm();
  std::printf("live sphere calibration: working volume %.3f mm, camera origin %.3f mm, rotation %.4f deg\n",
              e_volume_mm, e_origin_mm, e_deg);
  EXPECT_LT(e_volume_mm, 0.1);
  EXPECT_LT(e_deg, 0.05);
  EXPECT_LT(e_origin_mm, 0.3);
  EXPECT_LT(c.hand_eye->rms_mm, 0.1);
}

TEST_F(CalibrateLive, PosesFromAFile) {
  LiveCell cell;
  const fs::path cfg = write_cell(cell.robot_port());
  std::ostringstream poses;
  const std::array<std::array<double, 3>, 7> p = {{{0, 0, 100},
                                                   {-120, -80, 150},
                                                   {120, -80, 100},
                                                   {120, 80, 200},
                                                   {-120, 80, 120},
                                                   {0, 90, 180},
                                                   {-60, -40, 220}}};
  for (std::size_t i = 0; i < p.size(); ++i)
    poses << "[[pose]]\nname = \"p" << i + 1 << "\"\nposition_mm = [" << p[i][0] << ".0, " << p[i][1] << ".0, "
          << p[i][2] << ".0]\n\n";
  std::ofstream(dir_ / "poses.toml") << poses.str();
  const fs::path out = dir_ / "cal.toml";
  const auto r = run_fettle("calibrate hand-eye --live --config " + cfg.string() + " --poses " +
                            (dir_ / "poses.toml").string() + " --sphere-radius-mm 25 --settle-ms 0 --out " +
                            out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_THAT(r.output, HasSubstr("p7"));
  const auto c = config::load_calibration(out);
  ASSERT_TRUE(c.T_base_camera.has_value());
  EXPECT_LT(rad_to_deg(rotation_angle_rad(c.T_base_camera->inverse() * true_T_base_camera())), 0.05);
}

TEST_F(CalibrateLive, UnreachableRobotIsADeviceErrorNamingIt) {
  LiveCell cell;  // the camera is there, the robot port is not
  const fs::path cfg = write_cell(1);  // nothing listens on port 1
  const auto r = run_fettle("calibrate hand-eye --live --config " + cfg.string() +
                            " --auto 6 --sphere-radius-mm 25 --out " + (dir_ / "cal.toml").string());
  EXPECT_EQ(r.exit_code, 3) << r.output;
  EXPECT_THAT(r.output, HasSubstr("127.0.0.1:1"));
  EXPECT_FALSE(fs::exists(dir_ / "cal.toml"));
}

TEST_F(CalibrateLive, BoardMethodIsRefusedWithTheReason) {
  const auto r = run_fettle("calibrate hand-eye --live --config " + (fs::path(FETTLE_SOURCE_DIR) / "config/cell.sim.toml").string() +
                            " --auto 6 --board 9x6 --square-mm 20 --out " + (dir_ / "cal.toml").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_THAT(r.output, HasSubstr("sphere method"));
}
