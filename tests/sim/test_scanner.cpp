// The scanner model: intrinsics round trip, range image encodings, noise statistics as
// configured, determinism, and the files it writes.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <sstream>
#include <unistd.h>

#include "fettle/config/calibration.hpp"
#include "fettle/core/ply.hpp"
#include "sim_test_util.hpp"

using namespace fettle::sim;  // NOLINT

namespace {

TEST(SimScanner, ProjectAndRayAreInversesIncludingDistortion) {
  const CameraIntrinsics K;
  for (double v = 0; v < K.height; v += 97)
    for (double u = 0; u < K.width; u += 101) {
      const fettle::Vec3 r = K.ray(u, v);
      const auto px = K.project(r * 612.0);
      EXPECT_NEAR(px.x(), u, 1e-6);
      EXPECT_NEAR(px.y(), v, 1e-6);
    }
  // distortion is really applied: a corner ray differs from the undistorted pinhole one
  const fettle::Vec3 r = K.ray(0, 0);
  EXPECT_GT(std::abs(r.x() - (0 - K.cx) / K.fx), 1e-3);
}

TEST(SimScanner, Coord3DC16EncodingRoundTripsWithinHalfAStep) {
  RangeImageF32 f;
  f.width = 4, f.height = 1;
  f.data = {600.0f, std::nanf(""), 123.456f, 1000.0f};
  const auto c = to_range16(f, 0.02, 100.0, 0);
  EXPECT_EQ(c.data[1], 0);
  const auto back = to_range_f32(c);
  EXPECT_TRUE(std::isnan(back.data[1]));
  for (std::size_t k : {0u, 2u, 3u}) EXPECT_NEAR(back.data[k], f.data[k], 0.0101);
}

class SimScan : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    recipe_ = new fettle::config::PartRecipe(sim_test::pump_body());
    casting_ = new Casting(Casting::make(*recipe_, 7));
  }
  static void TearDownTestSuite() {
    delete casting_;
    delete recipe_;
  }
  static fettle::config::PartRecipe* recipe_;
  static Casting* casting_;
};
fettle::config::PartRecipe* SimScan::recipe_ = nullptr;
Casting* SimScan::casting_ = nullptr;

TEST_F(SimScan, IdealCapturePointsLieOnTheSceneAtTheirGroundTruthPose) {
  auto cfg = sim_test::small_scanner();
  cfg.noise.enabled = false;
  const auto cap = Scanner(cfg).capture(*casting_, 0.0);
  ASSERT_GT(cap.cloud.count_valid(), cap.cloud.size() * 9 / 10);
  const auto T_part_camera = cap.truth.T_base_part.inverse() * cap.truth.T_base_camera;
  std::size_t on_part = 0, checked = 0;
  for (std::size_t k = 0; k < cap.cloud.size(); k += 13) {
    if (!cap.cloud.is_valid(k)) continue;
    const fettle::Vec3 p = T_part_camera * cap.cloud.points[k].cast<double>();
    const double top = casting_->surface_z_mm(p.x(), p.y());
    if (std::isnan(top) || p.z() < 1.0) continue;  // table, clamps, clutter
    ++checked;
    on_part += casting_->distance_to_surface_mm(p) < 0.05 ? 1 : 0;
  }
  ASSERT_GT(checked, 1000u);
  EXPECT_GT(static_cast<double>(on_part) / static_cast<double>(checked), 0.98);
}

