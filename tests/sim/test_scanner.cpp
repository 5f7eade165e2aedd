// The scanner model: intrinsics round trip, range image encodings, noise statistics as
// configured, determinism, and the files it writes.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <sstream>
#include <unistd.h>

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

TEST_F(SimScan, DepthNoiseOnAFlatTablePatchMatchesTheConfiguredSigma) {
  for (double sigma : {0.05, 0.2}) {
    auto cfg = sim_test::small_scanner();
    cfg.noise.sigma_z_mm = sigma;
    cfg.noise.surface_dropout_fraction = 0;
    cfg.noise.flying_pixel_fraction = 0;
    cfg.noise.outlier_fraction = 0;
    const auto cap = Scanner(cfg).capture(*casting_, 0.0);
    // Table pixels: base z of the ideal ray hit is 0 -> Z = 600 exactly (camera looks straight down).
    // Fit a plane Z = a u + b v + c to a table patch (left image border) and compare the residual
    // with the configured sigma (which grows with the incidence angle off-axis).
    const auto& K = cap.truth.intrinsics;
    Eigen::Matrix3d AtA = Eigen::Matrix3d::Zero();
    Eigen::Vector3d Atb = Eigen::Vector3d::Zero();
    std::vector<std::array<double, 4>> samples;
    for (int v = K.height / 4; v < 3 * K.height / 4; ++v)
      for (int u = 2; u < K.width / 10; ++u) {
        const float z = cap.range.data[static_cast<std::size_t>(v * K.width + u)];
        if (std::isnan(z) || std::abs(z - 600.0f) > 5.0f) continue;
        const fettle::Vec3 r = K.ray(u, v);
        const double cos_inc = 1.0 / r.norm();
        const double expected = sigma * std::pow(600.0 / 600.0, 2) * (1 + cfg.noise.grazing_gain * (1 / cos_inc - 1));
        samples.push_back({double(u), double(v), double(z), expected});
        const Eigen::Vector3d a(u, v, 1);
        AtA += a * a.transpose();
        Atb += a * z;
      }
    ASSERT_GT(samples.size(), 2000u);
    const Eigen::Vector3d plane = AtA.ldlt().solve(Atb);
    double sum2 = 0;
    for (const auto& s : samples) {
      const double res = s[2] - (plane[0] * s[0] + plane[1] * s[1] + plane[2]);
      sum2 += (res / s[3]) * (res / s[3]);
    }
    const double normalized_sigma = std::sqrt(sum2 / static_cast<double>(samples.size()));
    EXPECT_NEAR(normalized_sigma, 1.0, 0.1) << "sigma " << sigma;
  }
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
  const auto pts = read_ply(dir / "a" / "view0.ply");
  ASSERT_TRUE(pts.ok());
  EXPECT_EQ(pts->size(), a.cloud.count_valid());
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

}  // namespace
