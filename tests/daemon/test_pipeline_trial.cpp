// The closed loop on simulated castings: `fettle-sim trial` on one seed writes its evaluation
// per region; on two seeds (issue 5 acceptance, CI-sized) it must keep, for
// every region type, <= 0.1 % of the ROI points > 0.5 mm and <= 1 % > 0.3 mm from the template
// after one cycle, with no gouge deeper than 0.1 mm. `make accuracy` runs the same on 50 seeds.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <sys/wait.h>

#include <nlohmann/json.hpp>
#include <unistd.h>

namespace {

namespace fs = std::filesystem;

struct TrialRun {
  fs::path out;
  int rc = -1;
  std::string log;
  nlohmann::json summary;
};

/// Runs `fettle-sim trial` on seeds `seeds` ("A-B") of the pump body in the simulated cell.
TrialRun run_trial(const std::string& seeds, const std::string& extra = {}) {
  TrialRun t;
  t.out = fs::temp_directory_path() / ("fettle-trial-" + std::to_string(::getpid()));
  fs::remove_all(t.out);
  const std::string cmd = std::string(FETTLE_BIN_DIR) + "/fettle-sim trial --part " + FETTLE_SOURCE_DIR +
                          "/config/parts/pump-body.toml --cell " + FETTLE_SOURCE_DIR + "/config/cell.sim.toml --seeds " +
                          seeds + " " + extra + " --out " + t.out.string() + " > " + (t.out.string() + ".log") + " 2>&1";
  t.rc = std::system(cmd.c_str());
  std::ifstream log(t.out.string() + ".log");
  t.log.assign((std::istreambuf_iterator<char>(log)), std::istreambuf_iterator<char>());
  std::ifstream in(t.out / "summary.json");
  if (in) t.summary = nlohmann::json::parse(in);
  return t;
}

void clean(const TrialRun& t) {
  fs::remove_all(t.out);
  fs::remove(t.out.string() + ".log");
}

TEST(Trial, OneSeedWritesItsEvaluationPerRegionWithTheDeepestGouge) {
  // Not the acceptance (that is the test below, 0.1 mm): the closed loop runs, every region
  // is planned and evaluated, and the numbers are where docs/planning.md says. A gouge deeper
  // than 0.5 mm is a regression.
  const auto t = run_trial("1-1");
  ASSERT_FALSE(t.summary.is_null()) << "no summary.json; output:\n" << t.log;
  EXPECT_TRUE(WIFEXITED(t.rc) && (WEXITSTATUS(t.rc) == 0 || WEXITSTATUS(t.rc) == 1)) << t.log;
  EXPECT_EQ(t.summary.at("failures").get<int>(), 0) << t.log;
  EXPECT_LT(t.summary.at("max_gouge_depth_mm").get<double>(), 0.5) << t.log;
  std::ifstream in(t.out / "seed-1" / "evaluation.json");
  ASSERT_TRUE(in) << t.log;
  const auto e = nlohmann::json::parse(in);
  ASSERT_EQ(e.at("regions").size(), 4U);
  double deepest = 0.0;
  for (const auto& r : e.at("regions")) {
    const auto name = r.at("name").get<std::string>();
    EXPECT_GT(r.at("plan").at("trajectory_points").get<long>(), 0) << name;
    // material the tool could not reach is reported: a riser's no higher than the planner's
    // leave_unreachable_mm (0.3 mm), a straight fin's that runs up to a wall with its length
    const double left = r.at("plan").at("material_left_mm").get<double>();
    EXPECT_GE(left, 0.0) << name;
    if (r.at("type") != "straight_flash") {
      EXPECT_LE(left, 0.3) << name;
    }
    EXPECT_EQ(r.at("plan").contains("material_left_at_mm"), left > 0.0) << name;
    EXPECT_GE(r.at("plan").at("material_left_length_mm").get<double>(), 0.0) << name;
    EXPECT_TRUE(r.contains("template_comparison")) << name;
    ASSERT_TRUE(r.contains("casting_comparison")) << name;  // the same points against the casting's own body
    EXPECT_EQ(r.at("casting_comparison").at("roi_points"), r.at("template_comparison").at("roi_points")) << name;
    EXPECT_LE(r.at("casting_comparison").at("share_over_0_5_pct").get<double>(), 0.1) << name;
    // where the vision stage put the region: its template within 0.2 mm RMS of the casting's
    // true surface (0.06-0.12 mm on this casting with the recipe's form deviation), the pose
    // errors at the ROI centre given
    ASSERT_TRUE(r.contains("vision")) << name;
    const auto& v = r.at("vision");
    EXPECT_LT(v.at("template_rms_to_true_surface_mm").at("region_pose").get<double>(), 0.2) << name;
    EXPECT_LT(v.at("template_rms_to_true_surface_mm").at("whole_part_pose").get<double>(), 0.2) << name;
    EXPECT_EQ(v.at("region_pose_vs_true_part").at("offset_mm").size(), 3U) << name;
    EXPECT_GE(v.at("region_pose_vs_true_part").at("mm").get<double>(), 0.0) << name;
    const double depth = r.at("max_gouge_depth_mm").get<double>();
    deepest = std::max(deepest, depth);
    if (r.at("gouges").get<long>() == 0) {
      EXPECT_FALSE(r.contains("deepest_gouge_mm")) << name;
      continue;
    }
    ASSERT_TRUE(r.contains("deepest_gouge_mm")) << name;
    const auto p = r.at("deepest_gouge_mm").get<std::vector<double>>();
    ASSERT_EQ(p.size(), 3U) << name;
    // on the part: the pump body spans x, y within +-110 / +-85 mm, z 0..65 (part frame)
    EXPECT_LE(std::abs(p[0]), 110.5) << name;
    EXPECT_LE(std::abs(p[1]), 85.5) << name;
    EXPECT_GE(p[2], -0.5) << name;
    EXPECT_LE(p[2], 65.5) << name;
  }
  EXPECT_DOUBLE_EQ(deepest, e.at("max_gouge_depth_mm").get<double>());
  if (!HasFailure()) clean(t);
}

// Issue 5's acceptance on the two castings CI can afford: every region type within its shares
// of the ROI points and no cut deeper than 0.1 mm, both against each casting's own body (the
// nominal with the recipe's form deviation). `make accuracy` asks the same of 50 castings drawn
// at run time (latest figures in docs/results.md).
TEST(Trial, TwoSeedsMeetTheAcceptanceThresholds) {
  const auto t = run_trial("1-2");
  ASSERT_FALSE(t.summary.is_null()) << "no summary.json; output:\n" << t.log;
  const auto& summary = t.summary;
  const std::string& text = t.log;
  const fs::path& out = t.out;
  EXPECT_EQ(summary.at("failures").get<int>(), 0) << text;
  EXPECT_LE(summary.at("max_body_cut_mm").get<double>(), 0.1) << text;
  EXPECT_DOUBLE_EQ(summary.at("max_body_cut_allowed_mm").get<double>(), 0.1) << text;
  const auto& types = summary.at("casting_comparison");
  for (const char* type : {"ring_flash", "riser", "circle_flash", "straight_flash"}) {
    ASSERT_TRUE(types.contains(type)) << type << "\n" << text;
    const auto& tt = types.at(type);
    EXPECT_EQ(tt.at("seeds").get<int>(), 2) << type;
    EXPECT_GT(tt.at("roi_points").get<long>(), 0) << type;
    EXPECT_LE(tt.at("worst_share_over_0_5_pct").get<double>(), 0.1) << type << "\n" << text;
    EXPECT_LE(tt.at("worst_share_over_0_3_pct").get<double>(), 1.0) << type << "\n" << text;
  }
  // per seed: the files anyone can recompute the figures from
  for (const char* seed : {"seed-1", "seed-2"}) {
    EXPECT_TRUE(fs::exists(out / seed / "evaluation.json")) << seed;
    EXPECT_TRUE(fs::exists(out / seed / "template.ply")) << seed;
    EXPECT_TRUE(fs::exists(out / seed / "roi_riser.ply")) << seed;
  }
  EXPECT_EQ(t.rc, 0) << text;
  clean(t);
}

// The executed path 0.4 mm below the commanded one (a calibration error in z): the tool cuts
// into every face it grinds, and the cell's own verification must say NOK, with the gouge's
// place, on every casting the simulator says is gouged deeper than gouge_depth_mm. At the
// demo's 1032 x 772 (a quarter of the time; the gouges are millimetres wide).
TEST(Trial, APathBiasGougeIsNokInTheCellsVerificationWithItsPlace) {
  const auto t = run_trial("3-3", "--path-bias-mm 0 0 -0.4 --width 1032");
  ASSERT_FALSE(t.summary.is_null()) << "no summary.json; output:\n" << t.log;
  EXPECT_EQ(t.summary.at("failures").get<int>(), 0) << t.log;
  EXPECT_GT(t.summary.at("max_body_cut_mm").get<double>(), 0.3) << t.log;  // gouged on purpose
  EXPECT_EQ(t.summary.at("gouged_castings").get<int>(), 1) << t.log;
  EXPECT_EQ(t.summary.at("gouges_missed_by_verification").get<int>(), 0) << t.log;
  std::ifstream in(t.out / "seed-3" / "evaluation.json");
  ASSERT_TRUE(in) << t.log;
  const auto e = nlohmann::json::parse(in);
  EXPECT_EQ(e.at("verdict").get<std::string>(), "NOK") << t.log;
  ASSERT_TRUE(e.at("verify_gouge").is_object()) << t.log;
  EXPECT_NE(e.at("verify_gouge").at("reason").get<std::string>().find("gouged "), std::string::npos);
  EXPECT_GT(e.at("verify_gouge").at("depth_mm").get<double>(), 0.3);
  EXPECT_EQ(t.rc, 0) << "the acceptance with a path bias is that the verification catches the gouge\n" << t.log;
  if (!HasFailure()) clean(t);
}

// The cell learns its own bias (docs/compensation.md): the executed path 0.2 mm below the
// commanded one over six castings. The first casting is gouged; each verification measures where
// the tool cut, the estimate converges on that offset (printed per casting) and the gouges
// shrink. Seen from above, the pump body's cut surfaces all face up: the estimate is vertical,
// nothing is guessed sideways. At the demo's 1032 x 772.
TEST(Trial, TheCellLearnsAPathBiasFromItsVerificationsAndTheGougesShrink) {
  const auto t = run_trial("4-9", "--path-bias-mm 0 0 -0.2 --width 1032");
  ASSERT_FALSE(t.summary.is_null()) << "no summary.json; output:\n" << t.log;
  std::vector<nlohmann::json> ground;  // castings planned, ground and verified, in order
  for (const auto& s : t.summary.at("seed_results"))
    if (s.contains("compensation")) ground.push_back(s);
  ASSERT_GE(ground.size(), 5U) << t.log;
  EXPECT_NE(t.log.find("learned bias"), std::string::npos) << "the estimate is printed per casting\n" << t.log;
  const auto z = [](const nlohmann::json& v) { return v.at(2).get<double>(); };
  const auto& first = ground.front().at("compensation");
  EXPECT_NEAR(z(first.at("bias_before_mm")), 0.0, 1e-12) << "it starts from zero";
  // the measurement is the cell's whole offset, commanded correction or not
  for (const auto& s : ground) {
    const auto& c = s.at("compensation");
    ASSERT_TRUE(c.contains("measured_mm")) << c.dump() << "\n" << t.log;
    EXPECT_LT(z(c.at("measured_mm")), -0.15) << c.dump();
    EXPECT_EQ(c.at("directions_observed").get<int>(), 1) << c.dump();
  }
  // after five castings the estimate is within a third of the offset the cell really has
  const auto& fifth = ground[4].at("compensation");
  const double learned = z(fifth.at("bias_after_mm")), measured = z(fifth.at("measured_mm"));
  EXPECT_LT(std::abs(learned - measured), std::abs(measured) / 3.0) << fifth.dump() << "\n" << t.log;
  EXPECT_LT(std::abs(-0.2 - learned), 0.2 / 3.0 + 0.08) << "the path noise's envelope adds a few hundredths\n"
                                                         << fifth.dump();
  const auto& last = ground.back().at("compensation").at("bias_after_mm");
  EXPECT_LT(std::abs(last.at(0).get<double>()) + std::abs(last.at(1).get<double>()), 0.01) << last.dump();
  // the gouges shrink: the first casting's is the deepest, the later ones are within the acceptance
  const double g0 = ground.front().at("max_body_cut_mm").get<double>();
  EXPECT_GT(g0, 0.15) << "0.2 mm down gouges the first casting\n" << t.log;
  for (std::size_t k = 2; k < ground.size(); ++k)
    EXPECT_LT(ground[k].at("max_body_cut_mm").get<double>(), 0.1) << "casting " << k + 1 << "\n" << t.log;
  if (!HasFailure()) clean(t);
}

}  // namespace
