// Bad camera data: frames whose size fields overflow or lie, and PLY scans (fettle::read_ply)
// with headers that lie about the vertex count or claim billions of vertices. Each is refused
// with its error code; none may read past the data or allocate more than the data can fill.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <vector>

#include "../support/child_process.hpp"
#include "fettle/drivers/camera_decode.hpp"
#include "fettle/core/ply.hpp"

namespace fd = fettle::drivers;
namespace fs = std::filesystem;
using fettle::test::ChildOutcome;
using ::testing::HasSubstr;

namespace {

fd::Scan3dParameters with_intrinsics() {
  fd::Scan3dParameters p;
  p.intrinsics = fd::Intrinsics{500.0, 500.0, 4.0, 3.0};
  return p;
}

class PlyBadInput : public ::testing::Test {
 protected:
  fs::path write(const std::string& name, const std::string& bytes) {
    const auto p = fs::temp_directory_path() / ("fettle-ply-bad-" + std::to_string(::getpid()) + "-" + name);
    std::ofstream(p, std::ios::binary) << bytes;
    files_.push_back(p);
    return p;
  }
  void TearDown() override {
    for (const auto& f : files_) fs::remove(f);
  }
  std::vector<fs::path> files_;
};

std::string header(const std::string& vertices, const std::string& cols = "", const std::string& rows = "") {
  std::string h = "ply\nformat binary_little_endian 1.0\n";
  if (!cols.empty()) h += "obj_info num_cols " + cols + "\n";
  if (!rows.empty()) h += "obj_info num_rows " + rows + "\n";
  return h + "element vertex " + vertices + "\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
}

std::string xyz(int n) {
  std::vector<float> v;
  for (int i = 0; i < 3 * n; ++i) v.push_back(static_cast<float>(i));
  std::string s(v.size() * sizeof(float), '\0');
  std::memcpy(s.data(), v.data(), s.size());
  return s;
}

}  // namespace

TEST(CameraDecodeBadInput, SizeThatOverflowsIsABadFrameNotAHugeCloud) {
  // 2^32-1 squared pixels of 12 bytes overflows 64 bits; the payload is 24 bytes.
  std::vector<std::byte> payload(24);
  const auto big = std::numeric_limits<std::uint32_t>::max();
  for (std::uint32_t format : {fd::pfnc::Coord3D_ABC32f, fd::pfnc::Coord3D_C32f, fd::pfnc::Coord3D_C16}) {
    fd::RawFrame f{format, big, big, payload.data(), payload.size()};
    auto cloud = fd::decode_frame(f, with_intrinsics());
    ASSERT_FALSE(cloud.ok()) << fd::pixel_format_name(format);
    EXPECT_EQ(cloud.error().code, "camera.bad_frame");
  }
  // Sizes whose product needs more than 32 bits but not 64.
  fd::RawFrame f{fd::pfnc::Coord3D_ABC32f, 0x10000, 0x10000, payload.data(), payload.size()};
  EXPECT_EQ(fd::decode_frame(f, with_intrinsics()).error().code, "camera.bad_frame");
}

TEST(CameraDecodeBadInput, ZeroSizeOrNoDataIsABadFrame) {
  std::vector<std::uint16_t> raw(4, 100);
  const auto* data = reinterpret_cast<const std::byte*>(raw.data());
  EXPECT_EQ(fd::decode_frame({fd::pfnc::Coord3D_C16, 0, 2, data, 8}, with_intrinsics()).error().code, "camera.bad_frame");
  EXPECT_EQ(fd::decode_frame({fd::pfnc::Coord3D_C16, 2, 0, data, 8}, with_intrinsics()).error().code, "camera.bad_frame");
  EXPECT_EQ(fd::decode_frame({fd::pfnc::Coord3D_C16, 2, 2, nullptr, 8}, with_intrinsics()).error().code,
            "camera.bad_frame");
}

