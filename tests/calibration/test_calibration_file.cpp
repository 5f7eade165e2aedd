// The calibration file: write/read round trip, errors with file:line, the shipped sim file.
#include <filesystem>
#include <fstream>
#include <string>

#include <gtest/gtest.h>

#include "fettle/config/calibration.hpp"
#include "fettle/config/load.hpp"

namespace fs = std::filesystem;
using namespace fettle;  // NOLINT

namespace {

fs::path scratch_path() { return fs::temp_directory_path() / ("fettle-calfile-" + std::to_string(::getpid())); }

fs::path temp_dir() {
  const auto d = scratch_path();
  fs::create_directories(d);
  return d;
}

/// The scratch folder goes when the test process ends (ctest runs each test in one of its own).
struct RemoveTempDir {
  RemoveTempDir() = default;
  RemoveTempDir(const RemoveTempDir&) = delete;
  RemoveTempDir& operator=(const RemoveTempDir&) = delete;
  ~RemoveTempDir() {
    std::error_code ec;
    fs::remove_all(scratch_path(), ec);
  }
} const remove_temp_dir;

fs::path write(const std::string& name, const std::string& text) {
  const auto p = temp_dir() / name;
  std::ofstream(p) << text;
  return p;
}

std::string all(const std::vector<config::Diagnostic>& d) {
  std::string s;
  for (const auto& x : d) s += x.to_string() + "\n";
  return s;
}

}  // namespace

TEST(CalibrationFile, RoundTripKeepsEveryValue) {
  config::CalibrationFile c;
  c.id = "cell7-2026-11-22";
  c.date = "2026-11-22T04:30:00Z";
  c.note = "after the camera was re-mounted";
  config::CameraIntrinsics k;
  k.width_px = 2064;
  k.height_px = 1544;
  k.fx_px = 2401.25;
  k.fy_px = 2399.5;
  k.cx_px = 1030.75;
  k.cy_px = 770.125;
  k.distortion = {-0.101, 0.0521, 0.0001, -0.0002, 0.0};
  k.rms_px = 0.123;
  k.views = 17;
  c.intrinsics = k;
  Transform T = Transform::Identity();
  T.linear() = Eigen::AngleAxisd(2.5, Vec3(0.3, -0.5, 0.8).normalized()).toRotationMatrix();
  T.translation() = Vec3(12.5, -7.25, 601.0);
  c.T_base_camera = T;
  c.T_flange_board = T.inverse();
  c.hand_eye = config::HandEyeResiduals{"board", 2, 0.05, 0.07, 0.01, 0.02,
                                        {{"p1", 0.04, 0.01, false}, {"p2", 0.06, 0.02, false}, {"p3", 3.0, 1.0, true}}};
  const auto file = temp_dir() / "cal.toml";
  config::write_calibration(file, c);
  const auto r = config::load_calibration(file);
  EXPECT_EQ(r.id, c.id);
  EXPECT_EQ(r.date, c.date);
  EXPECT_EQ(r.note, c.note);
  ASSERT_TRUE(r.intrinsics);
  EXPECT_EQ(r.intrinsics->width_px, 2064);
  EXPECT_DOUBLE_EQ(r.intrinsics->fx_px, 2401.25);
  EXPECT_DOUBLE_EQ(r.intrinsics->cy_px, 770.125);
  EXPECT_EQ(r.intrinsics->distortion, k.distortion);
  EXPECT_EQ(r.intrinsics->views, 17);
  ASSERT_TRUE(r.T_base_camera);
  EXPECT_TRUE(r.T_base_camera->isApprox(T, 1e-9));
  ASSERT_TRUE(r.T_flange_board);
  EXPECT_TRUE(r.T_flange_board->isApprox(T.inverse(), 1e-9));
  EXPECT_FALSE(r.T_camera_projector);
  ASSERT_TRUE(r.hand_eye);
  EXPECT_EQ(r.hand_eye->method, "board");
  ASSERT_EQ(r.hand_eye->per_pose.size(), 3u);
  EXPECT_TRUE(r.hand_eye->per_pose[2].outlier);
  EXPECT_FALSE(r.hand_eye->per_pose[0].outlier);
}

TEST(CalibrationFile, NonUnitQuaternionIsAnErrorWithItsLine) {
  const auto f = write("badq.toml",
                       "[calibration]\nid = \"x\"\ndate = \"2026-11-22\"\n\n[T_base_camera]\n"
                       "position_mm = [0.0, 0.0, 600.0]\nquaternion_wxyz = [0.0, 1.0, 0.0, 0.5]\n");
  const auto d = config::check_calibration(f);
  ASSERT_EQ(d.size(), 1u) << all(d);
  EXPECT_EQ(d[0].line, 7);
  EXPECT_EQ(d[0].key, "T_base_camera.quaternion_wxyz");
  EXPECT_NE(d[0].message.find("unit quaternion"), std::string::npos);
}