TEST_F(SimScan, AnEmptyFixtureShowsTheSceneWithoutThePart) {
  auto cfg = sim_test::small_scanner();
  cfg.noise.enabled = false;
  Casting empty = *casting_;
  empty.take_off_fixture();
  EXPECT_FALSE(empty.on_fixture());
  EXPECT_TRUE(casting_->on_fixture());
  const auto with = Scanner(cfg).capture(*casting_, 0.0);
  const auto without = Scanner(cfg).capture(empty, 0.0);
  ASSERT_GT(without.cloud.count_valid(), without.cloud.size() * 9 / 10);  // the table is still there
  // Where the part was seen, the empty scene is farther from the camera (table, clamps below).
  const auto T_part_camera = with.truth.T_base_part.inverse() * with.truth.T_base_camera;
  std::size_t on_part = 0, deeper = 0;
  for (std::size_t k = 0; k < with.cloud.size(); k += 7) {
    if (!with.cloud.is_valid(k)) continue;
    const fettle::Vec3 p = T_part_camera * with.cloud.points[k].cast<double>();
    if (std::isnan(casting_->surface_z_mm(p.x(), p.y())) || p.z() < 1.0) continue;
    if (casting_->distance_to_surface_mm(p) > 0.05) continue;
    ++on_part;
    if (without.cloud.is_valid(k) && without.cloud.points[k].z() > with.cloud.points[k].z() + 1.0f) ++deeper;
  }
  ASSERT_GT(on_part, 1000u);
  EXPECT_GT(static_cast<double>(deeper) / static_cast<double>(on_part), 0.98);
}

/// Depth noise on a table patch (left image border, where the table is seen past the part): a
/// plane Z = a u + b v + c fitted to it, residuals against the sigma the configuration gives
/// each pixel: sigma_z (Z / reference)^exponent (1 + grazing_gain (1 / cos(incidence) - 1)),
/// the incidence of a table pixel being its ray's angle off the optical axis.
struct TableNoise {
  std::size_t samples = 0;
  double normalized_sigma = 0;  ///< RMS of residual / configured sigma: 1 if the model holds
  double rms_mm = 0;            ///< RMS residual
};
TableNoise table_noise(const Capture& cap, const NoiseModel& nm, double table_z_mm) {
  const auto& K = cap.truth.intrinsics;
  Eigen::Matrix3d AtA = Eigen::Matrix3d::Zero();
  Eigen::Vector3d Atb = Eigen::Vector3d::Zero();
  std::vector<std::array<double, 4>> samples;
  for (int v = K.height / 4; v < 3 * K.height / 4; ++v)
    for (int u = 2; u < K.width / 10; ++u) {
      const float z = cap.range.data[static_cast<std::size_t>(v * K.width + u)];
      if (std::isnan(z) || std::abs(z - table_z_mm) > 5.0) continue;
      const fettle::Vec3 r = K.ray(u, v);
      const double cos_inc = 1.0 / r.norm();
      const double expected = nm.sigma_z_mm * std::pow(z / nm.reference_distance_mm, nm.distance_exponent) *
                              (1 + nm.grazing_gain * (1 / cos_inc - 1));
      samples.push_back({double(u), double(v), double(z), expected});
      const Eigen::Vector3d a(u, v, 1);
      AtA += a * a.transpose();
      Atb += a * z;
    }
  TableNoise out;
  out.samples = samples.size();
  if (samples.empty()) return out;
  const Eigen::Vector3d plane = AtA.ldlt().solve(Atb);
  double sum2 = 0, raw2 = 0;
  for (const auto& s : samples) {
    const double res = s[2] - (plane[0] * s[0] + plane[1] * s[1] + plane[2]);
    sum2 += (res / s[3]) * (res / s[3]);
    raw2 += res * res;
  }
  out.normalized_sigma = std::sqrt(sum2 / static_cast<double>(samples.size()));
  out.rms_mm = std::sqrt(raw2 / static_cast<double>(samples.size()));
  return out;
}

/// Only the depth noise (no dropouts, flying pixels or outliers).
ScannerConfig depth_noise_only() {
  auto cfg = sim_test::small_scanner();
  cfg.noise.surface_dropout_fraction = 0;
  cfg.noise.flying_pixel_fraction = 0;
  cfg.noise.outlier_fraction = 0;
  return cfg;
}

TEST_F(SimScan, DepthNoiseOnAFlatTablePatchMatchesTheConfiguredSigma) {
  for (double sigma : {0.05, 0.2}) {
    auto cfg = depth_noise_only();
    cfg.noise.sigma_z_mm = sigma;
    const auto n = table_noise(Scanner(cfg).capture(*casting_, 0.0), cfg.noise, 600.0);
    ASSERT_GT(n.samples, 2000u);
    EXPECT_NEAR(n.normalized_sigma, 1.0, 0.1) << "sigma " << sigma;
  }
}

