// Fettle's own PCD and PLY readers (vision/src/cloud_readers.cpp, used by load_cloud) against
// the Point Cloud Library as an independent peer: files PCL's writers write in every encoding,
// and the public PCD and PLY files in tests/data, read the same through both; plus the field
// types PCL itself cannot convert, big-endian PLY, and errors that must name the line at fault.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include <pcl/io/pcd_io.h>
#include <pcl/io/ply_io.h>
#include <pcl/point_types.h>

#include "fettle/core/error.hpp"
#include "fettle/vision/cloud.hpp"
#include "test_support.hpp"
#include "../support/draws.hpp"

using fettle::UserError;
using fettle::vision::Cloud;
using fettle::vision::load_cloud;
using ::testing::HasSubstr;
namespace fs = std::filesystem;

namespace {

class CloudReaders : public fettle::vision::test::TempFilesTest {
 protected:
  CloudReaders() : TempFilesTest("fettle-pcd-") {}
};

/// An organized 40 x 30 cloud with normals, a curvature field and a tenth of its points NaN
/// (as a structured-light camera delivers them).
pcl::PointCloud<pcl::PointNormal> organized_cloud() {
  pcl::PointCloud<pcl::PointNormal> pc(40, 30);
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(-100.0f, 100.0f);
  for (auto& p : pc) {
    p.x = u(rng);
    p.y = u(rng);
    p.z = 600.0f + u(rng);
    const auto a = fettle::test::draws<3>(u, rng);
    const Eigen::Vector3f n = Eigen::Vector3f(a[0], a[1], a[2] + 150.0f).normalized();
    p.normal_x = n.x();
    p.normal_y = n.y();
    p.normal_z = n.z();
    p.curvature = 0.01f;
    if (rng() % 10 == 0) p.x = p.y = p.z = std::numeric_limits<float>::quiet_NaN();
  }
  pc.is_dense = false;
  return pc;
}

/// PCL's own reading of a file: its finite points, in order.
std::vector<Eigen::Vector3f> pcl_points(const fs::path& file) {
  pcl::PointCloud<pcl::PointXYZ> pc;
  if (file.extension() == ".ply")
    EXPECT_EQ(pcl::io::loadPLYFile(file.string(), pc), 0) << file;
  else
    EXPECT_EQ(pcl::io::loadPCDFile(file.string(), pc), 0) << file;
  std::vector<Eigen::Vector3f> out;
  for (const auto& p : pc)
    if (p.getVector3fMap().allFinite()) out.push_back(p.getVector3fMap());
  return out;
}

}  // namespace

TEST_F(CloudReaders, ReadsWhatPclWritesInAllThreeEncodings) {
  const auto pc = organized_cloud();
  std::size_t finite = 0;
  for (const auto& p : pc) finite += p.getVector3fMap().allFinite() ? 1 : 0;
  ASSERT_GT(finite, 1000U);
  ASSERT_LT(finite, pc.size());
  pcl::PCDWriter writer;
  for (const char* encoding : {"ascii", "binary", "binary_compressed"}) {
    const auto f = path(std::string("written_") + encoding + ".pcd");
    const std::string e = encoding;
    const int rc = e == "ascii" ? writer.writeASCII(f.string(), pc, 9)
                   : e == "binary" ? writer.writeBinary(f.string(), pc)
                                   : writer.writeBinaryCompressed(f.string(), pc);
    ASSERT_EQ(rc, 0) << encoding;
    const Cloud c = load_cloud(f);
    ASSERT_EQ(c.size(), finite) << encoding;
    ASSERT_TRUE(c.has_normals()) << encoding;
    std::size_t k = 0;
    for (const auto& p : pc) {
      if (!p.getVector3fMap().allFinite()) continue;
      ASSERT_LT((c.points[k] - p.getVector3fMap()).norm(), 1e-4f) << encoding << " point " << k;
      ASSERT_LT((c.normals[k] - p.getNormalVector3fMap()).norm(), 1e-5f) << encoding << " normal " << k;
      ++k;
    }
  }
}

