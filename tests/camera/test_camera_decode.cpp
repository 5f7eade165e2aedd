// Decoding Scan3d frames into organized clouds, against exact geometry.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>
#include <vector>

#include "fettle/drivers/camera_decode.hpp"
#include "fettle/core/ply.hpp"

namespace fd = fettle::drivers;
using ::testing::HasSubstr;

namespace {

fd::Scan3dParameters params(double scale, double offset, std::uint16_t invalid) {
  fd::Scan3dParameters p;
  p.scale = scale;
  p.offset = offset;
  p.invalid_data_flag = true;
  p.invalid_data_value = invalid;
  p.intrinsics = fd::Intrinsics{500.0, 400.0, 31.5, 23.5};
  return p;
}

template <class T>
fd::RawFrame frame(std::uint32_t format, std::uint32_t w, std::uint32_t h, const std::vector<T>& data) {
  return fd::RawFrame{format, w, h, reinterpret_cast<const std::byte*>(data.data()), data.size() * sizeof(T)};
}

}  // namespace

TEST(CameraDecode, C16RangeMapBecomesPointsOnTheRays) {
  const std::uint32_t w = 64, h = 48;
  std::vector<std::uint16_t> raw(w * h);
  for (std::uint32_t i = 0; i < w * h; ++i) raw[i] = static_cast<std::uint16_t>(1000 + i);
  const auto p = params(0.05, 100.0, 0);
  auto cloud = fd::decode_frame(frame(fd::pfnc::Coord3D_C16, w, h, raw), p);
  ASSERT_TRUE(cloud.ok()) << cloud.error().message;
  ASSERT_EQ(cloud->width, w);
  ASSERT_EQ(cloud->height, h);
  for (std::uint32_t v : {0u, 17u, 47u})
    for (std::uint32_t u : {0u, 31u, 63u}) {
      const auto& pt = cloud->points[v * w + u];
      const double z = (1000.0 + v * w + u) * 0.05 + 100.0;
      EXPECT_NEAR(pt.z(), z, 1e-3);
      EXPECT_NEAR(pt.x(), (u - 31.5) / 500.0 * z, 1e-3);
      EXPECT_NEAR(pt.y(), (v - 23.5) / 400.0 * z, 1e-3);
    }
}

TEST(CameraDecode, C16InvalidValueIsNaN) {
  std::vector<std::uint16_t> raw{0, 500, 0, 700};
  auto cloud = fd::decode_frame(frame(fd::pfnc::Coord3D_C16, 2, 2, raw), params(1.0, 0.0, 0));
  ASSERT_TRUE(cloud.ok());
  EXPECT_FALSE(cloud->is_valid(0));
  EXPECT_TRUE(cloud->is_valid(1));
  EXPECT_FALSE(cloud->is_valid(2));
  EXPECT_EQ(cloud->count_valid(), 2u);
}

TEST(CameraDecode, C16WithoutInvalidFlagKeepsZeroAsAValue) {
  std::vector<std::uint16_t> raw{0, 10};
  auto p = params(1.0, 300.0, 0);
  p.invalid_data_flag = false;
  auto cloud = fd::decode_frame(frame(fd::pfnc::Coord3D_C16, 2, 1, raw), p);
  ASSERT_TRUE(cloud.ok());
  EXPECT_EQ(cloud->count_valid(), 2u);
  EXPECT_NEAR(cloud->points[0].z(), 300.0, 1e-4);
}

TEST(CameraDecode, DistanceUnitInchIsConvertedToMillimetres) {
  std::vector<std::uint16_t> raw{10};
  auto p = params(1.0, 0.0, 0);
  p.unit_mm = 25.4;
  auto cloud = fd::decode_frame(frame(fd::pfnc::Coord3D_C16, 1, 1, raw), p);
  ASSERT_TRUE(cloud.ok());
  EXPECT_NEAR(cloud->points[0].z(), 254.0, 1e-3);
}

TEST(CameraDecode, C32fRangeMapWithNaNAndInvalidValue) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  std::vector<float> raw{812.5f, nan, -1.0f, 400.0f};
  auto p = params(1.0, 0.0, 0);
  p.invalid_data_value = -1.0;
  auto cloud = fd::decode_frame(frame(fd::pfnc::Coord3D_C32f, 2, 2, raw), p);
  ASSERT_TRUE(cloud.ok()) << cloud.error().message;
  EXPECT_NEAR(cloud->points[0].z(), 812.5, 1e-4);
  EXPECT_NEAR(cloud->points[0].x(), (0 - 31.5) / 500.0 * 812.5, 1e-3);
  EXPECT_FALSE(cloud->is_valid(1));
  EXPECT_FALSE(cloud->is_valid(2));
  EXPECT_NEAR(cloud->points[3].y(), (1 - 23.5) / 400.0 * 400.0, 1e-3);
}

