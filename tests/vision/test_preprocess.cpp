// Preprocessing: voxel centroid, crop, outlier removal, normals; cloud files and bad input.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <fstream>
#include <random>

#include "fettle/core/error.hpp"
#include "fettle/vision/preprocess.hpp"
#include "test_support.hpp"
#include "../support/draws.hpp"

using namespace fettle::vision;
using ::testing::HasSubstr;
namespace fs = std::filesystem;

namespace {

fs::path temp_path(const std::string& name) {
  return fs::temp_directory_path() / ("fettle-vision-" + std::to_string(::getpid()) + "-" + name);
}

void write_text(const fs::path& p, const std::string& text) { std::ofstream(p) << text; }

}  // namespace

TEST(VoxelDownsample, OnePointPerVoxelAtTheCentroidOfItsPoints) {
  Cloud c;
  // Voxel size 1: the grid starts at the minimum point (0,0,0).
  c.points = {{0.1f, 0.1f, 0.1f}, {0.3f, 0.5f, 0.9f}, {0.8f, 0.3f, 0.2f},  // voxel (0,0,0)
              {2.5f, 0.5f, 0.5f},                                          // voxel (2,0,0)
              {2.2f, 3.1f, 0.4f}, {2.6f, 3.9f, 0.6f}};                     // voxel (2,3,0)
  const Cloud d = voxel_downsample(c, 1.0);
  ASSERT_EQ(d.size(), 3U);
  auto has = [&](const Eigen::Vector3f& q) {
    for (const auto& p : d.points)
      if ((p - q).norm() < 1e-5f) return true;
    return false;
  };
  EXPECT_TRUE(has({0.4f, 0.3f, 0.4f}));  // mean of the first three, not the voxel centre
  EXPECT_TRUE(has({2.5f, 0.5f, 0.5f}));
  EXPECT_TRUE(has({2.4f, 3.5f, 0.5f}));
}

TEST(VoxelDownsample, AveragesNormalsAndKeepsThemUnit) {
  Cloud c;
  c.points = {{0.1f, 0.1f, 0.1f}, {0.2f, 0.2f, 0.2f}};
  c.normals = {Eigen::Vector3f::UnitZ(), Eigen::Vector3f(0.0f, 1.0f, 1.0f).normalized()};
  const Cloud d = voxel_downsample(c, 1.0);
  ASSERT_EQ(d.size(), 1U);
  ASSERT_TRUE(d.has_normals());
  EXPECT_NEAR(d.normals[0].norm(), 1.0f, 1e-5f);
  EXPECT_GT(d.normals[0].z(), d.normals[0].y());
}

TEST(VoxelDownsample, DenseGridKeepsOnePerCellAndVoxelForCountHitsTarget) {
  Cloud c;
  for (int x = 0; x < 100; ++x)
    for (int y = 0; y < 100; ++y) c.points.emplace_back(0.1f * static_cast<float>(x), 0.1f * static_cast<float>(y), 0.0f);
  EXPECT_EQ(voxel_downsample(c, 1.0).size(), 100U);  // 10 x 10 cells of 1 x 1
  const double v = voxel_for_count(c, 400);
  const std::size_t n = voxel_downsample(c, v).size();
  EXPECT_LE(n, 400U);
  EXPECT_GT(n, 250U);
}

TEST(CropBox, KeepsPointsInsideTheBoxGivenInAnotherFrame) {
  Cloud c;
  c.points = {{0, 0, 0}, {10, 0, 0}, {20, 0, 0}};
  fettle::Transform T_frame_cloud = fettle::Transform::Identity();
  T_frame_cloud.translation() = fettle::Vec3(-10, 0, 0);  // the box frame sees the cloud shifted by -10
  const Cloud k = crop_box(c, T_frame_cloud, {-1, -1, -1}, {1, 1, 1});
  ASSERT_EQ(k.size(), 1U);
  EXPECT_FLOAT_EQ(k.points[0].x(), 10.0f);  // returned in the cloud's own frame
}

