// The closed loop on simulated castings (issue 5 acceptance, CI-sized): `fettle-sim trial`
// on two seeds must keep, for every region type, <= 0.1 % of the ROI points > 0.5 mm and
// <= 1 % > 0.3 mm from the template after one cycle, with no gouge deeper than 0.1 mm.
// `make accuracy` runs the same on 50 seeds.
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>
#include <unistd.h>

namespace {

namespace fs = std::filesystem;

// DISABLED: the closed loop does not complete yet - the flange ring's plan is refused on the
// simulated pump body (see test_pipeline.cpp); enable once `fettle-sim trial --seeds 1-2` passes.
TEST(Trial, DISABLED_TwoSeedsMeetTheAcceptanceThresholds) {
  const fs::path out = fs::temp_directory_path() / ("fettle-trial-" + std::to_string(::getpid()));
  fs::remove_all(out);
  const std::string cmd = std::string(FETTLE_BIN_DIR) + "/fettle-sim trial --part " + FETTLE_SOURCE_DIR +
                          "/config/parts/pump-body.toml --cell " + FETTLE_SOURCE_DIR +
                          "/config/cell.sim.toml --seeds 1-2 --out " + out.string() + " > " + (out.string() + ".log") +
                          " 2>&1";
  const int rc = std::system(cmd.c_str());
  std::ifstream log(out.string() + ".log");
  const std::string text((std::istreambuf_iterator<char>(log)), std::istreambuf_iterator<char>());
  std::ifstream in(out / "summary.json");
  ASSERT_TRUE(in) << "no summary.json; output:\n" << text;
  const auto summary = nlohmann::json::parse(in);
  EXPECT_EQ(summary.at("failures").get<int>(), 0) << text;
  EXPECT_LE(summary.at("max_gouge_depth_mm").get<double>(), 0.1) << text;
  const auto& types = summary.at("template_comparison");
  for (const char* type : {"ring_flash", "riser", "circle_flash", "straight_flash"}) {
    ASSERT_TRUE(types.contains(type)) << type << "\n" << text;
    const auto& t = types.at(type);
    EXPECT_EQ(t.at("seeds").get<int>(), 2) << type;
    EXPECT_GT(t.at("roi_points").get<long>(), 0) << type;
    EXPECT_LE(t.at("worst_share_over_0_5_pct").get<double>(), 0.1) << type << "\n" << text;
    EXPECT_LE(t.at("worst_share_over_0_3_pct").get<double>(), 1.0) << type << "\n" << text;
  }
  // per seed: the files anyone can recompute the figures from
  for (const char* seed : {"seed-1", "seed-2"}) {
    EXPECT_TRUE(fs::exists(out / seed / "evaluation.json")) << seed;
    EXPECT_TRUE(fs::exists(out / seed / "template.ply")) << seed;
    EXPECT_TRUE(fs::exists(out / seed / "roi_riser.ply")) << seed;
  }
  EXPECT_EQ(rc, 0) << text;
  fs::remove_all(out);
  fs::remove(out.string() + ".log");
}

}  // namespace