TEST(CameraDecode, ABC32fPointCloudIsTakenAsIs) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  std::vector<float> raw{1.f, 2.f, 3.f, nan, nan, nan, -5.5f, 6.25f, 700.f};
  auto p = params(1.0, 0.0, 0);
  p.intrinsics.reset();  // not needed for point clouds
  auto cloud = fd::decode_frame(frame(fd::pfnc::Coord3D_ABC32f, 3, 1, raw), p);
  ASSERT_TRUE(cloud.ok()) << cloud.error().message;
  EXPECT_EQ(cloud->points[0], Eigen::Vector3f(1.f, 2.f, 3.f));
  EXPECT_FALSE(cloud->is_valid(1));
  EXPECT_EQ(cloud->points[2], Eigen::Vector3f(-5.5f, 6.25f, 700.f));
}

TEST(CameraDecode, OtherPixelFormatsAreAClearErrorNamingThem) {
  std::vector<std::uint8_t> raw(16, 7);
  auto cloud = fd::decode_frame(frame(fd::pfnc::Mono8, 4, 4, raw), params(1, 0, 0));
  ASSERT_FALSE(cloud.ok());
  EXPECT_EQ(cloud.error().code, "camera.unsupported_pixel_format");
  EXPECT_THAT(cloud.error().message, HasSubstr("unsupported pixel format Mono8"));
  auto unknown = fd::decode_frame(frame(0x01234567u, 4, 4, raw), params(1, 0, 0));
  ASSERT_FALSE(unknown.ok());
  EXPECT_THAT(unknown.error().message, HasSubstr("unsupported pixel format 0x01234567"));
}

TEST(CameraDecode, ShortFrameIsAnError) {
  std::vector<std::uint16_t> raw(10);
  auto cloud = fd::decode_frame(frame(fd::pfnc::Coord3D_C16, 4, 4, raw), params(1, 0, 0));
  ASSERT_FALSE(cloud.ok());
  EXPECT_EQ(cloud.error().code, "camera.bad_frame");
}

TEST(CameraDecode, RangeMapWithoutIntrinsicsSaysWhatToDo) {
  std::vector<std::uint16_t> raw(4, 9);
  auto p = params(1, 0, 0);
  p.intrinsics.reset();
  auto cloud = fd::decode_frame(frame(fd::pfnc::Coord3D_C16, 2, 2, raw), p);
  ASSERT_FALSE(cloud.ok());
  EXPECT_EQ(cloud.error().code, "camera.no_intrinsics");
  EXPECT_THAT(cloud.error().message, HasSubstr("calibration"));
}

TEST(CameraDecode, PixelFormatNames) {
  EXPECT_EQ(fd::pixel_format_name(fd::pfnc::Coord3D_C16), "Coord3D_C16");
  EXPECT_EQ(fd::pixel_format_from_name("Coord3D_ABC32f"), fd::pfnc::Coord3D_ABC32f);
  EXPECT_FALSE(fd::pixel_format_from_name("Nope").has_value());
  EXPECT_TRUE(fd::is_supported_pixel_format(fd::pfnc::Coord3D_C32f));
  EXPECT_FALSE(fd::is_supported_pixel_format(fd::pfnc::Mono16));
}

TEST(CameraPly, OrganizedCloudRoundTripsWithNaN) {
  fettle::OrganizedCloud c;
  c.width = 3;
  c.height = 2;
  c.points = {{1, 2, 3}, fettle::OrganizedCloud::invalid(), {4, 5, 6}, {7, 8, 9}, {-1, -2, 1000}, {0, 0, 0.5f}};
  const auto file = std::filesystem::temp_directory_path() / ("fettle-ply-" + std::to_string(::getpid()) + ".ply");
  ASSERT_TRUE(fettle::write_ply(file, c).ok());
  auto back = fettle::read_ply(file);
  std::filesystem::remove(file);
  ASSERT_TRUE(back.ok()) << back.error().message;
  EXPECT_EQ(back->width, 3u);
  EXPECT_EQ(back->height, 2u);
  ASSERT_EQ(back->points.size(), 6u);
  EXPECT_FALSE(back->is_valid(1));
  EXPECT_EQ(back->points[4], Eigen::Vector3f(-1, -2, 1000));
}