TEST(StatisticalOutliers, RemovesIsolatedPointsAndKeepsTheSurface) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<float> u(0.0f, 50.0f);
  Cloud c;
  for (int i = 0; i < 5000; ++i) {
    const auto xy = fettle::test::draws<2>(u, rng);
    c.points.emplace_back(xy[0], xy[1], 0.0f);
  }
  c.points.emplace_back(25.0f, 25.0f, 40.0f);
  c.points.emplace_back(-30.0f, 10.0f, 5.0f);
  const Cloud k = remove_statistical_outliers(c, 8, 2.5);
  EXPECT_GT(k.size(), 4900U);
  for (const auto& p : k.points) EXPECT_LT(std::abs(p.z()), 1e-3f);
}

TEST(StatisticalOutliers, OrganizedVariantUsesImageNeighbours) {
  fettle::OrganizedCloud o;
  o.width = 60;
  o.height = 40;
  for (std::uint32_t v = 0; v < o.height; ++v)
    for (std::uint32_t u = 0; u < o.width; ++u) o.points.emplace_back(static_cast<float>(u), static_cast<float>(v), 500.0f);
  o.points[20 * 60 + 30].z() = 560.0f;  // a flying pixel
  o.points[5] = fettle::OrganizedCloud::invalid();
  const auto k = remove_statistical_outliers(o, 1, 3.0);
  EXPECT_FALSE(k.is_valid(20 * 60 + 30));
  EXPECT_FALSE(k.is_valid(5));
  EXPECT_EQ(k.width, 60U);
  EXPECT_GT(k.count_valid(), o.count_valid() - 12);  // the spike and a few of its neighbours at most
}

TEST(JumpEdges, FlyingPixelsBetweenTwoSurfacesAreDroppedAndTheSurfacesKept) {
  // A step seen from above: left half at 500 mm, right half at 510 mm, with a flying pixel
  // halfway down the step in every row.
  fettle::OrganizedCloud o;
  o.width = 40;
  o.height = 10;
  for (std::uint32_t v = 0; v < o.height; ++v)
    for (std::uint32_t u = 0; u < o.width; ++u)
      o.points.emplace_back(0.5f * static_cast<float>(u), 0.5f * static_cast<float>(v), u < 20 ? 500.0f : 510.0f);
  for (std::uint32_t v = 0; v < o.height; ++v) o.points[v * 40 + 20].z() = 505.0f;
  const auto k = remove_jump_edges(o, 2.0);
  EXPECT_EQ(k.width, 40U);
  for (std::uint32_t v = 0; v < o.height; ++v) {
    EXPECT_FALSE(k.is_valid(v * 40 + 20)) << "flying pixel in row " << v;
    EXPECT_FALSE(k.is_valid(v * 40 + 19)) << "the step's edge pixel goes too";
    EXPECT_TRUE(k.is_valid(v * 40 + 18));
    EXPECT_TRUE(k.is_valid(v * 40 + 22));
  }
  EXPECT_EQ(k.count_valid(), o.count_valid() - 3 * o.height);
  // a gentle slope (0.25 mm per pixel) is a surface, not a jump; 0 switches the filter off
  fettle::OrganizedCloud slope = o;
  for (std::uint32_t v = 0; v < o.height; ++v)
    for (std::uint32_t u = 0; u < o.width; ++u) slope.points[v * 40 + u].z() = 500.0f + 0.25f * static_cast<float>(u);
  EXPECT_EQ(remove_jump_edges(slope, 2.0).count_valid(), slope.count_valid());
  EXPECT_EQ(remove_jump_edges(o, 0.0).count_valid(), o.count_valid());
}

