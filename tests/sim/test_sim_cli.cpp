// fettle-sim scan | grind | evaluate as a person runs them: the files they write, determinism,
// progress on stderr, and bad part files and trajectories refused before anything runs.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "fettle/core/ply.hpp"
#include "sim_test_util.hpp"

namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::Not;

namespace {

const std::string kSim = std::string(FETTLE_BIN_DIR) + "/fettle-sim";

struct Run {
  int exit_code = -1;
  std::string out;  ///< stdout
  std::string err;  ///< stderr
};

std::string slurp(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  std::stringstream s;
  s << f.rdbuf();
  return s.str();
}

/// Runs fettle-sim with `args`, stdout and stderr captured separately.
Run sim(const std::string& args, const fs::path& scratch) {
  const fs::path err = scratch / "stderr.txt";
  const std::string command = kSim + " " + args + " 2>" + err.string() + " </dev/null";
  FILE* pipe = ::popen(command.c_str(), "r");
  Run r;
  std::array<char, 4096> buf{};
  while (pipe != nullptr && std::fgets(buf.data(), buf.size(), pipe) != nullptr) r.out += buf.data();
  const int status = pipe != nullptr ? ::pclose(pipe) : -1;
  r.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  r.err = slurp(err);
  return r;
}

std::string replaced(std::string text, const std::string& from, const std::string& to) {
  const auto at = text.find(from);
  EXPECT_NE(at, std::string::npos) << from;
  if (at != std::string::npos) text.replace(at, from.size(), to);
  return text;
}

class SimCli : public ::testing::Test {
 protected:
  void SetUp() override {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    dir_ = fs::temp_directory_path() / ("fettle-sim-cli-" + std::to_string(::getpid()) + "-" + info->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    ASSERT_TRUE(fs::exists(kSim)) << kSim << " is not built";
  }
  void TearDown() override { fs::remove_all(dir_); }

  /// A ball-12 sweep along the straight parting-line flash of casting `seed`, `clearance_mm`
  /// above the face it stands on (poses T_base_tool, from the casting's true placement).
  /// A ball pass along the straight flash (segment 0); with `riser`, then a plunge into the
  /// riser 2 mm above its face (segment 1, region "riser", whose tool is the 16 mm flat end).
  fs::path flash_sweep(std::uint64_t seed, double clearance_mm, const std::string& name, bool riser = false) const {
    const auto recipe = sim_test::pump_body();
    const auto c = fettle::sim::Casting::make(recipe, seed);
    const auto& f = recipe.geometry.straight_flashes.at(0);
    fettle::Trajectory t;
    t.part_id = recipe.id;
    t.segment_regions = {f.region};
    // along the fin, clearance_mm over the casting's own face (its form deviation kept: the fin
    // stands on it), every 2 mm
    for (double s = -8.0; s <= f.length_mm.max + 8.0 + 1e-9; s += 2.0) {
      const double x = f.start_mm[0] + s, y = f.start_mm[1];
      const double face = c.golden_top_z_mm(f.start_mm[0], y) + c.form_deviation_mm(x, y);
      fettle::TrajectoryPoint q;
      q.T_base_tool.position_mm = c.T_base_part() * fettle::Vec3(x, y, face + clearance_mm);  // TCP at the ball's tip
      q.speed_mm_s = 20;
      q.spindle_rpm = 9000;
      t.points.push_back(q);
    }
    if (riser) {
      const auto& r = recipe.geometry.risers.at(0);
      const double pad = c.golden_top_z_mm(r.center_mm[0], r.center_mm[1]);
      t.segment_regions.push_back("riser");
      fettle::TrajectoryPoint q;
      q.T_base_tool.position_mm = c.T_base_part() * fettle::Vec3(r.center_mm[0], r.center_mm[1], pad + 2.0);
      q.T_base_tool.orientation = fettle::Quat(c.T_base_part().linear());
      q.speed_mm_s = 20;
      q.spindle_rpm = 9000;
      q.segment = 1;
      t.points.push_back(q);
      t.points.push_back(q);
    }
    const fs::path p = dir_ / name;
    EXPECT_TRUE(fettle::sim::write_trajectory_json(p, t).ok());
    return p;
  }

  fs::path dir_;
};

const std::string kPart = sim_test::kPumpBody.string();

TEST_F(SimCli, ScanWritesAMillionPointPlyRangeImagesAndGroundTruth) {
  const auto r = sim("scan --part " + kPart + " --seed 4 --out " + (dir_ / "scan").string(), dir_);
  ASSERT_EQ(r.exit_code, 0) << r.out << r.err;
  const fs::path d = dir_ / "scan";
  // PLY: the valid points of the default 2064 x 1544 scanner, at least 1 M.
  const auto cloud = fettle::read_ply(d / "view0.ply");
  ASSERT_TRUE(cloud.ok()) << cloud.error().message;
  const auto& points = cloud->points;
  EXPECT_GE(points.size(), 1'000'000u);
  EXPECT_LE(points.size(), std::size_t{2064} * 1544);
  for (std::size_t i = 0; i < points.size(); i += 50'000) {
    const auto& p = points[i];
    EXPECT_TRUE(p.allFinite());
    EXPECT_GT(p.z(), 300.0f);  // camera frame, mm: the scene is ~600 mm away
    EXPECT_LT(p.z(), 700.0f);
  }
  // Range images: Coord3D_C16 with its description, float32 with the same size.
  EXPECT_EQ(fs::file_size(d / "view0.c16"), std::uintmax_t{2064} * 1544 * 2);
  EXPECT_EQ(fs::file_size(d / "view0.f32"), std::uintmax_t{2064} * 1544 * 4);
  const auto c16 = nlohmann::json::parse(slurp(d / "view0.c16.json"));
  EXPECT_EQ(c16.at("width"), 2064);
  EXPECT_EQ(c16.at("height"), 1544);
  EXPECT_EQ(c16.at("pixel_format"), "Coord3D_C16");
  EXPECT_TRUE(fs::exists(d / "view0.pcd"));
  // Ground truth: poses and per-region material, as printed on stdout.
  const auto truth = nlohmann::json::parse(slurp(d / "view0.truth.json"));
  EXPECT_EQ(truth.at("seed"), 4);
  EXPECT_TRUE(truth.contains("T_base_camera"));
  EXPECT_TRUE(truth.contains("T_base_part"));
  ASSERT_EQ(truth.at("regions").size(), 4u);
  for (const auto& region : truth.at("regions")) {
    EXPECT_GT(region.at("volume_mm3").get<double>(), 0.0) << region.dump();
    EXPECT_GT(region.at("max_height_mm").get<double>(), 0.0) << region.dump();
    EXPECT_THAT(r.out, HasSubstr(region.at("name").get<std::string>()));
  }
  EXPECT_THAT(r.out, HasSubstr("view 0:"));
  // Progress of the long steps on stderr, results on stdout.
  EXPECT_THAT(r.err, HasSubstr("built casting 4"));
  EXPECT_THAT(r.err, HasSubstr("rendering view 1 of 1"));
}

TEST_F(SimCli, ScanIsByteIdenticalForTheSameSeedAndDiffersForAnother) {
  const std::string small = " --width 688 --positions-mm 0 150";
  ASSERT_EQ(sim("scan --part " + kPart + " --seed 9 --out " + (dir_ / "a").string() + small, dir_).exit_code, 0);
  ASSERT_EQ(sim("scan --part " + kPart + " --seed 9 --out " + (dir_ / "b").string() + small, dir_).exit_code, 0);
  ASSERT_EQ(sim("scan --part " + kPart + " --seed 10 --out " + (dir_ / "c").string() + small, dir_).exit_code, 0);
  std::size_t files = 0;
  for (const auto& e : fs::directory_iterator(dir_ / "a")) {
    const auto name = e.path().filename();
    const std::string a = slurp(e.path());
    EXPECT_FALSE(a.empty()) << name;
    EXPECT_EQ(a, slurp(dir_ / "b" / name)) << name << " differs between two runs with seed 9";
    ++files;
  }
  EXPECT_EQ(files, 2u * 7u);  // two views: ply, pcd, c16, c16.json, f32, f32.json, truth.json
  EXPECT_NE(slurp(dir_ / "a" / "view1.c16"), slurp(dir_ / "c" / "view1.c16"));
  EXPECT_NE(slurp(dir_ / "a" / "view0.truth.json"), slurp(dir_ / "c" / "view0.truth.json"));
}

// `--cell-seed random` draws a cell when the command runs and prints it, so a claim about a cell
// comes from one nobody looked at first and the run can still be repeated; a word that is
// neither a number nor "random" is refused.
TEST_F(SimCli, ARandomCellSeedIsDrawnNowAndPrinted) {
  const std::string small = " --width 688 --positions-mm 0 --errors " + std::string(FETTLE_SOURCE_DIR) +
                            "/config/sim/errors-realistic.toml";
  std::vector<std::string> drawn;
  for (const char* out : {"a", "b"}) {
    const auto r = sim("scan --part " + kPart + " --seed 9 --cell-seed random --out " + (dir_ / out).string() + small, dir_);
    ASSERT_EQ(r.exit_code, 0) << r.out << r.err;
    std::smatch m;
    ASSERT_TRUE(std::regex_search(r.out, m, std::regex("cell seed ([0-9]+) \\(drawn now for --cell-seed random; "
                                                       "repeat with --cell-seed ([0-9]+)\\)")))
        << r.out;
    EXPECT_EQ(m[1].str(), m[2].str());
    const auto errors = nlohmann::json::parse(slurp(dir_ / out / "errors.json"));
    EXPECT_EQ(errors.dump().find("\"cell_seed\":" + m[1].str()) != std::string::npos, true) << errors.dump();
    drawn.push_back(m[1].str());
  }
  EXPECT_NE(drawn[0], drawn[1]) << "two runs drew the same cell";
  const auto bad = sim("scan --part " + kPart + " --seed 9 --cell-seed banana --out " + (dir_ / "c").string() + small, dir_);
  EXPECT_NE(bad.exit_code, 0);
  EXPECT_THAT(bad.err, HasSubstr("--cell-seed"));
}

TEST_F(SimCli, GrindRemovesTheFlashAndEvaluateTabulatesTheResult) {
  // Two regions in one file: each is ground with its own tool from the recipe.
  const auto both = flash_sweep(3, 0.05, "sweep-riser.json", true);
  const auto g = sim("grind --part " + kPart + " --seed 3 --trajectory " + both.string() + " --out " +
                         (dir_ / "g").string() + " --rescan --width 516",
                     dir_);
  ASSERT_EQ(g.exit_code, 0) << g.out << g.err;
  EXPECT_THAT(g.out, HasSubstr("in 2 run(s)"));
  EXPECT_THAT(g.err, HasSubstr("grinding: "));  // progress
  const auto j = nlohmann::json::parse(slurp(dir_ / "g" / "grind.json"));
  ASSERT_EQ(j.at("runs").size(), 2u) << j.dump();
  EXPECT_EQ(j.at("runs")[0].at("region"), "side-parting-line");
  EXPECT_EQ(j.at("runs")[0].at("tool"), "ball-12");
  EXPECT_EQ(j.at("runs")[1].at("region"), "riser");
  EXPECT_EQ(j.at("runs")[1].at("tool"), "flat-16");
  EXPECT_GT(j.at("removed_mm3").get<double>(), 10.0);
  int seen = 0;
  for (const auto& r : j.at("regions")) {
    const double before = r.at("volume_before_mm3").get<double>(), after = r.at("volume_after_mm3").get<double>();
    if (r.at("name") == "side-parting-line") {
      ++seen;
      EXPECT_LT(after, 0.05 * before) << r.dump();
    } else if (r.at("name") == "riser") {
      ++seen;
      EXPECT_LT(after, 0.9 * before) << r.dump();  // a 16 mm core of the riser, down to 2 mm above its face
      EXPECT_GT(after, 0.1 * before) << r.dump();
    } else {
      EXPECT_EQ(before, after) << r.dump();  // not touched
    }
  }
  EXPECT_EQ(seen, 2);
  // --tool puts one tool on every point
  const auto one = sim("grind --part " + kPart + " --seed 3 --trajectory " + both.string() + " --tool ball-12 --out " +
                           (dir_ / "g1").string() + " --width 516",
                       dir_);
  ASSERT_EQ(one.exit_code, 0) << one.out << one.err;
  const auto j1 = nlohmann::json::parse(slurp(dir_ / "g1" / "grind.json"));
  ASSERT_EQ(j1.at("runs").size(), 2u);
  EXPECT_EQ(j1.at("runs")[1].at("tool"), "ball-12");
  EXPECT_TRUE(fs::exists(dir_ / "g" / "ground-view0.ply"));
  EXPECT_TRUE(fs::exists(dir_ / "g" / "ground-view0.truth.json"));

  // Evaluate: the same grind on castings 3 and 5, template comparison and batch consistency.
  const auto traj = flash_sweep(3, 0.05, "sweep.json");
  const auto traj5 = flash_sweep(5, 0.05, "sweep5.json");
  const auto e = sim("evaluate --part " + kPart + " --seeds 3,5 --trajectory " + traj.string() + " --trajectory " +
                         traj5.string() + " --width 516",
                     dir_);
  ASSERT_EQ(e.exit_code, 0) << e.out << e.err;
  EXPECT_THAT(e.out, HasSubstr("Template comparison (after grinding)"));
  EXPECT_THAT(e.out, HasSubstr("Batch consistency (after grinding)"));
  EXPECT_THAT(e.out, HasSubstr("Material left (simulator truth)"));
  EXPECT_THAT(e.out, ::testing::ContainsRegex("casting 5 .*side-parting-line [0-9.]+ / [0-9.]+"));
  EXPECT_THAT(e.out, HasSubstr("side-parting-line"));
  EXPECT_THAT(e.err, HasSubstr("scanning casting 5"));
}

TEST_F(SimCli, PartFileWithImpossibleGeometryIsRefusedWithFileAndLine) {
  const std::string text = slurp(sim_test::kPumpBody);
  struct Case {
    std::string from, to, key;
  };
  for (const auto& c : {Case{"radius_mm = 45.0", "radius_mm = -45.0", "radius_mm"},
                        Case{"roi_center_mm = [82.0, -48.0, 47.0]", "roi_center_mm = [482.0, -48.0, 47.0]", "off the body"},
                        Case{"center_mm = [-82.0, 48.0]", "center_mm = [-382.0, 48.0]", "off the body"}}) {
    const fs::path bad = dir_ / "bad.toml";
    std::ofstream(bad) << replaced(text, c.from, c.to);
    const auto r = sim("scan --part " + bad.string() + " --seed 1 --out " + (dir_ / "out").string(), dir_);
    EXPECT_EQ(r.exit_code, 1) << c.to << "\n" << r.out << r.err;
    EXPECT_TRUE(std::regex_search(r.err, std::regex(std::regex_replace(bad.string(), std::regex("[.]"), "\\.") +
                                                    ":[0-9]+:")))
        << "no file:line in: " << r.err;
    EXPECT_THAT(r.err, HasSubstr(c.key));
    EXPECT_FALSE(fs::exists(dir_ / "out")) << "wrote output for a bad part file";
  }
}

TEST_F(SimCli, TrajectoryWithNaNOrFarOutsideTheCellIsRefusedAndNotExecuted) {
  const std::string header = "x,y,z,qw,qx,qy,qz,speed_mm_s,spindle_rpm,segment\n";
  std::ofstream(dir_ / "nan.csv") << header << "-100,-70,50,1,0,0,0,20,9000,0\n"
                                  << "0,-70,nan,1,0,0,0,20,9000,0\n";
  std::ofstream(dir_ / "far.csv") << header << "-100,-70,50,1,0,0,0,20,9000,0\n"
                                  << "5000,-70,50,1,0,0,0,20,9000,0\n";
  for (const char* name : {"nan.csv", "far.csv"}) {
    const fs::path out = dir_ / (std::string(name) + ".out");
    const auto r = sim("grind --part " + kPart + " --seed 1 --trajectory " + (dir_ / name).string() + " --out " +
                           out.string(),
                       dir_);
    EXPECT_EQ(r.exit_code, 1) << name << "\n" << r.out << r.err;
    EXPECT_THAT(r.err, HasSubstr((dir_ / name).string()));
    EXPECT_THAT(r.err, HasSubstr("trajectory point 1"));
    EXPECT_THAT(r.err, HasSubstr("nothing was executed"));
    EXPECT_THAT(r.out, Not(HasSubstr("executed")));
    EXPECT_THAT(r.err, Not(HasSubstr("grinding: ")));
    EXPECT_FALSE(fs::exists(out / "grind.json"));
  }
  // The same refusal in evaluate: nothing is ground or scanned.
  const auto e = sim("evaluate --part " + kPart + " --seeds 1 --trajectory " + (dir_ / "far.csv").string(), dir_);
  EXPECT_EQ(e.exit_code, 1) << e.out << e.err;
  EXPECT_THAT(e.err, HasSubstr("outside the cell"));
  EXPECT_THAT(e.err, Not(HasSubstr("scanning casting")));
}

}  // namespace