TEST_F(SimScan, DepthNoiseGrowsWithDistanceAsConfigured) {
  // The camera 300 mm higher: the table at Z = 900 mm, sigma x (900/600)^2 = 2.25.
  auto cfg = depth_noise_only();
  const auto near = table_noise(Scanner(cfg).capture(*casting_, 0.0), cfg.noise, 600.0);
  cfg.slide_origin_mm.z() += 300.0;
  const auto far = table_noise(Scanner(cfg).capture(*casting_, 0.0), cfg.noise, 900.0);
  ASSERT_GT(near.samples, 2000u);
  ASSERT_GT(far.samples, 2000u);
  EXPECT_NEAR(far.normalized_sigma, 1.0, 0.1);
  EXPECT_NEAR(far.rms_mm / near.rms_mm, 2.25, 0.25);
  // and with the exponent 1 it grows linearly: x 1.5
  cfg.noise.distance_exponent = 1.0;
  const auto linear = table_noise(Scanner(cfg).capture(*casting_, 0.0), cfg.noise, 900.0);
  EXPECT_NEAR(linear.normalized_sigma, 1.0, 0.1);
  EXPECT_NEAR(linear.rms_mm / near.rms_mm, 1.5, 0.17);
}

TEST_F(SimScan, DepthNoiseGrowsWithTheIncidenceAngleAsConfigured) {
  // Off-axis table pixels are seen at up to ~20 deg: with a gain of 10 their sigma is 1.2-1.7x.
  auto cfg = depth_noise_only();
  cfg.noise.grazing_gain = 0.0;
  const auto flat = table_noise(Scanner(cfg).capture(*casting_, 0.0), cfg.noise, 600.0);
  cfg.noise.grazing_gain = 10.0;
  const auto grazing = table_noise(Scanner(cfg).capture(*casting_, 0.0), cfg.noise, 600.0);
  ASSERT_GT(grazing.samples, 2000u);
  EXPECT_NEAR(flat.normalized_sigma, 1.0, 0.1);
  EXPECT_NEAR(grazing.normalized_sigma, 1.0, 0.1);
  EXPECT_GT(grazing.rms_mm / flat.rms_mm, 1.2);
}

/// Pixels where the ideal image sees the table, with their incidence: the camera looks straight
/// down at it, so its Z is 600 mm at every pixel; a pixel and its 4 neighbours at 600 mm keeps
/// out the part's base, whose height field meets the table at a slant.
std::vector<std::pair<std::size_t, double>> table_pixels(const Capture& ideal) {
  const auto& K = ideal.truth.intrinsics;
  auto on_table = [&](int u, int v) {
    const float z = ideal.range.data[static_cast<std::size_t>(v * K.width + u)];
    return !std::isnan(z) && std::abs(z - 600.0f) < 1e-3f;
  };
  std::vector<std::pair<std::size_t, double>> out;
  for (int v = 1; v + 1 < K.height; ++v)
    for (int u = 1; u + 1 < K.width; ++u)
      if (on_table(u, v) && on_table(u - 1, v) && on_table(u + 1, v) && on_table(u, v - 1) && on_table(u, v + 1))
        out.emplace_back(static_cast<std::size_t>(v * K.width + u), fettle::rad_to_deg(std::acos(1.0 / K.ray(u, v).norm())));
  return out;
}