TEST_F(CloudReaders, PublicFilesReadAsPclReadsThem) {
  // bun0 and sac_plane_test: ASCII PCD with normals; bun4: PCD v.5; milk: binary_compressed;
  // the cluttered scene: organized 640 x 480, binary_compressed, an rgba field, NaN points;
  // the KITTI pair: binary PLY.
  const std::vector<std::pair<const char*, std::size_t>> files = {
      {"bun0.pcd", 300}, {"bun4.pcd", 300}, {"sac_plane_test.pcd", 300}, {"milk.pcd", 300},
      {"milk_cartoon_all_small_clorox.pcd", 300}, {"kitti_source.ply", 1000}, {"kitti_target.ply", 1000}};
  for (const auto& [name, at_least] : files) {
    const auto file = fettle::vision::test::data(name);
    const auto expected = pcl_points(file);
    const Cloud c = load_cloud(file);
    ASSERT_EQ(c.size(), expected.size()) << name;
    ASSERT_GT(c.size(), at_least) << name;
    for (std::size_t i = 0; i < c.size(); ++i) ASSERT_EQ(c.points[i], expected[i]) << name << " point " << i;
  }
}

TEST_F(CloudReaders, IntegerAndDoubleCoordinatesAreConverted) {
  // x as int16, y as uint8, z as float64 (PCL's fromPCLPointCloud2 would give zeros for these).
  std::string data = "VERSION 0.7\nFIELDS x y z\nSIZE 2 1 8\nTYPE I U F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA binary\n";
  auto put = [&](auto v) { data.append(reinterpret_cast<const char*>(&v), sizeof v); };
  put(std::int16_t{-300});
  put(std::uint8_t{200});
  put(double{12.5});
  put(std::int16_t{7});
  put(std::uint8_t{0});
  put(double{-0.25});
  const Cloud c = load_cloud(write("types.pcd", data));
  ASSERT_EQ(c.size(), 2U);
  EXPECT_EQ(c.points[0], Eigen::Vector3f(-300, 200, 12.5f));
  EXPECT_EQ(c.points[1], Eigen::Vector3f(7, 0, -0.25f));
  const Cloud a = load_cloud(write("types_ascii.pcd", data.substr(0, data.find("DATA")) + "DATA ascii\n-300 200 12.5\n+7 0 -2.5e-1\n"));
  ASSERT_EQ(a.size(), 2U);
  EXPECT_EQ(a.points[1], Eigen::Vector3f(7, 0, -0.25f));
}

TEST_F(CloudReaders, MistakesAreNamedWithTheirLine) {
  const std::string head = "# a comment\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\n";
  struct Case {
    std::string name, text, message;
  };
  const std::vector<Case> cases = {
      {"bad_value.pcd", head + "DATA ascii\n1 2 3\n4 five 6\n", "line 12: field 'y' value 'five' is not a number"},
      {"short_line.pcd", head + "DATA ascii\n1 2 3\n40 50\n", "line 12: 2 values, the header's fields need 3"},
      {"int_range.pcd", "FIELDS x y z\nSIZE 1 4 4\nTYPE U F F\nWIDTH 1\nDATA ascii\n300 1 2\n", "field 'x' value '300' is not a number of TYPE U SIZE 1"},
      {"unknown_key.pcd", std::string(head).replace(head.find("VERSION"), 7, "VERSIO"), "PCD header, line 2: unknown line 'VERSIO 0.7'"},
      {"two_fields.pcd", head + "FIELDS a b c\nDATA ascii\n", "PCD header, line 10: a second FIELDS line"},
      {"bad_width.pcd", std::string(head).replace(head.find("WIDTH 2"), 7, "WIDTH -2"), "PCD header, line 7: WIDTH '-2' is not one whole number"},
      {"f2.pcd", std::string(head).replace(head.find("SIZE 4 4 4"), 10, "SIZE 4 2 4") + "DATA ascii\n1 2 3\n4 5 6\n", "field 'y' has TYPE F with SIZE 2"},
      {"disagree.pcd", std::string(head).replace(head.find("POINTS 2"), 8, "POINTS 3") + "DATA ascii\n1 2 3\n4 5 6\n", "WIDTH x HEIGHT (2 x 1 = 2) and POINTS (3) disagree"},
      {"no_data_format.pcd", head + "DATA\n", "PCD header, line 10: DATA without a value"},
      {"bad_data_format.pcd", head + "DATA text\n", "DATA 'text' is not ascii, binary or binary_compressed"},
      {"corrupt_lzf.pcd", head + "DATA binary_compressed\n" + std::string("\x08\x00\x00\x00\x18\x00\x00\x00\xff\xff\xff\xff\xff\xff\xff\xff", 16),
       "the compressed data is corrupt"},
      {"wrong_uncompressed.pcd", head + "DATA binary_compressed\n" + std::string("\x08\x00\x00\x00\x10\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00", 16),
       "uncompresses to 16 bytes, the header's 2 points of 12 bytes need 24"},
  };
  for (const auto& c : cases) {
    const auto f = write(c.name, c.text);
    EXPECT_THAT([&] { (void)load_cloud(f); }, ::testing::ThrowsMessage<UserError>(HasSubstr(c.message))) << c.name;
    EXPECT_THAT([&] { (void)load_cloud(f); }, ::testing::ThrowsMessage<UserError>(HasSubstr(f.string()))) << c.name;
  }
}