TEST(CameraDecodeBadInput, NonFiniteScan3dParametersGiveNaNOrAnErrorNeverACrash) {
  std::vector<std::uint16_t> raw(4, 100);
  auto p = with_intrinsics();
  p.scale = std::numeric_limits<double>::infinity();
  p.offset = std::numeric_limits<double>::quiet_NaN();
  p.invalid_data_value = std::numeric_limits<double>::quiet_NaN();
  p.invalid_data_flag = true;
  auto cloud = fd::decode_frame({fd::pfnc::Coord3D_C16, 2, 2, reinterpret_cast<const std::byte*>(raw.data()), 8}, p);
  ASSERT_TRUE(cloud.ok());
  EXPECT_EQ(cloud->count_valid(), 0U);  // z = inf * 100 + NaN: no valid point
  p.intrinsics->fx_px = 0.0;
  EXPECT_EQ(fd::decode_frame({fd::pfnc::Coord3D_C16, 2, 2, reinterpret_cast<const std::byte*>(raw.data()), 8}, p)
                .error()
                .code,
            "camera.no_intrinsics");
}

TEST_F(PlyBadInput, HeaderClaimingMoreVerticesThanTheFileHoldsIsTruncated) {
  const auto f = write("short.ply", header("1000", "40", "25") + xyz(3));
  auto cloud = fettle::read_ply(f);
  ASSERT_FALSE(cloud.ok());
  EXPECT_EQ(cloud.error().code, "ply.bad");
  EXPECT_THAT(cloud.error().message, HasSubstr(f.string()));
}

TEST_F(PlyBadInput, HeaderClaimingBillionsOfVerticesIsRefusedWithoutAllocating) {
  const auto f = write("billions.ply", header("4000000000", "64000", "62500") + xyz(3));
  const auto out = fettle::test::run_in_child([f] {
    auto cloud = fettle::read_ply(f);
    if (cloud.ok() || cloud.error().code != "ply.bad") std::_Exit(3);
  });
  EXPECT_TRUE(out.how == ChildOutcome::How::returned) << out.detail;
  EXPECT_LT(out.max_rss_mb, 512);
  // Also more than 2^32 vertices (the grid size cannot hold them).
  const auto g = write("huge.ply", header("99999999999999999") + xyz(1));
  auto cloud = fettle::read_ply(g);
  ASSERT_FALSE(cloud.ok());
  EXPECT_EQ(cloud.error().code, "ply.bad");
}

TEST_F(PlyBadInput, GridThatDoesNotMatchTheVerticesBecomesOneRow) {
  const auto f = write("grid.ply", header("6", "4", "4") + xyz(6));
  auto cloud = fettle::read_ply(f);
  ASSERT_TRUE(cloud.ok()) << cloud.error().message;
  EXPECT_EQ(cloud->width, 6U);
  EXPECT_EQ(cloud->height, 1U);
  // A grid whose product overflows 32 bits is not taken as matching either.
  const auto g = write("overflow.ply", header("0", "65536", "65536"));
  auto empty = fettle::read_ply(g);
  ASSERT_TRUE(empty.ok()) << empty.error().message;
  EXPECT_EQ(std::size_t{empty->width} * empty->height, empty->points.size());
}

TEST_F(PlyBadInput, GarbageHeadersAreRefused) {
  for (const auto& [name, text] : std::vector<std::pair<std::string, std::string>>{
           {"empty.ply", ""},
           {"ascii.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                         "property float z\nend_header\n1 2 3\n"},
           {"doubles.ply", "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty double x\n"
                           "property double y\nproperty double z\nend_header\n"},
           {"negative.ply", header("-5") + xyz(1)},
           {"no_end.ply", "ply\nformat binary_little_endian 1.0\nelement vertex 1\n"},
           {"binary_junk.ply", std::string("\0\xff\x10ply\n\n\n", 8)}}) {
    const auto f = write(name, text);
    auto cloud = fettle::read_ply(f);
    EXPECT_FALSE(cloud.ok()) << name;
    if (!cloud.ok()) {
      EXPECT_EQ(cloud.error().code, "ply.bad") << name;
    }
  }
}
