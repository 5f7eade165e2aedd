// Region planning on the synthetic part: riser layers and allowance, ring / circle loops,
// straight passes, region ordering.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <numbers>

#include "synthetic_part.hpp"

namespace fettle::planning {
namespace {

using testing::make_scene;
using testing::part_sdf;

/// Whether a grinding point of the plan has `m` under its tool (radius R, axis along z): the
/// riser raster's coverage in plan view.
bool under_a_grinding_point(const RegionPlan& plan, const Vec3& m, double R) {
  return std::any_of(plan.points.begin(), plan.points.end(), [&](const TrajectoryPoint& p) {
    return p.kind == MoveKind::grind && (p.T_base_tool.position_mm.head<2>() - m.head<2>()).norm() <= R + 1e-9;
  });
}

TEST(RiserLayers, OnePassWhenWithinTheDepthElseCeilDOverDepth) {
  EXPECT_EQ(layer_levels({1.5, 0.3}, 2.0, 0.05).size(), 1U);
  EXPECT_NEAR(layer_levels({1.5, 0.3}, 2.0, 0.05).back(), 0.05, 1e-12);
  const auto ten = layer_levels({10.0, 4.0, 2.0}, 2.0, 0.05);
  EXPECT_EQ(ten.size(), 5U);  // ⌈10 / 2⌉
  const auto tenhalf = layer_levels({10.5}, 2.0, 0.05);
  EXPECT_EQ(tenhalf.size(), 6U);  // ⌈10.5 / 2⌉
  double previous = 10.5;
  for (double level : tenhalf) {
    EXPECT_LE(previous - level, 2.0 + 1e-9);  // no layer deeper than depth_per_pass
    EXPECT_LT(level, previous);
    previous = level;
  }
  EXPECT_NEAR(tenhalf.back(), 0.05, 1e-12);  // the last layer leaves the allowance
  EXPECT_TRUE(layer_levels({0.04}, 2.0, 0.05).empty());  // nothing above the allowance
}

TEST(RiserPlan, LayersCoverTheFootprintAndLeaveTheAllowance) {
  auto scene = make_scene();
  const RegionInput& in = scene.inputs[1];
  const auto plan = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  const double D = plan->max_excess_mm;
  EXPECT_NEAR(D, 9.0 + 15.0 * std::tan(8.0 * std::numbers::pi / 180.0), 0.3);
  EXPECT_EQ(plan->segments, static_cast<int>(std::ceil(D / 2.0)));
  EXPECT_EQ(plan->layer_levels_mm.size(), static_cast<std::size_t>(plan->segments));
  // last layer: ball tip 0.05 mm above the pad face (z = 45), everywhere
  const int last = plan->segments - 1;
  double xmin = 1e9, xmax = -1e9, ymin = 1e9, ymax = -1e9;
  std::size_t last_points = 0;
  for (const auto& p : plan->points) {
    if (p.segment != last || p.kind != MoveKind::grind) continue;
    ++last_points;
    const Vec3& x = p.T_base_tool.position_mm;
    EXPECT_NEAR(x.z(), 45.05, 1e-3);
    EXPECT_NEAR(p.T_base_tool.orientation.toRotationMatrix().col(2).z(), 1.0, 1e-6);  // axis along the face normal
    xmin = std::min(xmin, x.x()), xmax = std::max(xmax, x.x()), ymin = std::min(ymin, x.y()), ymax = std::max(ymax, x.y());
  }
  EXPECT_GT(last_points, 100U);
  // footprint (radius 15 around (-82, 48)) plus the 3 mm margin
  EXPECT_LE(xmin, -82.0 - 18.0 + 0.3);
  EXPECT_GE(xmax, -82.0 + 18.0 - 0.3);
  EXPECT_LE(ymin, 48.0 - 18.0 + 0.3);
  EXPECT_GE(ymax, 48.0 + 18.0 - 0.3);
  // raster rows at most stepover_mm apart
  std::vector<double> rows;
  for (const auto& p : plan->points)
    if (p.segment == last && p.kind == MoveKind::grind) rows.push_back(p.T_base_tool.position_mm.y());
  std::sort(rows.begin(), rows.end());
  rows.erase(std::unique(rows.begin(), rows.end(), [](double a, double b) { return std::abs(a - b) < 1e-6; }), rows.end());
  for (std::size_t i = 1; i < rows.size(); ++i) EXPECT_LE(rows[i] - rows[i - 1], 4.0 + 1e-6);
}

// A cup wheel worn from 16 to 10 mm under a recipe's 10 mm stepover: its rows close up to 0.8 of
// its diameter, and every point of the riser's footprint lies under the worn wheel's end face on
// the last layer (at 10 mm apart a 10 mm wheel just touches between rows, and the path's noise
// leaves a ridge there).
TEST(RiserPlan, AWornWheelsRowsCloseUp) {
  auto scene = make_scene();
  RegionInput in = scene.inputs[1];
  config::Region region = *in.region;
  region.stepover_mm = 10.0;
  config::Tool worn;
  worn.name = "flat-16";
  worn.shape = config::ToolShape::cylinder;
  worn.diameter_mm = 10.0;  // worn 3 mm in radius
  worn.length_mm = 10.0;
  worn.tcp_mm = {0, 0, 160};
  region.tool = worn.name;
  in.region = &region;
  in.tool = &worn;
  const auto plan = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  const int last = plan->segments - 1;
  std::vector<double> rows;
  for (const auto& p : plan->points)
    if (p.segment == last && p.kind == MoveKind::grind) rows.push_back(p.T_base_tool.position_mm.y());
  std::sort(rows.begin(), rows.end());
  rows.erase(std::unique(rows.begin(), rows.end(), [](double a, double b) { return std::abs(a - b) < 1e-6; }), rows.end());
  ASSERT_GT(rows.size(), 3U);
  for (std::size_t i = 1; i < rows.size(); ++i) EXPECT_LE(rows[i] - rows[i - 1], 8.0 + 1e-6);
  RegionPlan last_layer = *plan;
  last_layer.points.erase(std::remove_if(last_layer.points.begin(), last_layer.points.end(),
                                         [&](const TrajectoryPoint& p) { return p.segment != last; }),
                          last_layer.points.end());
  // the pad's riser footprint (radius 15 round (-82, 48)) under the worn wheel, 0.2 mm inside its rim
  for (double x = -96.0; x <= -68.0; x += 1.0)
    for (double y = 34.0; y <= 62.0; y += 1.0)
      if (std::hypot(x + 82.0, y - 48.0) <= 14.0) {
        EXPECT_TRUE(under_a_grinding_point(last_layer, Vec3(x, y, 45.0), 5.0 - 0.2)) << x << ", " << y;
      }
}

// Stray excess points along two sides of the pad stretch the raster's bounding box to a corner
// over a tall column beside the pad, where the tool cannot go at any height the back-off allows:
// the raster leaves out the points there that cover no material and lifts over the gap. Material under an unreachable point is
// left when it is no higher than leave_unreachable_mm (RegionPlan::left_mm says so), else it is an
// error naming it.
// A casting whose pad stands 0.3 mm (+ 0.005 mm per mm in x) over the nominal: the last
// layer ends on the casting's own face, not 0.3 mm into it at the nominal's level; where the
// casting is below the nominal it ends on the face there too, down to twice the form deviation.
TEST(RiserPlan, TheLastPassEndsOnTheCastingsOwnFaceNotTheNominal) {
  auto scene = make_scene();
  RegionInput in = scene.inputs[1];
  in.form_offset_mm = [](const Vec3& p) { return 0.3 + 0.005 * (p.x() + 82.0); };
  const auto plan = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  const int last = plan->segments - 1;
  std::size_t checked = 0;
  for (const auto& p : plan->points) {
    if (p.segment != last || p.kind != MoveKind::grind) continue;
    const Vec3& x = p.T_base_tool.position_mm;
    const double face = 45.0 + std::max(0.0, 0.3 + 0.005 * (x.x() + 82.0));
    EXPECT_NEAR(x.z(), face + 0.05, 0.02) << "at x = " << x.x();
    ++checked;
  }
  EXPECT_GT(checked, 100U);
  // a face under the nominal: the last pass follows it down (no riser stub left on it), by no
  // more than twice the stated form deviation (the form and the located pose's lift)
  in.form_deviation_mm = 0.5;
  for (const double offset : {-0.4, -0.9, -1.3}) {
    in.form_offset_mm = [offset](const Vec3&) { return offset; };
    const auto below = plan_region(in, PlannerSettings{});
    ASSERT_TRUE(below) << below.error().message;
    const double face = 45.0 + std::max(offset, -1.0);
    std::size_t on_face = 0;
    for (const auto& p : below->points)
      if (p.segment == below->segments - 1 && p.kind == MoveKind::grind) {
        EXPECT_NEAR(p.T_base_tool.position_mm.z(), face + 0.05, 1e-3) << "offset " << offset;
        ++on_face;
      }
    EXPECT_GT(on_face, 100U) << "offset " << offset;
  }
}

// A casting whose face under the riser is a crest (0.3 mm over the nominal at the riser's
// centre, falling to 0 at 18 mm: a sand-cast form wave of about 100 mm): the layers follow the
// face under each raster point, so the last one leaves about the allowance over the whole
// footprint, where a layer flat at the centre's height leaves 0.23 mm more at the rim.
TEST(RiserPlan, TheLastLayerFollowsTheCastingsFaceUnderTheRiser) {
  auto scene = make_scene();
  RegionInput in = scene.inputs[1];
  const auto crest = [](double x, double y) {
    return 0.3 * (1.0 - (std::pow(x + 82.0, 2) + std::pow(y - 48.0, 2)) / (18.0 * 18.0));
  };
  in.form_offset_mm = [&](const Vec3& p) { return crest(p.x(), p.y()); };
  in.form_deviation_mm = 0.5;
  const auto plan = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  // the last layer's tips over the footprint: the allowance over the face under each
  double most_left = 0.0, least_left = 1e9;
  std::size_t over_footprint = 0;
  for (const auto& p : plan->points) {
    const Vec3& x = p.T_base_tool.position_mm;
    if (p.segment != plan->segments - 1 || p.kind != MoveKind::grind || std::hypot(x.x() + 82.0, x.y() - 48.0) > 15.0)
      continue;
    const double left = x.z() - (45.0 + crest(x.x(), x.y()));
    most_left = std::max(most_left, left), least_left = std::min(least_left, left);
    ++over_footprint;
  }
  EXPECT_GT(over_footprint, 100U);
  EXPECT_GE(least_left, 0.05 - 0.005) << "the allowance is kept";
  EXPECT_LT(most_left, 0.05 + 0.03) << "left over the face beyond the allowance";
}

// The cell's placement bound (0.35 mm sideways, 0.20 mm vertically; the allowance is 0.05):
// every grinding pose of the ball-tool regions keeps the bound along the nearest surface's
// normal and the nearest comes to it (the boss's loop rides its top edge, whose normal is
// diagonal: 0.29 mm), the riser's last layer 0.20 mm over its face. Without the bound the same
// plans come within 0.15 mm.
TEST(RegionPlanning, EveryPoseKeepsThePlacementBoundAlongTheSurfacesNormal) {
  const Eigen::Matrix3d M = Vec3(0.35 * 0.35, 0.35 * 0.35, 0.2 * 0.2).asDiagonal();
  const auto bound_along = [&](const Vec3& n) { return std::sqrt(n.dot(M * n)); };
  // a ball-tool plan's grinding poses: the smallest gap to the template, and the same less the
  // bound along the nearest surface's normal there
  struct Gaps {
    double gap = 1e9, over_bound = 1e9;
  };
  const auto gaps = [&](const RegionPlan& plan, const RegionInput& in) {
    Gaps g;
    const double R = 0.5 * in.tool->diameter_mm;
    for (const auto& p : plan.points) {
      if (p.kind != MoveKind::grind) continue;
      const Transform T_part_tool = in.T_base_part.inverse() * p.T_base_tool.to_transform();
      const Vec3 c = T_part_tool * Vec3(0.0, 0.0, R);  // the ball's centre, R up the axis from the tip
      Vec3 n;
      for (int k = 0; k < 3; ++k) {
        Vec3 d = Vec3::Zero();
        d(k) = 0.01;
        n(k) = part_sdf(c + d) - part_sdf(c - d);
      }
      n.normalize();
      const double gap = part_sdf(c) - R;
      g.gap = std::min(g.gap, gap);
      g.over_bound = std::min(g.over_bound, gap - bound_along(n));
    }
    return g;
  };
  auto scene = make_scene();
  for (const std::size_t i : {1U, 2U, 3U}) {
    RegionInput in = scene.inputs[i];
    const auto free = plan_region(in, PlannerSettings{});
    ASSERT_TRUE(free) << free.error().message;
    in.placement_bound_mm2 = M;
    const auto kept = plan_region(in, PlannerSettings{});
    ASSERT_TRUE(kept) << kept.error().message;
    EXPECT_LT(gaps(*free, in).gap, 0.15) << in.region->name;
    EXPECT_NEAR(gaps(*kept, in).over_bound, 0.0, 0.02) << in.region->name << ": the bound, not more";
  }
  RegionInput riser = scene.inputs[1];
  riser.placement_bound_mm2 = M;
  const auto plan = plan_region(riser, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  for (const auto& p : plan->points) {
    if (p.segment == plan->segments - 1 && p.kind == MoveKind::grind) {
      EXPECT_NEAR(p.T_base_tool.position_mm.z(), 45.2, 0.02);
    }
  }
}

TEST(RiserPlan, AnUnreachableRasterCornerWithoutMaterialIsLeftOutAndLiftedOver) {
  auto scene = make_scene();
  RegionInput in = scene.inputs[1];
  const Vec3 col_lo(-62, 14, 0), col_hi(-45, 29, 90);  // beside the pad's +x edge, 45 mm above it
  in.template_sdf = [=](const Vec3& p) { return std::min(part_sdf(p), testing::sdf_box(p, col_lo, col_hi)); };
  in.excess_points_part.emplace_back(-64.0, 52.0, 45.4);  // amax: -61
  in.excess_points_part.emplace_back(-84.0, 26.0, 45.4);  // bmin: 23
  const PlannerSettings settings;
  const auto plan = plan_region(in, settings);
  ASSERT_TRUE(plan) << plan.error().message;
  const double R = 6.0;  // ball-12
  std::size_t grind = 0, air = 0;
  for (const auto& p : plan->points) {
    (p.kind == MoveKind::grind ? grind : air) += 1;
    if (p.kind != MoveKind::grind) continue;
    // no grinding point with the ball over the column
    const Vec3& x = p.T_base_tool.position_mm;
    EXPECT_FALSE(x.x() > col_lo.x() - R && x.y() < col_hi.y() + R && x.y() > col_lo.y() - R) << x.transpose();
  }
  EXPECT_GT(grind, 100U);
  EXPECT_GT(air, 2U * (plan->segments - 1U));  // lifts over the gaps besides those between layers
  // every material point is under the ball of some grinding point
  for (const auto& m : in.excess_points_part) EXPECT_TRUE(under_a_grinding_point(*plan, m, R)) << m.transpose();
  // the whole trajectory keeps the allowance, lifts included
  RegionInput one = in;
  const auto traj = plan_part("p", {one}, settings);
  ASSERT_TRUE(traj) << traj.error().message;
  EXPECT_EQ(plan->left_mm, 0.0);
  // a low excess point beside the column (0.25 mm: noise at the pad's edge) is left and said
  in.excess_points_part.emplace_back(-63.0, 27.0, 45.25);
  const auto low = plan_region(in, settings);
  ASSERT_TRUE(low) << low.error().message;
  EXPECT_NEAR(low->left_mm, 0.25, 1e-6);
  EXPECT_NEAR((low->left_at - Vec3(-63.0, 27.0, 45.25)).norm(), 0.0, 1e-9);
  // material higher than leave_unreachable_mm there: the tool cannot reach it, and says so
  in.excess_points_part.back() = Vec3(-63.0, 27.0, 45.6);
  const auto refused = plan_region(in, settings);
  ASSERT_FALSE(refused);
  EXPECT_NE(refused.error().message.find("cannot reach the riser material"), std::string::npos) << refused.error().message;
  EXPECT_NE(refused.error().message.find("(-63.00, 27.00, 45.60), 0.60 mm above"), std::string::npos)
      << refused.error().message;
  // on a casting whose form deviates up to 0.7 mm from the nominal, 0.6 mm there may be its own
  // face: left and said, not a casting refused
  in.form_deviation_mm = 0.7;
  const auto form = plan_region(in, settings);
  ASSERT_TRUE(form) << form.error().message;
  EXPECT_NEAR(form->left_mm, 0.6, 1e-6);
}

// A flat-ended tool's raster reaches over a block beside the pad (the flange beside a casting's
// riser, up to 10 mm above a layer; stray excess points stretch the raster's
// bounding box over it): the points over the block back off up onto it, and the steep moves up
// onto it cut the block's edge. Pushing both ends of such a move up, as for a dip of the
// sampled template, does not clear it within the back-off limit: the raster lifts over the move
// as over a left-out point, grinds the rest, and the whole trajectory keeps the allowance.
TEST(RiserPlan, AMoveUpOntoAHigherBlockBesideThePadIsLiftedOver) {
  auto scene = make_scene();
  RegionInput in = scene.inputs[1];
  config::Tool flat;  // the pump body's flat-16 cup wheel
  flat.name = "flat-16";
  flat.shape = config::ToolShape::cylinder;
  flat.diameter_mm = 16.0;
  flat.length_mm = 10.0;
  flat.tcp_mm = {0, 0, 160};
  in.tool = &flat;
  const Vec3 block_lo(-62, 14, 0), block_hi(-40, 29, 55);  // 8 mm above the first layer (z 54.3)
  in.template_sdf = [=](const Vec3& p) { return std::min(part_sdf(p), testing::sdf_box(p, block_lo, block_hi)); };
  in.excess_points_part.emplace_back(-64.0, 52.0, 45.4);  // amax: -61
  in.excess_points_part.emplace_back(-84.0, 26.0, 45.4);  // bmin: 23
  const PlannerSettings settings;
  const auto plan = plan_region(in, settings);
  ASSERT_TRUE(plan) << plan.error().message;
  const double R = 8.0;
  std::size_t grind = 0, air = 0, on_block = 0;
  for (const auto& p : plan->points) {
    (p.kind == MoveKind::grind ? grind : air) += 1;
    const Vec3& x = p.T_base_tool.position_mm;
    if (p.kind == MoveKind::grind && x.x() > block_lo.x() - R && x.y() < block_hi.y() + R) on_block += 1;
  }
  EXPECT_GT(grind, 100U);
  EXPECT_GT(on_block, 0U);  // the raster does go up onto the block (it backs off there)
  EXPECT_GT(air, 2U * (plan->segments - 1U));  // and lifts over the moves up onto it
  EXPECT_EQ(plan->left_mm, 0.0);
  // every material point is under the wheel of some grinding point
  for (const auto& m : in.excess_points_part) EXPECT_TRUE(under_a_grinding_point(*plan, m, R)) << m.transpose();
  // every pose and move of the whole trajectory keeps the allowance (plan_part validates it)
  const auto traj = plan_part("p", {in}, settings);
  ASSERT_TRUE(traj) << traj.error().message;
}

// A lift is checked on its way up and down too: a slab over the pad (an overhang the ball
// passes under while grinding) is in the way of the lift between the riser's layers, however
// high it goes, and the plan is refused naming the move (the planner does not leave a lift
// through the slab for validation to catch).
TEST(RiserPlan, ALiftUnderAnOverhangIsRefusedNamingTheMove) {
  auto scene = make_scene();
  RegionInput in = scene.inputs[1];
  const auto open = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(open) << open.error().message;
  ASSERT_GT(open->segments, 1);  // lifts between layers
  // the ball's top passes 5.7 mm under the slab on the first layer; the lift (D + 5 mm) reaches it
  const Vec3 slab_lo(-110, 22, 72), slab_hi(-62, 85, 80);
  in.template_sdf = [=](const Vec3& p) { return std::min(part_sdf(p), testing::sdf_box(p, slab_lo, slab_hi)); };
  const auto refused = plan_region(in, PlannerSettings{});
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().code, "planning.gouge");
  EXPECT_NE(refused.error().message.find("region 'riser': the air move lifting off at"), std::string::npos)
      << refused.error().message;
  EXPECT_NE(refused.error().message.find("the template overhangs it: on the way up"), std::string::npos)
      << refused.error().message;
}

// A wall 400 mm tall across part of the pad (the material beside it removed, so the raster
// leaves the points over it out and lifts over the gap): no lift up to 300 mm clears it, and
// the plan says so instead of adding a lift through the wall.
TEST(RiserPlan, AWallNoLiftClearsIsRefusedNamingIt) {
  auto scene = make_scene();
  RegionInput in = scene.inputs[1];
  const Vec3 wall_lo(-83, 22, 0), wall_hi(-81, 34, 400);
  in.template_sdf = [=](const Vec3& p) { return std::min(part_sdf(p), testing::sdf_box(p, wall_lo, wall_hi)); };
  std::erase_if(in.excess_points_part, [](const Vec3& p) { return std::abs(p.x() + 82.0) < 14.0 && p.y() < 50.0; });
  const auto refused = plan_region(in, PlannerSettings{});
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().code, "planning.gouge");
  EXPECT_NE(refused.error().message.find("no lift up to 300 mm keeps the allowance"), std::string::npos)
      << refused.error().message;
}

// Tool probes ask the template's near(p, d), which is exact only within d: a clearance larger
// than the 2 mm the probes ask for by default must be asked for. A template whose near() answers
// 2.5 mm too far beyond d (as a signed-distance grid's lattice may, within its bound) and a
// ridge beside the riser that the disc's last layers must back off from: every grinding pose
// keeps the 3 mm allowance by the exact distance (with d = 2 mm the back-off stopped at 2 mm).
TEST(RiserPlan, ABackOffKeepsAnAllowanceBeyondTwoMillimetres) {
  auto scene = make_scene();
  RegionInput in = scene.inputs[1];
  in.tool = &scene.tools[0];  // the 40 mm disc: probes over its face and rim
  config::Region region = scene.regions[1];
  region.allowance_mm = 3.0;
  in.region = &region;
  const Vec3 ridge_lo(-110, 76, 45), ridge_hi(-62, 80, 47.6);  // 2.6 mm above the pad
  auto exact = [=](const Vec3& p) { return std::min(part_sdf(p), testing::sdf_box(p, ridge_lo, ridge_hi)); };
  in.template_sdf = SignedDistance(exact, [=](const Vec3& p, double d) {
    const double v = exact(p);
    return std::abs(v) <= d ? v : v + std::copysign(2.5, v);
  });
  const auto plan = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  const SignedDistance truth = exact;
  std::size_t grind = 0, backed_off = 0;
  double worst = -1e9;
  for (const auto& p : plan->points) {
    if (p.kind != MoveKind::grind) continue;
    ++grind;
    const double pen = tool_penetration_mm(*in.tool, p.T_base_tool.to_transform(), truth, nullptr, 3.0);
    worst = std::max(worst, pen);
    if (p.segment == plan->segments - 1 && p.T_base_tool.position_mm.z() > 45.0 + 3.0 + 0.1) ++backed_off;
  }
  EXPECT_GT(grind, 100U);
  EXPECT_GT(backed_off, 0U);  // the ridge did push the last layer up somewhere
  EXPECT_LE(worst, -3.0 + 0.01);
}

// A ring is fitted only to flash that goes round it and only where the recipe says the ring is:
// a re-grind's leftover arc or a region the camera barely sees is refused with the reason, never
// turned into a loop around a guessed ellipse (a ring guessed from a re-grind's arc can put
// the disc 7 mm into the flange).
TEST(RingPlan, AShortArcOrARingOutsideTheRoiIsRefusedWithTheReason) {
  auto scene = make_scene();
  RegionInput arc = scene.inputs[0];
  std::vector<Vec3> kept;
  for (const auto& p : arc.excess_points_part)
    if (std::atan2(p.y(), p.x()) > 0.0 && std::atan2(p.y(), p.x()) < 1.2) kept.push_back(p);  // ~70 degrees
  ASSERT_GT(kept.size(), 20U);
  arc.excess_points_part = kept;
  const auto short_arc = plan_region(arc, PlannerSettings{});
  ASSERT_FALSE(short_arc);
  EXPECT_EQ(short_arc.error().code, "planning.fit");
  EXPECT_NE(short_arc.error().message.find("too short an arc"), std::string::npos) << short_arc.error().message;
  EXPECT_NE(short_arc.error().message.find("flange-ring"), std::string::npos) << short_arc.error().message;

  config::Region elsewhere = *scene.inputs[0].region;
  elsewhere.roi_center_mm = {100.0, 0.0, 50.0};  // the ROI 100 mm beside the flange
  RegionInput moved = scene.inputs[0];
  moved.region = &elsewhere;
  const auto outside = plan_region(moved, PlannerSettings{});
  ASSERT_FALSE(outside);
  EXPECT_NE(outside.error().message.find("does not lie in the region's ROI"), std::string::npos) << outside.error().message;
}

// A re-grind's leftover of the fin, 70 degrees of it, fits no ring; the re-grind grinds along the
// first plan's ring (fitted to the whole fin), its contact points on the template's wall as the
// first plan's were.
TEST(RingPlan, AReGrindFollowsTheFirstPlansRing) {
  auto scene = make_scene();
  const auto first = plan_region(scene.inputs[0], PlannerSettings{});
  ASSERT_TRUE(first) << first.error().message;
  RegionInput arc = scene.inputs[0];
  std::vector<Vec3> kept;
  for (const auto& p : arc.excess_points_part)
    if (std::atan2(p.y(), p.x()) > 0.0 && std::atan2(p.y(), p.x()) < 1.2) kept.push_back(p);
  arc.excess_points_part = kept;
  ASSERT_FALSE(plan_region(arc, PlannerSettings{}));  // on its own: too short an arc
  arc.first = &first.value();
  const auto again = plan_region(arc, PlannerSettings{});
  ASSERT_TRUE(again) << again.error().message;
  ASSERT_EQ(again->points.size(), first->points.size());
  for (std::size_t i = 0; i < again->points.size(); ++i)
    EXPECT_LT((again->points[i].T_base_tool.position_mm - first->points[i].T_base_tool.position_mm).norm(), 1e-9) << i;
  EXPECT_LT((again->conic_origin - first->conic_origin).norm(), 1e-12);
  // another region type's plan is no ring to follow
  const auto riser = plan_region(scene.inputs[1], PlannerSettings{});
  ASSERT_TRUE(riser) << riser.error().message;
  arc.first = &riser.value();
  EXPECT_FALSE(plan_region(arc, PlannerSettings{}));
}

// The pump body's boss: its fin ground by a burr's side, edge-on to the camera, so the placement
// error across the wall is never measured and the loop keeps the whole bound from it (0.5 mm
// here; the fin 5 mm under the boss's top, the boss block's top 7 mm under the fin). The first grind leaves a fin that wide plus the error. Where the re-scan sees it stand
// 0.45 mm off the wall, the re-grind comes 0.30 mm nearer (0.45 less the 0.15 mm repeatability);
// where it stands 0.9 mm off, as near as the allowance; where it sees none, or one stray point, or
// points off the fin's level, the loop runs where it ran.
TEST(CirclePlan, AReGrindComesNearerTheWallWhereTheFirstLeftTheFin) {
  auto scene = make_scene();
  config::Region boss = scene.regions[2];
  boss.contact = config::FlashContact::periphery;
  boss.allowance_mm = 0.12;
  RegionInput in = scene.inputs[2];
  in.region = &boss;
  in.tool = &scene.tools.at(2);
  ASSERT_EQ(in.tool->name, "burr-10");
  // the boss 5 mm above its fin, as on the pump body (the burr's side does not pass its top edge)
  in.template_sdf = [](const Vec3& p) {
    return std::min(part_sdf(p), testing::sdf_cylinder(p, 82, -48, 7, 0, 52));
  };
  in.placement_bound_mm2 = Vec3(0.5 * 0.5, 0.5 * 0.5, 0.39 * 0.39).asDiagonal();
  PlannerSettings settings;
  settings.repeatability_mm = 0.15;
  const auto first = plan_region(in, settings);
  ASSERT_TRUE(first) << first.error().message;
  const auto at = [](double deg, double r, double z) {
    const double a = deg * std::numbers::pi / 180.0;
    return Vec3(82.0 + (7.0 + r) * std::cos(a), -48.0 + (7.0 + r) * std::sin(a), z);
  };
  RegionInput again = in;
  again.first = &first.value();
  again.excess_points_part.clear();  // the re-scan's stub is too thin to read as excess
  const auto leave = [&](double deg, double r, double z) {
    again.leftover_part.push_back(at(deg, r, z));
    again.leftover_mm.push_back(r);
  };
  for (double deg = 30.0; deg <= 120.0; deg += 1.0)
    for (const double r : {0.1, 0.2, 0.35, 0.45}) leave(deg, r, 46.6);
  for (double deg = 150.0; deg <= 200.0; deg += 1.0) leave(deg, 0.9, 46.6);
  leave(270.0, 1.5, 46.6);                                               // one stray point
  for (double deg = 295.0; deg <= 315.0; deg += 1.0) leave(deg, 0.8, 41.6);  // 5 mm under the fin
  const auto second = plan_region(again, settings);
  ASSERT_TRUE(second) << second.error().message;
  ASSERT_EQ(second->points.size(), first->points.size());
  // the burr's side from the wall, and where round the boss
  const auto gap = [](const TrajectoryPoint& p) {
    return std::hypot(p.T_base_tool.position_mm.x() - 82.0, p.T_base_tool.position_mm.y() + 48.0) - 7.0 - 5.0;
  };
  const auto deg_of = [](const TrajectoryPoint& p) {
    const double a = std::atan2(p.T_base_tool.position_mm.y() + 48.0, p.T_base_tool.position_mm.x() - 82.0);
    return std::fmod(a * 180.0 / std::numbers::pi + 360.0, 360.0);
  };
  std::size_t nearer = 0, allowance = 0, same = 0;
  for (std::size_t i = 1; i + 1 < first->points.size(); ++i) {  // the leads stand off
    const auto &p1 = first->points[i], &p2 = second->points[i];
    // the bound, and the back-off's tolerance at most over it
    EXPECT_GE(gap(p1), 0.5 - 0.01) << i;
    EXPECT_LE(gap(p1), 0.5 + 0.05) << i;
    EXPECT_GE(gap(p2), boss.allowance_mm - 0.01) << i;
    const double deg = deg_of(p1);
    if (deg > 40.0 && deg < 110.0) {
      // 0.30 nearer, less where the wall's normal turns from the leftover's (never more)
      EXPECT_GE(gap(p2), gap(p1) - 0.30 - 0.005) << deg;
      EXPECT_LE(gap(p2), gap(p1) - 0.30 + 0.02) << deg;
      ++nearer;
    } else if (deg > 160.0 && deg < 190.0) {
      EXPECT_LE(gap(p2), boss.allowance_mm + 0.05) << deg;
      ++allowance;
    } else if (deg > 215.0 || deg < 15.0) {
      EXPECT_NEAR(gap(p2), gap(p1), 0.01) << deg;  // within the back-off search's steps
      ++same;
    }
  }
  EXPECT_GT(nearer, 5U);
  EXPECT_GT(allowance, 3U);
  EXPECT_GT(same, 10U);
  // nothing the first grind left beyond the repeatability: nothing to grind again
  again.leftover_part = {at(90.0, 0.1, 46.6), at(91.0, 0.12, 46.6), at(92.0, 0.14, 46.6)};
  again.leftover_mm = {0.1, 0.12, 0.14};
  const auto none = plan_region(again, settings);
  ASSERT_TRUE(none) << none.error().message;
  EXPECT_TRUE(none->points.empty());
}

// A camera that sees 240 degrees of the fin, and excess elsewhere in the ROI (the body's form
// deviation read as material, 15 mm below the parting plane, on the side the fin is not seen):
// the ring is fitted to the flash on the parting plane only. With the stray points in the
// ellipse's fit it came out 50.6 x 47.4 mm and the disc went 0.78 mm into the flange.
TEST(RingPlan, ExcessOffThePartingPlaneDoesNotPullTheRingOffTheFlange) {
  auto scene = make_scene();
  RegionInput seen = scene.inputs[0];
  std::vector<Vec3> kept;
  double z = 0.0;
  for (const auto& p : seen.excess_points_part)
    if (std::abs(std::atan2(p.y(), p.x())) < 120.0 * std::numbers::pi / 180.0) kept.push_back(p), z = p.z();
  ASSERT_GT(kept.size(), 40U);
  // stray bumps on the body 15 mm below the fin
  const int stray = static_cast<int>(kept.size()) / 3;
  for (int i = 0; i < stray; ++i) {  // on the side the camera does not see, outside the flange
    const double a = std::numbers::pi * (0.8 + 0.4 * i / stray), r = 53.0 + 0.5 * std::sin(0.7 * i);
    kept.emplace_back(r * std::cos(a), r * std::sin(a), z - 15.0 + 0.2 * std::sin(1.3 * i));
  }
  seen.excess_points_part = kept;
  const auto plan = plan_region(seen, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  const auto e = ellipse_geometry(plan->conic);
  ASSERT_TRUE(e);
  EXPECT_LT(e->semi_major - e->semi_minor, 2.0);
  EXPECT_GT(e->semi_minor, 44.0);
  EXPECT_LT(e->semi_major, 49.0);
  for (const auto& p : plan->points) {
    if (p.kind != MoveKind::grind) continue;
    EXPECT_LE(tool_penetration_mm(*seen.tool, p.T_base_tool.to_transform(), part_sdf), 0.0);
  }
}

// A casting's form deviation (0.5 mm for sand-cast iron) makes the body's top read as excess
// all round the flange, more points than the fin itself: the parting plane is the plane of the
// points standing out of a wall it cuts (the flange's), not of the face below. With a plain
// RANSAC plane the ring was fitted on the base plate's top, 15 mm below the fin.
TEST(RingPlan, FormDeviationOnTheFaceBelowDoesNotTakeThePartingPlane) {
  auto scene = make_scene();
  RegionInput in = scene.inputs[0];
  const std::size_t fin = in.excess_points_part.size();
  for (double r = 46.0; r <= 58.0; r += 0.5)
    for (double a = 0.0; a < 2 * std::numbers::pi; a += 0.5 / r)
      in.excess_points_part.emplace_back(r * std::cos(a), r * std::sin(a), 35.3 + 0.15 * std::sin(3 * a + 0.2 * r));
  ASSERT_GT(in.excess_points_part.size(), 2 * fin) << "the face below outnumbers the fin";
  const auto plan = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_GT(plan->plane.normal.z(), 0.999);
  EXPECT_NEAR(-plan->plane.d, 50.0, 0.5) << "the parting plane is the fin's, at z = 50";
  const auto e = ellipse_geometry(plan->conic);
  ASSERT_TRUE(e);
  EXPECT_GT(e->semi_minor, 45.0);
  EXPECT_LT(e->semi_major, 48.5);
  std::size_t grind = 0;
  for (const auto& p : plan->points) {
    if (p.kind != MoveKind::grind) continue;
    ++grind;
    EXPECT_LE(tool_penetration_mm(*in.tool, p.T_base_tool.to_transform(), part_sdf), 0.0);
  }
  EXPECT_GT(grind, 290U);
}

TEST(RingPlan, ClosedChamferLoopAtOneMillimetreSpacingWithOverlapAndLeads) {
  auto scene = make_scene();
  const RegionInput& in = scene.inputs[0];
  const auto plan = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  // the fitted plane is the flange top, the ellipse a circle in the fin's band
  EXPECT_GT(plan->plane.normal.z(), 0.999);
  const auto e = ellipse_geometry(plan->conic);
  ASSERT_TRUE(e);
  EXPECT_NEAR(e->semi_major, e->semi_minor, 0.5);
  EXPECT_GT(e->semi_minor, 45.0);
  EXPECT_LT(e->semi_major, 48.5);
  const auto& pts = plan->points;
  ASSERT_GT(pts.size(), 290U);  // 2π·45 mm + 10 mm overlap at ≤ 1 mm
  double travelled_deg = 0.0;
  for (std::size_t i = 2; i + 1 < pts.size(); ++i) {  // the contact points, without lead-in / lead-out
    const Vec3 a = pts[i - 1].T_base_tool.position_mm, b = pts[i].T_base_tool.position_mm;
    EXPECT_LE((b - a).norm(), 1.0 + 1e-6) << "contact " << i;
    travelled_deg += std::abs(std::remainder(std::atan2(b.y(), b.x()) - std::atan2(a.y(), a.x()), 2 * std::numbers::pi)) * 180.0 / std::numbers::pi;
  }
  EXPECT_GT(travelled_deg, 360.0 + 10.0);  // closed, with the 10 mm overlap (~12.7°)
  for (std::size_t i = 1; i + 1 < pts.size(); ++i) {
    const Transform T = pts[i].T_base_tool.to_transform();
    const Vec3 z = T.linear().col(2);
    const Vec3 radial = Vec3(T.translation().x(), T.translation().y(), 0.0).normalized();
    EXPECT_NEAR(z.z(), std::sqrt(0.5), 1e-3);            // 45° chamfer: √2/2 along w
    EXPECT_NEAR(z.dot(radial), std::sqrt(0.5), 2e-2);    // and √2/2 along n
    const double r = std::hypot(T.translation().x(), T.translation().y());
    EXPECT_NEAR(r, 45.05, 0.2);  // contact at the edge, the allowance outside
    EXPECT_LE(tool_penetration_mm(*in.tool, T, part_sdf), 0.0);
  }
  // lead-in / lead-out: radially outside the first / last contact point
  EXPECT_NEAR((pts.front().T_base_tool.position_mm - pts[1].T_base_tool.position_mm).norm(), 5.0, 1e-6);
  EXPECT_NEAR((pts.back().T_base_tool.position_mm - pts[pts.size() - 2].T_base_tool.position_mm).norm(), 5.0, 1e-6);
}

TEST(CirclePlan, SmallBossLoopUsesItsOwnToolAndAngle) {
  auto scene = make_scene();
  scene.regions[2].chamfer_deg = 60.0;
  const auto plan = plan_region(scene.inputs[2], PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  const auto e = ellipse_geometry(plan->conic);
  ASSERT_TRUE(e);
  EXPECT_NEAR(e->semi_major, 8.0, 1.0);
  ASSERT_GT(plan->points.size(), 44U);
  for (std::size_t i = 1; i + 1 < plan->points.size(); ++i) {
    const auto& p = plan->points[i];
    EXPECT_NEAR(p.T_base_tool.orientation.toRotationMatrix().col(2).z(), std::sin(deg_to_rad(60.0)), 1e-3);
    EXPECT_DOUBLE_EQ(p.spindle_rpm, 9000.0);
    EXPECT_DOUBLE_EQ(p.speed_mm_s, 15.0);
    const Vec3 x = p.T_base_tool.position_mm;
    EXPECT_NEAR(std::hypot(x.x() - 82.0, x.y() + 48.0), 7.05, 0.3);
  }
}

TEST(StraightPlan, PassesAlongTheFittedLineWithTheToolOnTheFaceNormal) {
  auto scene = make_scene();
  const auto plan = plan_region(scene.inputs[3], PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_GT(std::abs(plan->line.direction.x()), 0.999);
  EXPECT_EQ(plan->segments, 2);
  ASSERT_EQ(plan->layer_levels_mm.size(), 2U);
  EXPECT_NEAR(plan->layer_levels_mm.back(), 0.05, 1e-9);
  double xmin = 1e9, xmax = -1e9;
  for (const auto& p : plan->points) {
    if (p.kind != MoveKind::grind) continue;
    const Vec3 x = p.T_base_tool.position_mm;
    EXPECT_NEAR(x.y(), -70.0, 0.3);
    EXPECT_NEAR(p.T_base_tool.orientation.toRotationMatrix().col(2).z(), 1.0, 1e-6);
    if (p.segment == 1) {
      EXPECT_NEAR(x.z(), 35.05, 1e-3);
    }
    xmin = std::min(xmin, x.x()), xmax = std::max(xmax, x.x());
  }
  EXPECT_LT(xmin, -95.0 - 6.0);  // past both ends by the tool radius
  EXPECT_GT(xmax, -5.0 + 6.0);
}

TEST(StraightPlan, StrayExcessPointsAlongTheLineDoNotStretchThePasses) {
  // The fin runs from x = -95 to -5; a few excess points 0.3 mm high lie on the same line at
  // x = 30..35 (a lower-resolution scan's noise at the ROI's end made the passes of a demo cycle
  // run 45 mm past the fin and gouge there).
  auto scene = make_scene();
  auto& in = scene.inputs[3];
  const std::size_t fin_points = in.excess_points_part.size();
  std::size_t stray = 0;
  for (double x = 30.0; x <= 35.0; x += 0.5, ++stray) in.excess_points_part.emplace_back(x, -70.0, 35.3);
  ASSERT_LT(stray * 10, fin_points);
  const auto plan = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  double xmax = -1e9;
  for (const auto& p : plan->points)
    if (p.kind == MoveKind::grind) xmax = std::max(xmax, p.T_base_tool.position_mm.x());
  EXPECT_GT(xmax, -5.0 + 6.0);
  EXPECT_LT(xmax, -5.0 + 6.0 + PlannerSettings{}.lead_mm + 1.0);  // the fin's end, the tool radius, the lead
  // Excess points within the fin's stretch but off the line's band (a taller spot of the fin)
  // set the height too.
  EXPECT_LT(plan->max_excess_mm, 2.5);
  auto taller = in;
  for (double x = -50.0; x <= -45.0; x += 0.5) taller.excess_points_part.emplace_back(x, -70.0, 39.5);
  const auto tall = plan_region(taller, PlannerSettings{});
  ASSERT_TRUE(tall) << tall.error().message;
  EXPECT_NEAR(tall->max_excess_mm, 4.5, 0.05);
  // A second piece as long as the fin is flash too: the passes cover both.
  for (const auto& p : testing::straight_fin(10.0, 40.0, -70.0, 35.0, 1.0, 1.0, 0.5)) in.excess_points_part.push_back(p);
  const auto both = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(both) << both.error().message;
  xmax = -1e9;
  for (const auto& p : both->points)
    if (p.kind == MoveKind::grind) xmax = std::max(xmax, p.T_base_tool.position_mm.x());
  EXPECT_GT(xmax, 40.0 + 6.0);
  EXPECT_EQ(both->left_length_mm, 0.0);
}

// A broad patch of the face 0.2 mm proud of the template beside the fin's end (the casting's
// form deviation where the whole part's fit leaves it: an unseen casting's excess points held one
// of 180 points at x 2..21, y -80..-70): it is no fin, and the line stays on the fin (a line
// fitted to every point runs 5 degrees across it, and its passes leave the fin 0.5-0.9 mm high
// over 10 mm).
TEST(StraightPlan, ALowPatchBesideTheFinDoesNotTiltTheLine) {
  auto scene = make_scene();
  auto& in = scene.inputs[3];
  in.excess_points_part = testing::straight_fin(-95.0, -35.0, -70.0, 35.0, 1.5, 1.0, 0.5);
  for (double x = 2.0; x <= 21.0; x += 1.0)
    for (double y = -80.0; y <= -70.0; y += 1.0) in.excess_points_part.emplace_back(x, y, 35.2);
  const auto plan = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_GT(std::abs(plan->line.direction.x()), 0.9999) << plan->line.direction.transpose();
  for (const auto& p : plan->points)
    if (p.kind == MoveKind::grind && p.T_base_tool.position_mm.x() < -30.0) {
      EXPECT_NEAR(p.T_base_tool.position_mm.y(), -70.0, 0.2) << p.T_base_tool.position_mm.transpose();
    }
}

// A fin that runs up to a wall (the boss block's at x = 62, outside the region's ROI): the
// passes end where the ball keeps the allowance from the wall, never ramping up it, and the
// fin the ball cannot reach there is left and reported with its length and height. On the
// simulator's pump body a 150 mm fin runs up to the tilted block's wall the same way.
TEST(StraightPlan, AFinThatRunsIntoAWallIsGroundUpToItAndTheRestIsLeft) {
  auto scene = make_scene();
  auto& in = scene.inputs[3];
  in.excess_points_part = testing::straight_fin(-40.0, 62.0, -70.0, 35.0, 2.0, 1.0, 0.5);
  const PlannerSettings settings;
  const auto plan = plan_region(in, settings);
  ASSERT_TRUE(plan) << plan.error().message;
  const double R = 6.0, allowance = in.region->allowance_mm;
  double xmax = -1e9;
  for (const auto& p : plan->points) {
    if (p.kind != MoveKind::grind) continue;
    const Vec3& x = p.T_base_tool.position_mm;
    xmax = std::max(xmax, x.x());
    // on the face at its level, never lifted over the wall: the tip within the fin's height
    EXPECT_LT(x.z(), 35.0 + 2.0 + 1e-6) << x.transpose();
    // and the ball keeps the allowance from the whole template
    EXPECT_LE(tool_penetration_mm(*in.tool, p.T_base_tool.to_transform(), in.template_sdf, nullptr, allowance),
              -allowance + 0.003)
        << x.transpose();
  }
  // the ball's centre (R + allowance above the face at 35) passes the wall's top edge (62, 40)
  // at R + allowance
  const double centre_over_edge = 35.0 + allowance + R - 40.0;
  const double x_limit = 62.0 - std::sqrt((R + allowance) * (R + allowance) - centre_over_edge * centre_over_edge);
  EXPECT_LE(xmax, x_limit + 1e-6);
  EXPECT_GT(xmax, x_limit - 1.01);  // as near as the point spacing allows
  // what the ball cannot reach: the last millimetres of the fin before the wall, up to its full
  // height (2 mm; the height is the distance to the template, so beside the wall the wall's)
  EXPECT_GT(plan->left_length_mm, 1.0);
  EXPECT_LT(plan->left_length_mm, 8.0);
  EXPECT_GT(plan->left_mm, 1.0);
  EXPECT_LE(plan->left_mm, 2.0 + 1e-6);
  EXPECT_GT(plan->left_at.x(), 55.0);
  // the whole region validates with the cell's clearance, leads and lifts included
  const auto traj = plan_part("p", {in}, settings);
  ASSERT_TRUE(traj) << traj.error().message;
}

// A fin on the casting's own face where that face waves 0.5 mm over 90 mm (the realistic form
// deviation: slopes up to 2 degrees, so 4 degrees off the line's normal where the line is fitted
// on the opposite slope). The ball `level` above the face along the normal comes nearer the
// sloping face than the level; the pass lifts it by what the slope explains and grinds the fin
// end to end, rather than taking the slope for a wall and leaving most of the fin.
TEST(StraightPlan, AFinOnAFaceSlopingOffTheLinesNormalIsGroundEndToEnd) {
  auto scene = make_scene();
  auto& in = scene.inputs[3];
  const auto wave = [](double x) { return 0.5 * std::sin(2.0 * std::numbers::pi * (x + 50.0) / 90.0); };
  in.form_deviation_mm = 0.5;
  in.form_offset_mm = [wave](const Vec3& p) { return wave(p.x()); };
  in.excess_points_part = testing::straight_fin(-95.0, -5.0, -70.0, 35.0, 2.0, 1.0, 0.5);
  for (auto& p : in.excess_points_part) p.z() += wave(p.x());
  const auto plan = plan_region(in, PlannerSettings{});
  ASSERT_TRUE(plan) << plan.error().message;
  EXPECT_EQ(plan->left_length_mm, 0.0);
  const double R = 6.0, allowance = in.region->allowance_mm;
  // the ball centre's distance from the casting's face (the wave at y = -70), sampled finely
  const auto from_face = [&](const Vec3& c) {
    double d = 1e9;
    for (double x = c.x() - 8.0; x <= c.x() + 8.0; x += 0.01) d = std::min(d, std::hypot(c.x() - x, c.z() - 35.0 - wave(x)));
    return d;
  };
  double xmin = 1e9, xmax = -1e9;
  std::size_t last_pass = 0;
  for (const auto& p : plan->points) {
    if (p.kind != MoveKind::grind) continue;
    const Transform T = p.T_base_tool.to_transform();
    xmin = std::min(xmin, T.translation().x()), xmax = std::max(xmax, T.translation().x());
    if (p.segment != plan->segments - 1) continue;
    ++last_pass;
    // the last pass keeps the allowance from the face, and no more than the back-off's tolerance
    // beyond it where the face slopes (a tool lifted over a wall would stand farther off)
    const double d = from_face(T.translation() + R * T.linear().col(2));
    EXPECT_GE(d, R + allowance - 0.005) << T.translation().transpose();
    EXPECT_LE(d, R + allowance + 0.02) << T.translation().transpose();
  }
  EXPECT_GT(last_pass, 90U);
  EXPECT_LT(xmin, -95.0 - R + 0.5);  // past both ends by the tool radius
  EXPECT_GT(xmax, -5.0 + R - 0.5);
}

RegionPlan line_plan(const std::string& name, double x) {
  RegionPlan p;
  p.region = name;
  p.segments = 1;
  for (double dx : {0.0, 10.0}) {
    TrajectoryPoint q;
    q.T_base_tool.position_mm = Vec3(x + dx, 0.0, 40.0);
    q.speed_mm_s = 10;
    q.spindle_rpm = 5000;
    p.points.push_back(q);
  }
  return p;
}

TEST(RegionOrder, ReducesTheAirMovesAgainstRecipeOrder) {
  const std::vector<RegionPlan> plans = {line_plan("a", 0), line_plan("b", 300), line_plan("c", 100),
                                         line_plan("d", 200)};
  const std::vector<std::size_t> recipe_order = {0, 1, 2, 3};
  const auto order = order_regions(plans);
  ASSERT_EQ(order.size(), 4U);
  const double before = air_move_length_mm(plans, recipe_order);
  const double after = air_move_length_mm(plans, order);
  EXPECT_NEAR(before, 290 + 210 + 90, 1e-9);
  EXPECT_NEAR(after, 3 * 90.0, 1e-9);  // a, c, d, b
  EXPECT_LT(after, before);
  const Trajectory t = assemble("p", plans, order, PlannerSettings{});
  ASSERT_EQ(t.segment_regions.size(), 4U);
  EXPECT_EQ(t.segment_regions[0], "a");
  EXPECT_EQ(t.segment_regions[1], "c");
  EXPECT_EQ(t.points.front().kind, MoveKind::approach);
  EXPECT_NEAR(t.points.front().T_base_tool.position_mm.z(), 40.0 + 100.0, 1e-9);  // safe height
  EXPECT_EQ(t.points.back().kind, MoveKind::retract);
}

TEST(Frames, PosesFollowThePartPlacementIntoTheBaseFrame) {
  Transform T_base_part = Transform::Identity();
  T_base_part.linear() = Eigen::AngleAxisd(deg_to_rad(3.0), Vec3::UnitZ()).toRotationMatrix();
  T_base_part.translation() = Vec3(300.0, -120.0, 20.0);
  auto nominal = make_scene();
  auto placed = make_scene(0.5, T_base_part);
  const auto a = plan_part("p", nominal.inputs, PlannerSettings{});
  const auto b = plan_part("p", placed.inputs, PlannerSettings{});
  ASSERT_TRUE(a) << a.error().message;
  ASSERT_TRUE(b) << b.error().message;
  ASSERT_EQ(a->points.size(), b->points.size());
  EXPECT_EQ(a->segment_regions, b->segment_regions);
  for (std::size_t i = 0; i < a->points.size(); ++i) {
    const Transform expected = T_base_part * a->points[i].T_base_tool.to_transform();
    const Transform got = b->points[i].T_base_tool.to_transform();
    EXPECT_LT((expected.translation() - got.translation()).norm(), 1e-6) << "point " << i;
    EXPECT_LT(rotation_angle_rad(expected.inverse() * got), 1e-9) << "point " << i;
  }
}

TEST(Frames, FlangeSitsTcpLengthUpTheToolAxis) {
  config::Tool tool;
  tool.tcp_mm = {0.0, 0.0, 180.0};
  Transform T_base_tool = Transform::Identity();
  T_base_tool.linear() = Eigen::AngleAxisd(deg_to_rad(45.0), Vec3::UnitY()).toRotationMatrix();
  T_base_tool.translation() = Vec3(10, 20, 30);
  const Transform T_base_flange = flange_pose(T_base_tool, tool);
  const Vec3 axis = T_base_tool.linear().col(2);
  EXPECT_LT((T_base_flange.translation() - (Vec3(10, 20, 30) + 180.0 * axis)).norm(), 1e-9);
  EXPECT_LT((T_base_flange.linear().col(2) + axis).norm(), 1e-12);  // flange z points down the tool
}

TEST(Settings, ComeFromTheCellSafetySection) {
  config::SafetySection safety;
  safety.workspace_min_mm = {-500, -400, -10};
  safety.workspace_max_mm = {500, 400, 700};
  safety.tool_axis_cone_deg = 30.0;
  safety.max_speed_mm_s = 80.0;
  safety.max_spindle_rpm = 10000.0;
  safety.safe_height_mm = 60.0;
  const auto s = PlannerSettings::from(safety);
  EXPECT_EQ(s.workspace_min_mm, Vec3(-500, -400, -10));
  EXPECT_EQ(s.workspace_max_mm, Vec3(500, 400, 700));
  EXPECT_NEAR(s.tool_axis_cone_rad, deg_to_rad(30.0), 1e-12);
  EXPECT_DOUBLE_EQ(s.max_speed_mm_s, 80.0);
  EXPECT_DOUBLE_EQ(s.air_speed_mm_s, 80.0);  // clamped to the limit
  EXPECT_DOUBLE_EQ(s.max_spindle_rpm, 10000.0);
  EXPECT_DOUBLE_EQ(s.safe_height_mm, 60.0);
}

}  // namespace
}  // namespace fettle::planning
