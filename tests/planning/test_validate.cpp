// Validation: every rule rejects with the region, the point index and the rule named; a plan
// for a hostile recipe is refused; the output files round-trip.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <set>
#include <string>

#include <unistd.h>

#include "fettle/planning/io.hpp"
#include "synthetic_part.hpp"

namespace fettle::planning {
namespace {

using testing::make_scene;

TEST(PlanPart, ThePumpBodyLikePartPlansAndValidates) {
  auto scene = make_scene();
  const auto traj = plan_part("pump-body", scene.inputs, PlannerSettings{});
  ASSERT_TRUE(traj) << traj.error().message;
  EXPECT_EQ(traj->part_id, "pump-body");
  std::set<std::string> regions(traj->segment_regions.begin(), traj->segment_regions.end());
  EXPECT_EQ(regions.size(), 4U);
  EXPECT_TRUE(validate(*traj, scene.inputs, PlannerSettings{}));
}

void expect_rejected(const Status& st, const std::string& rule, const std::string& region, std::size_t point) {
  ASSERT_FALSE(st) << "expected rule " << rule << " to reject";
  EXPECT_EQ(st.error().code, "planning." + rule);
  EXPECT_NE(st.error().message.find("region '" + region + "'"), std::string::npos) << st.error().message;
  EXPECT_NE(st.error().message.find("point " + std::to_string(point) + ","), std::string::npos) << st.error().message;
  EXPECT_NE(st.error().message.find("rule " + rule), std::string::npos) << st.error().message;
}

struct Planned {
  testing::Scene scene = make_scene();
  Trajectory traj;
  std::size_t first_grind_of(const std::string& region) const {
    for (std::size_t i = 0; i < traj.points.size(); ++i)
      if (traj.points[i].kind == MoveKind::grind && traj.region_of(traj.points[i]) == region)
        return i;
    return traj.points.size();
  }
  std::size_t last_grind_of(const std::string& region) const {
    for (std::size_t i = traj.points.size(); i-- > 0;)
      if (traj.points[i].kind == MoveKind::grind && traj.region_of(traj.points[i]) == region)
        return i;
    return traj.points.size();
  }
};

Planned planned() {
  Planned p;
  auto t = plan_part("pump-body", p.scene.inputs, PlannerSettings{});
  if (t) p.traj = std::move(t.value());
  return p;
}

TEST(Validate, WorkspaceRuleNamesRegionPointAndRule) {
  auto p = planned();
  ASSERT_FALSE(p.traj.points.empty());
  const std::size_t i = p.first_grind_of("riser");
  p.traj.points[i].T_base_tool.position_mm.x() = 5000.0;
  expect_rejected(validate(p.traj, p.scene.inputs, PlannerSettings{}), "workspace", "riser", i);
}

TEST(Validate, ToolAxisConeRule) {
  auto p = planned();
  ASSERT_FALSE(p.traj.points.empty());
  const std::size_t i = p.first_grind_of("side-parting-line");
  p.traj.points[i].T_base_tool.orientation = Quat(Eigen::AngleAxisd(deg_to_rad(70.0), Vec3::UnitX()));
  expect_rejected(validate(p.traj, p.scene.inputs, PlannerSettings{}), "tool_axis_cone", "side-parting-line", i);
  // and the 45° chamfer ring is refused by a 30° cone at its first point
  PlannerSettings narrow;
  narrow.tool_axis_cone_rad = deg_to_rad(30.0);
  auto q = planned();
  ASSERT_FALSE(q.traj.points.empty());
  const auto st = validate(q.traj, q.scene.inputs, narrow);
  ASSERT_FALSE(st);
  EXPECT_EQ(st.error().code, "planning.tool_axis_cone");
}

TEST(Validate, SpeedRuleCoversFeedAndSpindle) {
  auto p = planned();
  ASSERT_FALSE(p.traj.points.empty());
  const std::size_t i = p.first_grind_of("boss-circle");
  auto fast = p.traj;
  fast.points[i].speed_mm_s = 400.0;
  expect_rejected(validate(fast, p.scene.inputs, PlannerSettings{}), "speed", "boss-circle", i);
  auto spin = p.traj;
  spin.points[i].spindle_rpm = 30000.0;
  expect_rejected(validate(spin, p.scene.inputs, PlannerSettings{}), "speed", "boss-circle", i);
  auto off = p.traj;
  off.points[i].spindle_rpm = 0.0;  // grinding with the spindle off
  expect_rejected(validate(off, p.scene.inputs, PlannerSettings{}), "speed", "boss-circle", i);
}

TEST(Validate, GougeRuleCatchesAToolInsideTheTemplate) {
  auto p = planned();
  ASSERT_FALSE(p.traj.points.empty());
  const std::size_t i = p.last_grind_of("riser") - 3;  // in the last layer, 0.05 mm above the face
  p.traj.points[i].T_base_tool.position_mm.z() -= 1.0;  // 0.95 mm into the pad face
  expect_rejected(validate(p.traj, p.scene.inputs, PlannerSettings{}), "gouge", "riser", i);
}

// A lead-out that runs on past the fin toward the boss block's wall (x = 62), outside every
// region's ROI (the straight flash's ends at x = 40): validation checks every pose against the
// whole template, not the region's ROI, and names the region, the point, the place and the depth.
TEST(Validate, ALeadOutIntoAWallOutsideTheRoiIsRefused) {
  auto p = planned();
  ASSERT_FALSE(p.traj.points.empty());
  const std::size_t i = p.last_grind_of("side-parting-line");
  ASSERT_LT(i, p.traj.points.size());
  auto& x = p.traj.points[i].T_base_tool.position_mm;
  x = Vec3(58.0, -70.0, 35.05);  // the ball (R 6) reaches x = 64: past the wall's top edge (62, 40)
  const auto st = validate(p.traj, p.scene.inputs, PlannerSettings{});
  expect_rejected(st, "gouge", "side-parting-line", i);
  const std::string& m = st.error().message;
  EXPECT_NE(m.find("reaches"), std::string::npos) << m;
  EXPECT_NE(m.find("mm into the template at ("), std::string::npos) << m;
  EXPECT_NE(m.find("(part frame)"), std::string::npos) << m;
  EXPECT_NE(m.find("min_clearance_mm"), std::string::npos) << m;
}

// The clearance is the cell's, whatever the region's allowance: a grinding pose 0.03 mm over
// the face is refused with a clearance of 0.05 mm and passes with 0.02; a region whose allowance
// is below the clearance is refused before it is planned.
TEST(Validate, EveryPoseKeepsTheCellsClearance) {
  auto p = planned();
  ASSERT_FALSE(p.traj.points.empty());
  const std::size_t i = p.last_grind_of("riser") - 3;  // in the last layer, 0.05 mm above the face
  ASSERT_NEAR(p.traj.points[i].T_base_tool.position_mm.z(), 45.05, 1e-3);
  p.traj.points[i].T_base_tool.position_mm.z() = 45.03;
  PlannerSettings settings;
  settings.min_clearance_mm = 0.05;
  const auto st = validate(p.traj, p.scene.inputs, settings);
  expect_rejected(st, "gouge", "riser", i);
  EXPECT_NE(st.error().message.find("comes within 0.030 mm of the template"), std::string::npos) << st.error().message;
  settings.min_clearance_mm = 0.02;
  EXPECT_TRUE(validate(p.traj, p.scene.inputs, settings));

  auto scene = make_scene();
  PlannerSettings strict;
  strict.min_clearance_mm = 0.1;  // above the riser's 0.05 mm allowance
  const auto refused = plan_region(scene.inputs[1], strict);
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().code, "planning.clearance");
  EXPECT_NE(refused.error().message.find("region 'riser'"), std::string::npos) << refused.error().message;
  EXPECT_NE(refused.error().message.find("allowance_mm"), std::string::npos) << refused.error().message;
}

// A cylinder's penetration between its samples: the rim of a 40 mm disc against a wall, with
// the wall's normal halfway between two of the rim's 24 samples (which alone read 0.07 mm clear
// for a rim 0.10 mm into the wall).
TEST(ToolPenetration, ACylinderBetweenItsSamplesIsFound) {
  config::Tool disc;
  disc.name = "disc";
  disc.shape = config::ToolShape::cylinder;
  disc.diameter_mm = 40.0;
  disc.length_mm = 6.0;
  const SignedDistance wall = [](const Vec3& p) { return 100.0 - p.x(); };  // body at x > 100
  Transform T = Transform::Identity();
  T.linear() = Eigen::AngleAxisd(deg_to_rad(7.5), Vec3::UnitZ()).toRotationMatrix();
  T.translation() = Vec3(80.1, 0.0, 0.0);
  Vec3 deepest = Vec3::Zero();
  EXPECT_NEAR(tool_penetration_mm(disc, T, wall, &deepest, 0.05), 0.1, 0.002);
  EXPECT_NEAR(deepest.x(), 100.1, 0.002);
  EXPECT_NEAR(deepest.y(), 0.0, 0.05);
  // a ball's deepest point faces the wall, not the floor
  config::Tool ball;
  ball.name = "ball";
  ball.shape = config::ToolShape::ball;
  ball.diameter_mm = 12.0;
  Transform B = Transform::Identity();
  B.translation() = Vec3(94.5, 3.0, 0.0);
  EXPECT_NEAR(tool_penetration_mm(ball, B, wall, &deepest, 0.05), 0.5, 1e-9);
  EXPECT_NEAR(deepest.x(), 100.5, 0.01);
  EXPECT_NEAR(deepest.z(), 6.0, 0.01);
}

TEST(Validate, AHostileRecipeIsRefused) {
  // regions with a feed beyond the cell's limit: no trajectory comes out
  {
    auto scene = make_scene();
    scene.regions[3].feed_mm_s = 900.0;
    const auto t = plan_part("pump-body", scene.inputs, PlannerSettings{});
    ASSERT_FALSE(t);
    EXPECT_EQ(t.error().code, "planning.speed");
    EXPECT_NE(t.error().message.find("side-parting-line"), std::string::npos);
  }
  // a part placed (or a calibration) that puts the poses outside the workspace
  {
    Transform far = Transform::Identity();
    far.translation() = Vec3(1500.0, 0.0, 0.0);
    auto scene = make_scene(0.5, far);
    const auto t = plan_part("pump-body", scene.inputs, PlannerSettings{});
    ASSERT_FALSE(t);
    EXPECT_EQ(t.error().code, "planning.workspace");
  }
  // a chamfer angle that points the tool outside the allowed cone
  {
    auto scene = make_scene();
    scene.regions[0].chamfer_deg = 10.0;
    const auto t = plan_part("pump-body", scene.inputs, PlannerSettings{});
    ASSERT_FALSE(t);
    EXPECT_TRUE(t.error().code == "planning.tool_axis_cone" || t.error().code == "planning.gouge") << t.error().message;
  }
}

// What fettled checks just before every upload: the template-free rules, against the cell's
// [safety] limits, on a trajectory that did not come out of plan_part (a hostile or corrupted
// one). NaN must fail every comparison.
TEST(ValidateLimits, AHostileTrajectoryIsRefusedAtThePointThatBreaksTheCellLimits) {
  auto p = planned();
  ASSERT_FALSE(p.traj.points.empty());
  const config::SafetySection safety;  // the shipped defaults; the edits below cross them
  const auto limits = PlannerSettings::from(safety);
  ASSERT_TRUE(validate_limits(p.traj, limits)) << validate_limits(p.traj, limits).error().message;

  const std::size_t g = p.first_grind_of("riser");
  const std::size_t a = g - 1;  // the approach onto the riser: not a grind move
  ASSERT_NE(p.traj.points[a].kind, MoveKind::grind);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  auto refused = [&](const std::string& rule, std::size_t i, const std::function<void(TrajectoryPoint&)>& edit) {
    auto t = p.traj;
    edit(t.points[i]);
    expect_rejected(validate_limits(t, limits), rule, "riser", i);
  };
  refused("workspace", g, [&](TrajectoryPoint& q) { q.T_base_tool.position_mm.z() = safety.workspace_min_mm[2] - 400.0; });
  refused("workspace", a, [&](TrajectoryPoint& q) { q.T_base_tool.position_mm.y() = safety.workspace_max_mm[1] + 0.5; });
  refused("finite", g, [&](TrajectoryPoint& q) { q.T_base_tool.position_mm.x() = nan; });
  refused("finite", g, [](TrajectoryPoint& q) { q.T_base_tool.orientation.coeffs() *= 2.0; });
  refused("tool_axis_cone", g, [](TrajectoryPoint& q) {
    q.T_base_tool.orientation = Quat(Eigen::AngleAxisd(deg_to_rad(180.0), Vec3::UnitX()));  // tool pointing up
  });
  refused("speed", g, [&](TrajectoryPoint& q) { q.speed_mm_s = safety.max_speed_mm_s + 0.5; });
  refused("speed", a, [&](TrajectoryPoint& q) { q.speed_mm_s = nan; });
  refused("speed", a, [](TrajectoryPoint& q) { q.speed_mm_s = 0.0; });
  refused("speed", g, [&](TrajectoryPoint& q) { q.spindle_rpm = safety.max_spindle_rpm + 1.0; });
  refused("speed", a, [&](TrajectoryPoint& q) { q.spindle_rpm = nan; });  // NaN passes a plain `> max` check
  refused("speed", a, [](TrajectoryPoint& q) { q.spindle_rpm = -1.0; });
  // The cell's limits, not the planner's defaults: a tighter [safety] refuses the same trajectory.
  config::SafetySection tight;
  tight.max_speed_mm_s = 1.0;
  const auto st = validate_limits(p.traj, PlannerSettings::from(tight));
  ASSERT_FALSE(st);
  EXPECT_EQ(st.error().code, "planning.speed");
  EXPECT_NE(st.error().message.find("point 0,"), std::string::npos) << st.error().message;
}

TEST(Files, TrajectoryJsonCsvAndPreviewRoundTrip) {
  auto p = planned();
  ASSERT_FALSE(p.traj.points.empty());
  const auto dir = std::filesystem::temp_directory_path() / ("fettle-planning-" + std::to_string(::getpid()));
  std::vector<PreviewPoint> cloud;
  for (const auto& in : p.scene.inputs)
    for (const auto& x : in.excess_points_part) cloud.push_back({in.T_base_part * x, in.template_sdf(x)});
  ASSERT_TRUE(write_outputs(dir, p.traj, cloud));
  const Trajectory back = read_trajectory(dir / "trajectory.json");
  EXPECT_EQ(back.part_id, p.traj.part_id);
  EXPECT_EQ(back.segment_regions, p.traj.segment_regions);
  ASSERT_EQ(back.points.size(), p.traj.points.size());
  for (std::size_t i = 0; i < back.points.size(); ++i) {
    const auto& a = back.points[i];
    const auto& b = p.traj.points[i];
    EXPECT_LT((a.T_base_tool.position_mm - b.T_base_tool.position_mm).norm(), 1e-9);
    EXPECT_LT(a.T_base_tool.orientation.angularDistance(b.T_base_tool.orientation), 1e-9);
    EXPECT_EQ(a.segment, b.segment);
    EXPECT_EQ(a.kind, b.kind);
    EXPECT_DOUBLE_EQ(a.speed_mm_s, b.speed_mm_s);
    EXPECT_DOUBLE_EQ(a.spindle_rpm, b.spindle_rpm);
  }
  std::ifstream csv(dir / "trajectory.csv");
  std::string header;
  std::getline(csv, header);
  EXPECT_EQ(header, "x,y,z,qw,qx,qy,qz,speed_mm_s,spindle_rpm,segment,kind");
  std::size_t rows = 0;
  for (std::string line; std::getline(csv, line);) ++rows;
  EXPECT_EQ(rows, p.traj.points.size());
  std::ifstream png(dir / "preview.png", std::ios::binary);
  char sig[8] = {};
  png.read(sig, 8);
  EXPECT_EQ(std::string(sig + 1, 3), "PNG");
  EXPECT_GT(std::filesystem::file_size(dir / "preview.png"), 10000U);
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace fettle::planning