TEST_F(CloudReaders, Pcd5FileWithOnlyPointsAndNoCount) {
  const Cloud c = load_cloud(write("v5.pcd", "VERSION .5\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 2\nDATA ascii\n1 2 3\n\n4 5 6\n"));
  ASSERT_EQ(c.size(), 2U);
  EXPECT_EQ(c.points[1], Eigen::Vector3f(4, 5, 6));
}

TEST_F(CloudReaders, CompressedFuzzSeedReadsAsPclReadsIt) {
  // fuzz_cloud's binary_compressed seed (tests/fuzz/make_corpus.py compresses it with literal
  // runs and back references): organized 8 x 8, one row of NaN points, an rgba field. It must
  // be a valid file, or the fuzzer would only ever explore the error paths from it.
  std::ifstream in(fs::path(FETTLE_SOURCE_DIR) / "tests/fuzz/corpus/cloud/organized_compressed.pcd", std::ios::binary);
  ASSERT_TRUE(in);
  const std::string seed(std::istreambuf_iterator<char>(in), {});
  const auto f = write("seed.pcd", seed.substr(1));  // the first byte picks fuzz_cloud's extension
  const auto expected = pcl_points(f);
  const Cloud c = load_cloud(f);
  ASSERT_EQ(c.size(), 56U);
  ASSERT_EQ(expected.size(), 56U);
  for (std::size_t i = 0; i < c.size(); ++i) EXPECT_EQ(c.points[i], expected[i]) << i;
  EXPECT_EQ(c.points[8], Eigen::Vector3f(0, 2, 600));
}

TEST_F(CloudReaders, ReadsWhatPclWritesAsPly) {
  const auto pc = organized_cloud();
  pcl::PLYWriter writer;
  for (const bool binary : {false, true}) {
    const auto f = path(binary ? "written_binary.ply" : "written_ascii.ply");
    ASSERT_EQ(writer.write(f.string(), pc, binary, false), 0);
    const auto expected = pcl_points(f);
    const Cloud c = load_cloud(f);
    ASSERT_EQ(c.size(), expected.size()) << f;
    ASSERT_GT(c.size(), 1000U);
    ASSERT_TRUE(c.has_normals()) << f;
    for (std::size_t i = 0; i < c.size(); ++i) ASSERT_LT((c.points[i] - expected[i]).norm(), 1e-3f) << f << " point " << i;
  }
}

