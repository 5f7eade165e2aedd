// Bad point-cloud files for load_cloud (PLY and PCD through Fettle's readers): NaN / Inf, no
// points, headers that lie about the point count, headers claiming billions of points. Every
// one is a UserError naming the file, or the finite points that are really there; none may
// crash or allocate gigabytes (checked in a child process with a memory cap).
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <string>
#include <vector>

#include "../support/child_process.hpp"
#include "fettle/core/error.hpp"
#include "fettle/vision/cloud.hpp"
#include "test_support.hpp"

using fettle::UserError;
using fettle::test::ChildOutcome;
using fettle::test::run_in_child;
using fettle::vision::Cloud;
using fettle::vision::load_cloud;
using ::testing::HasSubstr;
namespace fs = std::filesystem;

namespace {

class CloudBadInput : public fettle::vision::test::TempFilesTest {
 protected:
  CloudBadInput() : TempFilesTest("fettle-cloud-bad-") {}
};

std::string floats(const std::vector<float>& v) {
  std::string s(v.size() * sizeof(float), '\0');
  std::memcpy(s.data(), v.data(), s.size());
  return s;
}

std::string pcd_header(const std::string& width, const std::string& points, const std::string& data) {
  return "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH " + width +
         "\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS " + points + "\nDATA " + data + "\n";
}

std::string ply_header(const std::string& format, const std::string& vertices) {
  return "ply\nformat " + format + " 1.0\nelement vertex " + vertices +
         "\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
}

/// Loads in a child with a 2 GB cap: must end in a UserError or a cloud, within the cap.
ChildOutcome load_in_child(const fs::path& file) {
  return run_in_child([file] {
    try {
      (void)load_cloud(file);
    } catch (const UserError&) {
    }
  });
}

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();

}  // namespace

TEST_F(CloudBadInput, NaNAndInfPointsAreDroppedAndFinitePointsKept) {
  const auto ply = write("mixed.ply", ply_header("binary_little_endian", "4") +
                                          floats({kNaN, 0, 0, 1, kInf, 2, 3, 4, 5, -kInf, 1, 1}));
  const Cloud c = load_cloud(ply);
  ASSERT_EQ(c.size(), 1U);
  EXPECT_EQ(c.points[0], Eigen::Vector3f(3, 4, 5));
  const auto pcd = write("mixed.pcd", pcd_header("3", "3", "ascii") + "nan 1 2\n1 inf 2\n7 8 9\n");
  const Cloud d = load_cloud(pcd);
  ASSERT_EQ(d.size(), 1U);
  EXPECT_EQ(d.points[0], Eigen::Vector3f(7, 8, 9));
}

TEST_F(CloudBadInput, OnlyInfinitePointsIsAUserErrorSayingSo) {
  const auto ply = write("inf.ply", ply_header("binary_little_endian", "2") + floats({kInf, 0, 0, 0, -kInf, 0}));
  EXPECT_THAT([&] { (void)load_cloud(ply); }, ::testing::ThrowsMessage<UserError>(HasSubstr("none is valid")));
}

TEST_F(CloudBadInput, NoPointsIsAUserErrorNamingTheFile) {
  for (const auto& [name, text] : std::vector<std::pair<std::string, std::string>>{
           {"zero.ply", ply_header("binary_little_endian", "0")},
           {"zero_ascii.ply", ply_header("ascii", "0")},
           {"zero.pcd", pcd_header("0", "0", "ascii")},
           {"zero_binary.pcd", pcd_header("0", "0", "binary")},
           {"empty.ply", ""},
           {"empty.pcd", ""}}) {
    const auto f = write(name, text);
    EXPECT_THAT([&] { (void)load_cloud(f); }, ::testing::ThrowsMessage<UserError>(HasSubstr(f.string()))) << name;
  }
}

TEST_F(CloudBadInput, HeaderClaimingMorePointsThanTheFileHolds) {
  // Three points in the file; the headers claim a thousand.
  const auto ply = write("short.ply", ply_header("binary_little_endian", "1000") + floats({1, 2, 3, 4, 5, 6, 7, 8, 9}));
  const auto ply_ascii = write("short_ascii.ply", ply_header("ascii", "1000") + "1 2 3\n4 5 6\n7 8 9\n");
  const auto pcd = write("short.pcd", pcd_header("1000", "1000", "binary") + floats({1, 2, 3, 4, 5, 6, 7, 8, 9}));
  const auto pcd_ascii = write("short_ascii.pcd", pcd_header("1000", "1000", "ascii") + "1 2 3\n4 5 6\n7 8 9\n");
  for (const auto& f : {ply, ply_ascii, pcd, pcd_ascii}) {
    try {
      const Cloud c = load_cloud(f);
      EXPECT_LE(c.size(), 3U) << f << ": points that are not in the file";
    } catch (const UserError& e) {
      EXPECT_THAT(e.what(), HasSubstr(f.string()));
    }
  }
}