TEST(CalibrationFile, MissingIdentityAndBadDateAreErrors) {
  const auto f = write("noid.toml", "[calibration]\ndate = \"yesterday\"\n");
  const auto d = config::check_calibration(f);
  const auto text = all(d);
  EXPECT_NE(text.find("calibration.id"), std::string::npos) << text;
  EXPECT_NE(text.find("ISO 8601"), std::string::npos) << text;
  EXPECT_THROW((void)config::load_calibration(f), config::ConfigError);
}

TEST(CalibrationFile, UnknownKeysAndBadIntrinsicsAreErrors) {
  const auto f = write("badk.toml",
                       "[calibration]\nid = \"x\"\ndate = \"2026-11-22\"\n[intrinsics]\nwidth_px = 100\nheight_px = 80\n"
                       "fx_px = 500.0\nfy_px = 500.0\ncx_px = 150.0\ncy_px = 40.0\ndistortion = [0.1, 0.2, 0.3]\n"
                       "focal_px = 3.0\n");
  const auto text = all(config::check_calibration(f));
  EXPECT_NE(text.find("intrinsics.cx_px"), std::string::npos) << text;
  EXPECT_NE(text.find("intrinsics.distortion"), std::string::npos) << text;
  EXPECT_NE(text.find("intrinsics.focal_px"), std::string::npos) << text;
}

TEST(CalibrationFile, ShippedSimulatorFileHoldsTheNominalCamera) {
  const auto c = config::load_calibration(fs::path(FETTLE_SOURCE_DIR) / "config/calibration.sim.toml");
  ASSERT_TRUE(c.intrinsics);
  EXPECT_EQ(c.intrinsics->width_px, 2064);
  EXPECT_EQ(c.intrinsics->height_px, 1544);
  EXPECT_DOUBLE_EQ(c.intrinsics->fx_px, 2400.0);
  ASSERT_TRUE(c.T_base_camera);
  // Looking straight down from 600 mm: the optical axis is -z of the base frame.
  EXPECT_TRUE((c.T_base_camera->rotation() * Vec3::UnitZ()).isApprox(-Vec3::UnitZ(), 1e-12));
  EXPECT_TRUE((*c.T_base_camera * Vec3(0, 0, 600.0)).isApprox(Vec3::Zero(), 1e-9));
}

TEST(CalibrationFile, CellFileRejectsAnInvalidCalibrationFile) {
  const auto cal = write("broken-cal.toml", "[calibration]\nid = \"x\"\n");
  auto cell = std::ifstream(fs::path(FETTLE_SOURCE_DIR) / "config/cell.sim.toml");
  std::string text((std::istreambuf_iterator<char>(cell)), std::istreambuf_iterator<char>());
  const auto pos = text.find("file = \"calibration.sim.toml\"");
  ASSERT_NE(pos, std::string::npos) << "cell.sim.toml no longer names calibration.sim.toml";
  text.replace(pos, std::string("file = \"calibration.sim.toml\"").size(), "file = \"" + cal.string() + "\"");
  // Recipes are relative to the shipped file: point them back there.
  const auto rp = text.find("file = \"parts/");
  if (rp != std::string::npos) text.replace(rp, 8, "file = \"" + std::string(FETTLE_SOURCE_DIR) + "/config/");
  const auto f = write("cell.toml", text);
  const auto d = config::check_file(f, config::FileKind::cell);
  const auto all_text = all(d);
  EXPECT_NE(all_text.find("calibration.file"), std::string::npos) << all_text;
  EXPECT_NE(all_text.find("calibration.date"), std::string::npos) << all_text;
}

TEST(CalibrationFile, Sha256MatchesTheStandardTestVectors) {
  EXPECT_EQ(config::sha256_hex(""), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
  EXPECT_EQ(config::sha256_hex("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  // Two blocks (56 bytes of message push the length into a second block).
  EXPECT_EQ(config::sha256_hex("abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq"),
            "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1");
}

TEST(CalibrationFile, IdentityHoldsIdDateAndTheHashOfTheBytesRead) {
  config::CalibrationFile c;
  c.id = "cell7-a";
  c.date = "2026-11-22T04:30:00Z";
  EXPECT_TRUE(config::calibration_identity(c).sha256.empty());  // built in memory, never read
  const auto file = temp_dir() / "ident.toml";
  config::write_calibration(file, c);
  const auto a = config::calibration_identity(config::load_calibration(file));
  EXPECT_EQ(a.id, "cell7-a");
  EXPECT_EQ(a.date, "2026-11-22T04:30:00Z");
  EXPECT_EQ(a.sha256, config::sha256_hex(config::to_toml(c)));
  EXPECT_EQ(a.file, fs::absolute(file).lexically_normal());
  EXPECT_NE(a.to_string().find("cell7-a (2026-11-22T04:30:00Z) sha256:" + a.sha256.substr(0, 12)), std::string::npos)
      << a.to_string();
  // Same id and date, different content (e.g. edited by hand): the hash tells them apart.
  c.note = "edited";
  config::write_calibration(file, c);
  const auto b = config::calibration_identity(config::load_calibration(file));
  EXPECT_EQ(b.id, a.id);
  EXPECT_NE(b.sha256, a.sha256);
}