TEST_F(CloudReaders, BigEndianPlyWithAnElementBeforeTheVerticesAndAVertexList) {
  auto be = [](auto v) {
    std::string b(sizeof v, '\0');
    std::memcpy(b.data(), &v, sizeof v);
    return std::string(b.rbegin(), b.rend());
  };
  std::string data = "ply\nformat binary_big_endian 1.0\ncomment written by hand\nelement camera 1\n"
                     "property list uchar float k\nproperty double f\nelement vertex 2\nproperty float x\n"
                     "property list uchar int idx\nproperty short y\nproperty double z\nend_header\n";
  data += std::string(1, '\x02') + be(1.5f) + be(2.5f) + be(800.0);                                   // camera
  data += be(10.25f) + std::string(1, '\x01') + be(std::int32_t{7}) + be(std::int16_t{-3}) + be(600.5);  // vertex 0
  data += be(-4.0f) + std::string(1, '\x00') + be(std::int16_t{9}) + be(0.125);                        // vertex 1
  const Cloud c = load_cloud(write("big_endian.ply", data));
  ASSERT_EQ(c.size(), 2U);
  EXPECT_EQ(c.points[0], Eigen::Vector3f(10.25f, -3, 600.5f));
  EXPECT_EQ(c.points[1], Eigen::Vector3f(-4, 9, 0.125f));
  // Cut one byte short, it is refused and the message says where the data ran out.
  const auto cut = write("big_endian_cut.ply", data.substr(0, data.size() - 1));
  EXPECT_THAT([&] { (void)load_cloud(cut); }, ::testing::ThrowsMessage<UserError>(HasSubstr("vertex 1 property 'z'")));
}

TEST_F(CloudReaders, PlyDataMistakesAreNamed) {
  const std::string head = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
  EXPECT_THAT([&] { (void)load_cloud(write("bad.ply", head + "1 2 3\n4 five 6\n")); },
              ::testing::ThrowsMessage<UserError>(HasSubstr("line 9: vertex 1 property 'y' 'five' is not a number")));
  EXPECT_THAT([&] { (void)load_cloud(write("noformat.ply", "ply\nelement vertex 1\nproperty float x\nend_header\n1 2 3\n")); },
              ::testing::ThrowsMessage<UserError>(HasSubstr("has no format line")));
  EXPECT_THAT([&] { (void)load_cloud(write("novertex.ply", "ply\nformat ascii 1.0\nelement face 0\nend_header\n")); },
              ::testing::ThrowsMessage<UserError>(HasSubstr("has no vertex element")));
  const std::string neg = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty list char float q\nproperty float x\n"
                          "property float y\nproperty float z\nend_header\n" + std::string(1, '\xff') + std::string(12, '\0');
  EXPECT_THAT([&] { (void)load_cloud(write("neg.ply", neg)); },
              ::testing::ThrowsMessage<UserError>(HasSubstr("vertex 0 property 'q' has a negative list count")));
}

TEST_F(CloudReaders, WhatOtherWritersWriteIsRead) {
  // PCL writes bool fields as TYPE B SIZE 1; some writers use lower-case type letters; PCD .5
  // files may have FIELDS without SIZE and TYPE (every field F 4).
  const Cloud b = load_cloud(write("bool.pcd", "VERSION 0.7\nFIELDS x y z valid\nSIZE 4 4 4 1\nTYPE f F F B\nCOUNT 1 1 1 1\n"
                                               "WIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n1 2 3 1\n4 5 6 0\n"));
  ASSERT_EQ(b.size(), 2U);
  EXPECT_EQ(b.points[1], Eigen::Vector3f(4, 5, 6));
  const Cloud v5 = load_cloud(write("v5_no_size.pcd", "VERSION .5\nFIELDS x y z\nPOINTS 1\nDATA ascii\n7 8 9\n"));
  ASSERT_EQ(v5.size(), 1U);
  EXPECT_EQ(v5.points[0], Eigen::Vector3f(7, 8, 9));
  // A PLY element after the vertices is not read, so a type Fettle does not know there is fine.
  const Cloud faces = load_cloud(write("faces_unknown.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                                                            "property float y\nproperty float z\nelement face 1\n"
                                                            "property list uchar quad idx\nend_header\n1 2 3\n"));
  EXPECT_EQ(faces.size(), 1U);
}

TEST_F(CloudReaders, AHugeHeaderLineIsRefusedWithoutReadingIt) {
  const std::string fields(200000, 'a');
  EXPECT_THAT([&] { (void)load_cloud(write("long.pcd", "VERSION 0.7\nFIELDS " + fields + "\nDATA ascii\n")); },
              ::testing::ThrowsMessage<UserError>(HasSubstr("line 2: a line of 200007 bytes")));
  EXPECT_THAT([&] { (void)load_cloud(write("long.ply", "ply\ncomment " + fields + "\nend_header\n")); },
              ::testing::ThrowsMessage<UserError>(HasSubstr("line 2: a line of 200008 bytes")));
}