namespace {

/// A pinhole camera (f = 1000 px, 80 x 40 pixels, looking along +z) over a block whose top
/// (500 mm away) ends at x = edge_x mm, with the floor 520 mm away beyond: each pixel's centre
/// ray hits one or the other (0.5 mm pixels on the top).
fettle::OrganizedCloud step_view(float edge_x) {
  fettle::OrganizedCloud o;
  o.width = 80;
  o.height = 40;
  for (std::uint32_t v = 0; v < o.height; ++v)
    for (std::uint32_t u = 0; u < o.width; ++u) {
      const Eigen::Vector3f ray((static_cast<float>(u) - 39.5f) / 1000.0f, (static_cast<float>(v) - 19.5f) / 1000.0f, 1.0f);
      o.points.push_back(ray * (ray.x() * 500.0f < edge_x ? 500.0f : 520.0f));
    }
  return o;
}

/// The last pixel on the block's top in row v.
std::uint32_t last_top(const fettle::OrganizedCloud& o, std::uint32_t v) {
  std::uint32_t u = 0;
  while (u + 1 < o.width && o.points[v * o.width + u + 1].z() < 510.0f) ++u;
  return u;
}

std::size_t count_mixed(const fettle::OrganizedCloud& o, double min_jump_mm) {
  const auto m = mixed_pixels(o, min_jump_mm, 0.3);
  return static_cast<std::size_t>(std::count(m.begin(), m.end(), std::uint8_t{1}));
}

}  // namespace

TEST(MixedPixels, PixelsBetweenTwoSurfacesAreMixedTheSurfacesLastPixelsAreNot) {
  auto o = step_view(0.11f);
  // Flying pixels: in rows 0, 4, 8, ... the top's last pixel pulled 30 % of the way down to
  // the floor, in rows 2, 6, 10, ... the floor's first pixel 60 % of the way up to the top.
  std::vector<std::size_t> flying;
  for (std::uint32_t v = 0; v < o.height; v += 2) {
    const std::size_t k = v * o.width + last_top(o, v) + (v % 4 == 0 ? 0 : 1);
    const float z = o.points[k].z();
    o.points[k] *= (z < 510.0f ? 506.0f : 508.0f) / z;
    flying.push_back(k);
  }
  const auto mixed = mixed_pixels(o, 2.0, 0.3);
  ASSERT_EQ(mixed.size(), o.size());
  for (std::size_t k : flying) EXPECT_EQ(mixed[k], 1) << "flying pixel " << k;
  for (std::uint32_t v = 1; v < o.height; v += 2) {  // rows without one: both sides' pixels are true
    EXPECT_EQ(mixed[v * o.width + last_top(o, v)], 0) << "row " << v;
    EXPECT_EQ(mixed[v * o.width + last_top(o, v) + 1], 0) << "row " << v;
  }
  EXPECT_EQ(count_mixed(o, 2.0), flying.size());
  EXPECT_EQ(count_mixed(o, 0.0), 0U);  // 0 finds none
  // a steep but smooth surface (3 mm per pixel) is no mixture of two
  fettle::OrganizedCloud steep = o;
  for (std::uint32_t v = 0; v < o.height; ++v)
    for (std::uint32_t u = 0; u < o.width; ++u) steep.points[v * o.width + u].z() = 500.0f + 3.0f * static_cast<float>(u);
  EXPECT_EQ(count_mixed(steep, 2.0), 0U);
}