TEST_F(CloudBadInput, HeaderClaimingFewerPointsThanTheFileHolds) {
  const auto ply = write("long.ply", ply_header("binary_little_endian", "1") + floats({1, 2, 3, 4, 5, 6}));
  const Cloud c = load_cloud(ply);
  ASSERT_EQ(c.size(), 1U);
  EXPECT_EQ(c.points[0], Eigen::Vector3f(1, 2, 3));
}

TEST_F(CloudBadInput, PcdWidthAndPointsDisagree) {
  const auto pcd = write("disagree.pcd", pcd_header("5", "2", "ascii") + "1 2 3\n4 5 6\n");
  try {
    const Cloud c = load_cloud(pcd);
    EXPECT_LE(c.size(), 2U);
  } catch (const UserError& e) {
    EXPECT_THAT(e.what(), HasSubstr(pcd.string()));
  }
}

TEST_F(CloudBadInput, HeaderClaimingBillionsOfPointsDoesNotAllocateGigabytes) {
  const std::string three = floats({1, 2, 3, 4, 5, 6, 7, 8, 9});
  const std::vector<fs::path> files = {
      write("billions.ply", ply_header("binary_little_endian", "4000000000") + three),
      write("billions_ascii.ply", ply_header("ascii", "4000000000") + "1 2 3\n"),
      write("billions.pcd", pcd_header("4000000000", "4000000000", "binary") + three),
      write("billions_ascii.pcd", pcd_header("4000000000", "4000000000", "ascii") + "1 2 3\n"),
      write("billions_compressed.pcd", pcd_header("4000000000", "4000000000", "binary_compressed") +
                                           std::string("\x10\x00\x00\x00\x00\x00\x00\x10", 8) + three),
  };
  for (const auto& f : files) {
    const auto out = load_in_child(f);
    EXPECT_TRUE(out.how == ChildOutcome::How::returned) << f.filename() << ": " << out.detail
                                                        << (out.how == ChildOutcome::How::bad_alloc ? " (bad_alloc)" : "");
    EXPECT_LT(out.max_rss_mb, 1024) << f.filename();
  }
}

TEST_F(CloudBadInput, PcdHeadersThatCrashPclAreRefusedFirst) {
  // PCL 1.13's PCDReader segfaults on each of these (found by fuzz_cloud); load_cloud reads PCD
  // itself, and its reader names the header's mistake.
  const std::string good = pcd_header("1", "1", "ascii") + "1 2 3\n";
  const auto no_size = write("no_size.pcd", std::string(good).replace(good.find("SIZE"), 4, ",IZE"));
  const auto binary_line = write("binary_line.pcd", std::string(good).insert(good.find("VERSION"), std::string("\0\0HB\0\n", 6)));
  const auto mismatch = write("mismatch.pcd", std::string(good).replace(good.find("TYPE F F F"), 10, "TYPE F F"));
  const auto count0 = write("count0.pcd", std::string(good).replace(good.find("COUNT 1 1 1"), 11, "COUNT 0 1 1"));
  for (const auto& f : {no_size, binary_line, mismatch, count0}) {
    const auto out = load_in_child(f);
    EXPECT_TRUE(out.how == ChildOutcome::How::returned) << f.filename() << ": " << out.detail;
    EXPECT_THAT([&] { (void)load_cloud(f); }, ::testing::ThrowsMessage<UserError>(HasSubstr("PCD header"))) << f;
  }
}