TEST_F(SimScan, DropoutsStartAndEndAtTheConfiguredIncidenceAngles) {
  auto cfg = depth_noise_only();
  cfg.noise.sigma_z_mm = 0.001;
  cfg.noise.enabled = false;
  const auto table = table_pixels(Scanner(cfg).capture(*casting_, 0.0));
  cfg.noise.enabled = true;
  cfg.noise.dropout_start_deg = 8.0;
  cfg.noise.dropout_full_deg = 12.0;
  const auto cap = Scanner(cfg).capture(*casting_, 0.0);
  std::size_t below = 0, below_lost = 0, beyond = 0, beyond_kept = 0, between = 0, between_lost = 0;
  for (const auto& [k, inc] : table) {
    const bool lost = std::isnan(cap.range.data[k]);
    if (inc < 7.9) ++below, below_lost += lost;
    else if (inc > 12.1) ++beyond, beyond_kept += !lost;
    else if (inc > 9.5 && inc < 10.5) ++between, between_lost += lost;
  }
  ASSERT_GT(below, 1000u);
  ASSERT_GT(beyond, 1000u);
  ASSERT_GT(between, 200u);
  EXPECT_EQ(below_lost, 0u);
  EXPECT_EQ(beyond_kept, 0u);
  // halfway between the two angles about half drop out
  EXPECT_NEAR(static_cast<double>(between_lost) / static_cast<double>(between), 0.5, 0.1);
}

TEST_F(SimScan, SurfaceDropoutsCoverTheConfiguredFraction) {
  auto cfg = depth_noise_only();
  cfg.noise.enabled = false;
  const auto table = table_pixels(Scanner(cfg).capture(*casting_, 0.0));
  ASSERT_GT(table.size(), 20000u);
  cfg.noise.enabled = true;
  for (double fraction : {0.0, 0.2}) {
    cfg.noise.surface_dropout_fraction = fraction;
    const auto cap = Scanner(cfg).capture(*casting_, 0.0);
    std::size_t lost = 0;
    for (const auto& [k, inc] : table) lost += std::isnan(cap.range.data[k]);
    EXPECT_NEAR(static_cast<double>(lost) / static_cast<double>(table.size()), fraction, 0.04) << fraction;
  }
}

TEST_F(SimScan, RandomOutliersAppearAtTheConfiguredRate) {
  auto cfg = depth_noise_only();
  cfg.noise.sigma_z_mm = 0.001;
  cfg.noise.enabled = false;
  const auto ideal = Scanner(cfg).capture(*casting_, 0.0);
  cfg.noise.enabled = true;
  cfg.noise.outlier_fraction = 0.01;
  const auto cap = Scanner(cfg).capture(*casting_, 0.0);
  std::size_t both = 0, off = 0;
  for (std::size_t k = 0; k < ideal.range.data.size(); ++k) {
    const float a = ideal.range.data[k], b = cap.range.data[k];
    if (std::isnan(a) || std::isnan(b)) continue;
    ++both;
    if (std::abs(a - b) > 1.0f) ++off;
  }
  ASSERT_GT(both, 100000u);
  // uniform within +-60 mm: 59/60 of them land more than 1 mm off
  EXPECT_NEAR(static_cast<double>(off) / static_cast<double>(both), 0.01 * 59.0 / 60.0, 0.002);
}

TEST_F(SimScan, SameSeedGivesIdenticalBytesAndAnotherSeedDoesNot) {
  auto cfg = sim_test::small_scanner();
  cfg.threads = 2;
  const auto a = Scanner(cfg).capture(*casting_, 0.0);
  cfg.threads = 1;
  const auto b = Scanner(cfg).capture(*casting_, 0.0);
  EXPECT_EQ(a.range16.data, b.range16.data);
  const auto c2 = Casting::make(*recipe_, 7);
  const auto c = Scanner(cfg).capture(c2, 0.0);
  EXPECT_EQ(a.range16.data, c.range16.data);
  EXPECT_EQ(ground_truth_json(a.truth), ground_truth_json(c.truth));
  const auto d = Scanner(cfg).capture(Casting::make(*recipe_, 8), 0.0);
  EXPECT_NE(a.range16.data, d.range16.data);
  EXPECT_NE(ground_truth_json(a.truth), ground_truth_json(d.truth));

  const auto dir = std::filesystem::temp_directory_path() / ("fettle-sim-det-" + std::to_string(::getpid()));
  ASSERT_TRUE(write_capture(dir / "a", "view0", a).ok());
  ASSERT_TRUE(write_capture(dir / "c", "view0", c).ok());
  for (const char* f : {"view0.ply", "view0.pcd", "view0.c16", "view0.f32", "view0.truth.json"}) {
    std::ifstream fa(dir / "a" / f, std::ios::binary), fc(dir / "c" / f, std::ios::binary);
    std::stringstream sa, sc;
    sa << fa.rdbuf();
    sc << fc.rdbuf();
    EXPECT_FALSE(sa.str().empty()) << f;
    EXPECT_EQ(sa.str(), sc.str()) << f;
  }
  const auto pts = fettle::read_ply(dir / "a" / "view0.ply");
  ASSERT_TRUE(pts.ok());
  EXPECT_EQ(pts->points.size(), a.cloud.count_valid());
  std::filesystem::remove_all(dir);
}