TEST(OccludingEdges, LieOnTheFacesEdgeWithinHalfAPixelWithoutBias) {
  // The edge at ten places across a pixel (0.5 mm): one edge point per row, at the top's depth,
  // off by half a pixel at most and by nothing on average.
  double sum = 0.0;
  std::size_t n = 0;
  for (int f = 0; f < 10; ++f) {
    const float edge_x = 0.03f + 0.05f * static_cast<float>(f);
    const auto o = step_view(edge_x);
    const auto edges = occluding_edges(o, mixed_pixels(o, 2.0, 0.3), 2.0);
    ASSERT_EQ(edges.size(), o.height) << "edge at x = " << edge_x;
    for (const auto& p : edges.points) {
      EXPECT_NEAR(p.z(), 500.0f, 0.01f);
      EXPECT_LE(std::abs(p.x() - edge_x), 0.25f + 1e-3f) << "edge at x = " << edge_x;
      sum += p.x() - edge_x;
      ++n;
    }
  }
  EXPECT_LT(std::abs(sum / static_cast<double>(n)), 0.01);
  // Past a mixed pixel, halfway between the true pixels on either side; a dropout beside the
  // face: where it ends is unknown, no edge point.
  auto o = step_view(0.11f);
  const std::size_t k = 7 * o.width + last_top(o, 7) + 1;
  o.points[k] *= 510.0f / o.points[k].z();
  const auto past = occluding_edges(o, mixed_pixels(o, 2.0, 0.3), 2.0);
  ASSERT_EQ(past.size(), o.height);
  // The one-call form (inspect's) finds the same points past the same mixed pixels.
  const auto one_call = occluding_edges(o, 2.0, 0.3);
  ASSERT_EQ(one_call.size(), past.size());
  for (std::size_t i = 0; i < past.size(); ++i) EXPECT_EQ(one_call.points[i], past.points[i]) << "edge point " << i;
  const auto row7 = std::find_if(past.points.begin(), past.points.end(),
                                 [](const Eigen::Vector3f& p) { return std::abs(p.y() / p.z() * 1000.0f + 19.5f - 7.0f) < 0.1f; });
  ASSERT_NE(row7, past.points.end());
  EXPECT_NEAR(row7->x(), o.points[k].x() / o.points[k].z() * 500.0f, 0.01f);  // on the mixed pixel's ray
  o.points[k] = fettle::OrganizedCloud::invalid();
  EXPECT_EQ(occluding_edges(o, mixed_pixels(o, 2.0, 0.3), 2.0).size(), o.height - 1);
}

TEST(Normals, PcaNormalsOfAPlaneFaceTheViewpoint) {
  Cloud c;
  for (int x = 0; x < 30; ++x)
    for (int y = 0; y < 30; ++y) c.points.emplace_back(static_cast<float>(x), static_cast<float>(y), 100.0f);
  estimate_normals(c, 10, Eigen::Vector3f::Zero());
  ASSERT_TRUE(c.has_normals());
  for (const auto& n : c.normals) EXPECT_NEAR(n.z(), -1.0f, 1e-4f);
}

TEST(Normals, IntegralImageNormalsOfATiltedPlane) {
  fettle::OrganizedCloud o;
  o.width = 80;
  o.height = 60;
  const Eigen::Vector3f n_true = Eigen::Vector3f(0.0f, 0.5f, -1.0f).normalized();
  for (std::uint32_t v = 0; v < o.height; ++v)
    for (std::uint32_t u = 0; u < o.width; ++u) {
      const float x = static_cast<float>(u) - 40.0f;
      const float y = static_cast<float>(v) - 30.0f;
      o.points.emplace_back(x, y, 400.0f + 0.5f * y);  // z = 400 + y/2: normal (0, 0.5, -1)
    }
  const Cloud c = organized_normals(o);
  ASSERT_GT(c.size(), 2000U);  // 80 x 60 minus the smoothing border
  for (const auto& n : c.normals) EXPECT_GT(n.dot(n_true), 0.999f);
}

TEST(CloudFiles, LoadsPcdWithNaNsAndKeepsOnlyFinitePoints) {
  const Cloud scene = load_cloud(test::data("milk_cartoon_all_small_clorox.pcd"));
  EXPECT_GT(scene.size(), 100000U);
  EXPECT_LT(scene.size(), 640U * 480U);  // the Kinect frame has invalid pixels
  for (const auto& p : scene.points) ASSERT_TRUE(p.allFinite());
}

TEST(CloudFiles, PlyRoundTrip) {
  Cloud c;
  c.points = {{1, 2, 3}, {4, 5, 6}};
  c.normals = {Eigen::Vector3f::UnitX(), Eigen::Vector3f::UnitY()};
  const auto p = temp_path("rt.ply");
  save_ply(p, c);
  const Cloud r = load_cloud(p);
  ASSERT_EQ(r.size(), 2U);
  EXPECT_EQ(r.points[1], c.points[1]);
  ASSERT_TRUE(r.has_normals());
  EXPECT_EQ(r.normals[1], c.normals[1]);
  fs::remove(p);
}