TEST_F(CloudBadInput, BinaryPcdWithHeaderLikeBytesInItsDataIsReadAsItsHeaderSays) {
  // Found by fuzz_cloud: a binary PCD of 64 points with normals whose data begins with
  // "COLUMNS"; PCL's PCDReader takes that for a header line, and fromPCLPointCloud2 reads past
  // the end of the buffer (AddressSanitizer: heap-buffer-overflow). Fettle's reader takes the
  // header at its word: the data starts after the DATA line and holds the 64 points.
  const fs::path reproducer = fs::path(FETTLE_SOURCE_DIR) / "tests/fuzz/regressions/cloud/pcd-header-lies-about-data-size";
  ASSERT_TRUE(fs::exists(reproducer)) << reproducer;
  std::ifstream in(reproducer, std::ios::binary);
  const std::string input(std::istreambuf_iterator<char>(in), {});
  const auto f = write("lies.pcd", input.substr(1));  // fuzz_cloud's first byte picks the extension
  const Cloud c = load_cloud(f);
  EXPECT_GT(c.size(), 0U);
  EXPECT_LE(c.size(), 64U);
  for (const auto& p : c.points) EXPECT_TRUE(p.allFinite());
  // Cut inside the data, the same file is refused and the message says how much is missing.
  const auto cut = write("cut.pcd", input.substr(1, input.find("DATA binary\n") + 12 + 100 - 1));
  EXPECT_THAT([&] { (void)load_cloud(cut); }, ::testing::ThrowsMessage<UserError>(HasSubstr("bytes of point data")));
}

TEST_F(CloudBadInput, PcdDataLineWithoutItsValueIsAUserError) {
  // PCL 1.13's PCDReader throws std::out_of_range on a DATA line without its value: it
  // terminates the program (found by fuzz_cloud; reproducer in tests/fuzz/regressions/cloud).
  const fs::path reproducer = fs::path(FETTLE_SOURCE_DIR) / "tests/fuzz/regressions/cloud/pcd-data-line-without-value";
  ASSERT_TRUE(fs::exists(reproducer)) << reproducer;
  std::ifstream in(reproducer, std::ios::binary);
  const std::string input(std::istreambuf_iterator<char>(in), {});
  const auto f = write("data_without_value.pcd", input.substr(1));  // the first byte picks the extension
  EXPECT_THAT([&] { (void)load_cloud(f); }, ::testing::ThrowsMessage<UserError>(HasSubstr("DATA without a value")));
}

TEST_F(CloudBadInput, PlyHeaderLinesPclWouldMisreadAreRefused) {
  // Found by fuzz_cloud: "element vertex -5" makes PCL's PLYReader allocate 36 GB (-5 read as
  // 2^32 - 5), an obj_info line trips an assertion in it. Fettle reads PLY itself:
  // every header line must be one PLY has, with values of the right kind.
  const std::string good = ply_header("binary_little_endian", "1") + floats({1, 2, 3});
  auto with = [&](const std::string& from, const std::string& to) { return std::string(good).replace(good.find(from), from.size(), to); };
  const std::vector<std::pair<std::string, std::string>> cases = {
      {with("element vertex 1", "element vertex -5"), "line 3: element 'vertex' has count '-5', not a whole number"},
      {with("property float y", "property flaot y"), "line 5: property 'y' of element 'vertex' has an unknown type"},
      {with("format binary_little_endian", "format binary_middle_endian"), "line 2: format 'binary_middle_endian' is not"},
      {with("property float z\n", "property float z\nproperty list uchar quad idx\n"), "line 7: property 'idx' of element 'vertex' has an unknown type"},
      {with("element vertex 1\n", "property float w\nelement vertex 1\n"), "line 3: property 'property float w' comes before any element"},
      {with("end_header", "`ormat 1ai\nend_header"), "line 7: unknown line '`ormat 1ai'"},
  };
  int i = 0;
  for (const auto& [text, message] : cases) {
    const auto f = write("strict" + std::to_string(i++) + ".ply", text);
    EXPECT_THAT([&] { (void)load_cloud(f); }, ::testing::ThrowsMessage<UserError>(HasSubstr(message))) << message;
  }
  // The fuzzer's reproducers themselves (first byte: fuzz_cloud's extension choice).
  for (const char* name : {"ply-negative-vertex-count", "ply-obj-info-assert"}) {
    std::ifstream in(fs::path(FETTLE_SOURCE_DIR) / "tests/fuzz/regressions/cloud" / name, std::ios::binary);
    ASSERT_TRUE(in) << name;
    const std::string input(std::istreambuf_iterator<char>(in), {});
    const auto out = load_in_child(write(std::string(name) + ".ply", input.substr(1)));
    EXPECT_TRUE(out.how == ChildOutcome::How::returned) << name << ": " << out.detail;
    EXPECT_LT(out.max_rss_mb, 1024) << name;
  }
  // A comment, obj_info and face lists stay readable.
  const auto faces = write("faces.ply", "ply\nformat ascii 1.0\ncomment scanner x\nobj_info y\nelement vertex 3\nproperty float x\n"
                                        "property float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                                        "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n");
  EXPECT_EQ(load_cloud(faces).size(), 3U);
}