TEST_F(SimScan, GrazingSurfacesDropOutAndDiscontinuitiesFly) {
  auto cfg = sim_test::small_scanner();
  cfg.noise.flying_pixel_fraction = 1.0;
  const auto noisy = Scanner(cfg).capture(*casting_, 0.0);
  cfg.noise.enabled = false;
  const auto ideal = Scanner(cfg).capture(*casting_, 0.0);
  EXPECT_LT(noisy.cloud.count_valid(), ideal.cloud.count_valid());
  std::size_t flying = 0;
  for (std::size_t k = 0; k < ideal.range.data.size(); ++k) {
    const float a = ideal.range.data[k], b = noisy.range.data[k];
    if (!std::isnan(a) && !std::isnan(b) && std::abs(a - b) > 1.0f) ++flying;
  }
  EXPECT_GT(flying, 50u);
}

TEST_F(SimScan, CaptureAllTakesOneViewPerSlidePosition) {
  auto cfg = sim_test::small_scanner(258, 193);
  cfg.photo_positions_mm = {0.0, 120.0};
  const auto caps = Scanner(cfg).capture_all(*casting_);
  ASSERT_EQ(caps.size(), 2u);
  EXPECT_NEAR((caps[1].truth.T_base_camera.translation() - caps[0].truth.T_base_camera.translation()).norm(), 120.0, 1e-9);
  EXPECT_NEAR(caps[0].truth.T_base_camera.translation().z(), 600.0, 1e-9);
}

// A simulator placed in a cell puts its camera where that cell's calibration file says (the
// shipped simulator cell: base (0, 0, 600) mm looking down at slide 0), so fettle-sim camera
// --cell and fettle-sim cell agree with what fettled computes from the same file.
TEST(SimScanner, PlacedInACellTheCameraIsWhereTheCellsCalibrationSays) {
  const auto cell = fettle::config::load_cell(FETTLE_SOURCE_DIR "/config/cell.sim.toml");
  const auto calibration = fettle::config::load_calibration(cell.calibration.file);
  ASSERT_TRUE(calibration.T_base_camera.has_value());
  ScannerConfig cfg;
  const auto before = cfg.T_base_camera(0.0);
  cfg.place_in_cell(cell);
  EXPECT_EQ(cfg.photo_positions_mm, cell.slide.photo_positions_mm);
  EXPECT_TRUE(cfg.T_base_camera(0.0).isApprox(*calibration.T_base_camera, 1e-12))
      << cfg.T_base_camera(0.0).matrix() << "\nvs\n" << calibration.T_base_camera->matrix();
  EXPECT_FALSE(before.isApprox(cfg.T_base_camera(0.0), 1e-6)) << "the default pose is not the cell's: the test needs them apart";
  // The slide moves the camera along base x by the photo position.
  const fettle::Transform at_0 = cfg.T_base_camera(0.0);
  const fettle::Transform at_120 = cfg.T_base_camera(120.0);
  EXPECT_NEAR(at_120(0, 3) - at_0(0, 3), 120.0, 1e-12);
  EXPECT_NEAR(at_120(1, 3) - at_0(1, 3), 0.0, 1e-12);
  EXPECT_NEAR(at_120(2, 3) - at_0(2, 3), 0.0, 1e-12);
}

}  // namespace