// Normals without a curvature field (what save_ply, the simulator and most scanners write):
// read without PCL's "Failed to find match for field 'curvature'" on every load; non-finite
// points dropped with their normals; a double-typed field still loads (PCL's conversion).
TEST(CloudFiles, NormalsWithoutCurvatureLoadQuietlyAndStayPaired) {
  const auto f = temp_path("normals.pcd");
  write_text(f, "VERSION 0.7\nFIELDS x y z normal_x normal_y normal_z\nSIZE 4 4 4 4 4 4\nTYPE F F F F F F\n"
                "COUNT 1 1 1 1 1 1\nWIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA ascii\n"
                "1 2 3 0 0 2\nnan 0 0 1 0 0\n4 5 6 0 1 0\n");
  ::testing::internal::CaptureStderr();
  const Cloud c = load_cloud(f);
  const std::string err = ::testing::internal::GetCapturedStderr();
  EXPECT_EQ(err.find("curvature"), std::string::npos) << err;
  ASSERT_EQ(c.size(), 2U);
  ASSERT_TRUE(c.has_normals());
  EXPECT_EQ(c.points[1], Eigen::Vector3f(4, 5, 6));
  EXPECT_EQ(c.normals[0], Eigen::Vector3f::UnitZ());  // normalised
  EXPECT_EQ(c.normals[1], Eigen::Vector3f::UnitY());
  const auto d = temp_path("normals_double.pcd");
  write_text(d, "VERSION 0.7\nFIELDS x y z normal_x normal_y normal_z\nSIZE 4 4 4 8 8 8\nTYPE F F F F F F\n"
                "COUNT 1 1 1 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n7 8 9 1 0 0\n");
  const Cloud e = load_cloud(d);
  ASSERT_EQ(e.size(), 1U);
  EXPECT_EQ(e.points[0], Eigen::Vector3f(7, 8, 9));
  for (const auto& p : {f, d}) fs::remove(p);
}

TEST(CloudFiles, BadInputIsAUserErrorThatSaysWhat) {
  EXPECT_THAT([] { (void)load_cloud("/nonexistent/scan.ply"); },
              ::testing::ThrowsMessage<fettle::UserError>(HasSubstr("no such file")));
  const auto empty = temp_path("empty.pcd");
  write_text(empty, "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\nHEIGHT 1\nPOINTS 0\nDATA ascii\n");
  EXPECT_THAT([&] { (void)load_cloud(empty); }, ::testing::Throws<fettle::UserError>());
  const auto nan = temp_path("nan.pcd");
  write_text(nan, "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA ascii\n"
                  "nan nan nan\nnan nan nan\nnan nan nan\n");
  EXPECT_THAT([&] { (void)load_cloud(nan); }, ::testing::ThrowsMessage<fettle::UserError>(HasSubstr("all NaN")));
  const auto junk = temp_path("junk.ply");
  write_text(junk, "this is not a point cloud\n");
  EXPECT_THAT([&] { (void)load_cloud(junk); }, ::testing::Throws<fettle::UserError>());
  const auto txt = temp_path("cloud.xyz");
  write_text(txt, "1 2 3\n");
  EXPECT_THAT([&] { (void)load_cloud(txt); }, ::testing::ThrowsMessage<fettle::UserError>(HasSubstr("use .ply or .pcd")));
  for (const auto& p : {empty, nan, junk, txt}) fs::remove(p);
}

TEST(Units, MetresWhereMillimetresAreExpectedAreDetectedFromTheExtent) {
  const Cloud milk = load_cloud(test::data("milk.pcd"));  // a carton in metres: ~0.2 units across
  EXPECT_THAT([&] { require_millimetres(milk, "scan.pcd"); },
              ::testing::ThrowsMessage<fettle::UserError>(HasSubstr("looks like metres")));
  const Cloud milk_mm = transformed(milk, fettle::Transform(Eigen::Scaling(1000.0)));
  EXPECT_NO_THROW(require_millimetres(milk_mm, "scan.pcd"));
}
