// PLY files of points (fettle/core/ply.hpp): what one component writes, every other reads back.
// The bad-input cases of the reader are in tests/camera/test_camera_bad_input.cpp and its fuzz target.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

#include "fettle/core/ply.hpp"

namespace fs = std::filesystem;

namespace {
fs::path temp(const std::string& name) {
  const auto dir = fs::temp_directory_path() / ("fettle-ply-" + std::to_string(::getpid()));
  fs::create_directories(dir);
  return dir / name;
}
}  // namespace

TEST(Ply, AnOrganizedCloudKeepsItsGridAndItsHoles) {
  fettle::OrganizedCloud c;
  c.width = 3;
  c.height = 2;
  for (int i = 0; i < 6; ++i)
    c.points.push_back(i == 4 ? fettle::OrganizedCloud::invalid() : Eigen::Vector3f(0.5f * i, -1.25f, 600.0f + i));
  const auto f = temp("organized.ply");
  ASSERT_TRUE(fettle::write_ply(f, c));
  const auto back = fettle::read_ply(f);
  ASSERT_TRUE(back.ok()) << back.error().message;
  EXPECT_EQ(back->width, 3U);
  EXPECT_EQ(back->height, 2U);
  ASSERT_EQ(back->points.size(), 6U);
  EXPECT_FALSE(back->points[4].allFinite());
  EXPECT_EQ(back->points[5], c.points[5]);
  fs::remove_all(f.parent_path());
}

TEST(Ply, PointsWithAPropertyAreReadBackAsTheirPoints) {
  const std::vector<Eigen::Vector3f> pts{{1.0f, 2.0f, 3.0f}, {-4.0f, 5.5f, 6.0f}};
  const std::vector<float> deviation{0.1f, -0.2f};
  const auto f = temp("deviation.ply");
  ASSERT_TRUE(fettle::write_ply(f, pts, {"deviation_mm"}, deviation, "test"));
  std::ifstream in(f);
  std::string header((std::istreambuf_iterator<char>(in)), {});
  EXPECT_NE(header.find("property float deviation_mm\nend_header\n"), std::string::npos);
  EXPECT_EQ(fs::file_size(f), header.find("end_header\n") + 11 + 2 * 16);
  const auto back = fettle::read_ply(f);
  ASSERT_TRUE(back.ok()) << back.error().message;
  ASSERT_EQ(back->points.size(), 2U);
  EXPECT_EQ(back->points[1], pts[1]);
  EXPECT_EQ(back->height, 1U);
  fs::remove_all(f.parent_path());
}

TEST(Ply, AMeshIsRefusedNotMisreadAsItsFaces) {
  const auto f = temp("mesh.ply");
  std::ofstream(f) << "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                      "property float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
                   << std::string(12, '\0');
  const auto back = fettle::read_ply(f);
  ASSERT_FALSE(back.ok());
  EXPECT_EQ(back.error().code, "ply.bad");
  EXPECT_NE(back.error().message.find("element 'face'"), std::string::npos) << back.error().message;
  fs::remove_all(f.parent_path());
}
