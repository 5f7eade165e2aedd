// The trajectory file format (fettle/core/trajectory_io.hpp): what the planner writes, fettle-sim
// and the CLI read back, in JSON and in CSV.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

#include "fettle/core/error.hpp"
#include "fettle/core/trajectory_io.hpp"

namespace fs = std::filesystem;
using fettle::MoveKind;
using fettle::Trajectory;

namespace {

class TrajectoryFiles : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("fettle-trajectory-io-" + std::to_string(::getpid()));
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  fs::path write(const std::string& name, const std::string& text) const {
    std::ofstream(dir_ / name) << text;
    return dir_ / name;
  }
  /// The UserError's message reading `path` gives ("" if it reads).
  static std::string refusal(const fs::path& path) {
    try {
      (void)fettle::read_trajectory(path);
    } catch (const fettle::UserError& e) {
      return e.what();
    }
    return "";
  }
  fs::path dir_;
};

Trajectory sample() {
  Trajectory t;
  t.part_id = "pump-body";
  t.segment_regions = {"ring_flash", "riser"};
  const MoveKind kinds[] = {MoveKind::approach, MoveKind::grind, MoveKind::air, MoveKind::retract};
  for (int i = 0; i < 4; ++i) {
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = fettle::Vec3(400.0 + 0.1 * i, -12.345678901234 * i, 35.0 + 1.0 / 3.0);
    p.T_base_tool.orientation = fettle::Quat(Eigen::AngleAxisd(0.1 * i, fettle::Vec3::UnitX()));
    p.speed_mm_s = 20.0 + i;
    p.spindle_rpm = i == 0 ? 0.0 : 9000.0;
    p.segment = i / 2;
    p.kind = kinds[i];
    t.points.push_back(p);
  }
  return t;
}

void expect_same(const Trajectory& a, const Trajectory& b) {
  ASSERT_EQ(a.points.size(), b.points.size());
  for (std::size_t i = 0; i < a.points.size(); ++i) {
    SCOPED_TRACE("point " + std::to_string(i));
    const auto& p = a.points[i];
    const auto& q = b.points[i];
    EXPECT_EQ(p.T_base_tool.position_mm, q.T_base_tool.position_mm);  // max_digits10: exact
    EXPECT_LT(p.T_base_tool.orientation.angularDistance(q.T_base_tool.orientation), 1e-12);
    EXPECT_EQ(p.speed_mm_s, q.speed_mm_s);
    EXPECT_EQ(p.spindle_rpm, q.spindle_rpm);
    EXPECT_EQ(p.segment, q.segment);
    EXPECT_EQ(p.kind, q.kind);
  }
}

}  // namespace

TEST_F(TrajectoryFiles, JsonAndCsvReadBackWhatWasWritten) {
  const auto t = sample();
  ASSERT_TRUE(fettle::write_trajectory_json(dir_ / "t.json", t));
  ASSERT_TRUE(fettle::write_trajectory_csv(dir_ / "t.csv", t));
  const auto json = fettle::read_trajectory(dir_ / "t.json");
  EXPECT_EQ(json.part_id, t.part_id);
  EXPECT_EQ(json.segment_regions, t.segment_regions);
  expect_same(json, t);
  expect_same(fettle::read_trajectory(dir_ / "t.csv"), t);
}

TEST_F(TrajectoryFiles, NanWrittenAsAStringIsReadForTheControllerToRefuse) {
  const auto path = write("nan.json", R"({"points": [{"x": "nan", "y": 0, "z": 1, "qw": 1, "qx": 0, "qy": 0, "qz": 0,
                                         "speed_mm_s": 10, "spindle_rpm": 0}]})");
  const auto t = fettle::read_trajectory(path);
  ASSERT_EQ(t.points.size(), 1U);
  EXPECT_TRUE(std::isnan(t.points[0].T_base_tool.position_mm.x()));
}

TEST_F(TrajectoryFiles, BadInputIsRefusedNamingTheFileAndWhere) {
  const std::string header = "x,y,z,qw,qx,qy,qz,speed_mm_s,spindle_rpm,segment,kind\n";
  EXPECT_NE(
      refusal(write("kind.csv", header + "1,2,3,1,0,0,0,10,0,0,sideways\n")).find("kind.csv:2: kind \"sideways\""),
      std::string::npos);
  EXPECT_NE(
      refusal(write("num.csv", header + "1,2,x3,1,0,0,0,10,0,0\n")).find("num.csv:2: column z: \"x3\" is not a number"),
      std::string::npos);
  EXPECT_NE(refusal(write("head.csv", "x,y,z\n1,2,3\n")).find("head.csv:1: the header must be"), std::string::npos);
  EXPECT_NE(refusal(write("short.csv", header + "1,2,3\n")).find("short.csv:2: expected at least 10 values, got 3"),
            std::string::npos);
  EXPECT_NE(refusal(write("syntax.json", "{\n \"points\": [\n  {\"x\": 1,,}\n ]\n}\n"))
                .find("syntax.json:3: JSON syntax error"),
            std::string::npos);
  EXPECT_NE(refusal(write("missing.json", R"({"points": [{"x": 1}]})")).find("missing.json: point 0:"),
            std::string::npos);
  EXPECT_NE(refusal(write("empty.csv", "")).find("empty.csv: empty trajectory file"), std::string::npos);
  EXPECT_NE(refusal(dir_ / "absent.json").find("absent.json: cannot open the trajectory file"), std::string::npos);
}
