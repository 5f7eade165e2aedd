// Grinding and evaluation: a known tool sweep removes what it should, cutting into the
// body is a gouge, bad trajectories are rejected untouched, evaluation counts.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <optional>
#include <unistd.h>
#include <vector>

#include "fettle/core/error.hpp"
#include "sim_test_util.hpp"

using namespace fettle::sim;  // NOLINT
using ::testing::HasSubstr;
using sim_test::pi;

namespace {

double riser_volume(const Casting& c) {
  for (const auto& r : c.material())
    if (r.name == "riser") return r.volume_mm3;
  return -1;
}

/// A vertical cylinder tool (axis +z, i.e. pointing down at the part) held at part-frame point p.
fettle::Trajectory plunge(const Casting& c, const fettle::Vec3& p_part) {
  fettle::Trajectory t;
  fettle::TrajectoryPoint q;
  q.T_base_tool.position_mm = c.T_base_part() * p_part;
  q.T_base_tool.orientation = fettle::Quat(c.T_base_part().linear());
  q.speed_mm_s = 10;
  q.spindle_rpm = 8000;
  t.points = {q, q};
  return t;
}

GrindOptions disc() {
  GrindOptions o;
  o.tool.shape = fettle::config::ToolShape::cylinder;
  o.tool.diameter_mm = 50.0;
  o.tool.length_mm = 30.0;
  o.path_noise_mm = 0.0;
  return o;
}

TEST(SimGrind, CylinderAboveTheFaceLeavesExactlyTheStubBelowIt) {
  const auto recipe = sim_test::pump_body();
  Casting c = Casting::make(recipe, 1, CastingOptions{.vary = false});
  const auto& f = recipe.geometry.risers.at(0);
  const double d = 0.5 * (f.diameter_mm.min + f.diameter_mm.max);
  const double face = c.golden_top_z_mm(f.center_mm[0], f.center_mm[1]);
  const double before = riser_volume(c);
  auto res = grind(c, plunge(c, {f.center_mm[0], f.center_mm[1], face + 2.0}), disc());
  ASSERT_TRUE(res.ok()) << res.error().message;
  const double expected = pi() * d * d / 4 * 2.0;
  EXPECT_NEAR(riser_volume(c), expected, 0.02 * expected);
  EXPECT_NEAR(res->removed_mm3(), before - expected, 0.02 * before);
  EXPECT_TRUE(res->gouges.empty());
  EXPECT_NEAR(c.surface_z_mm(f.center_mm[0], f.center_mm[1]), face + 2.0, 0.02);
}

/// A ball-12 pass along the straight flash `clearance_mm` above the golden face (the TCP at
/// the ball's tip), ground with `o` (tool set here, no path noise).
fettle::Result<GrindResult> straight_pass(Casting& c, GrindOptions o, double* length_mm = nullptr, double* face_mm = nullptr,
                                          double clearance_mm = 0.0) {
  const auto recipe = sim_test::pump_body();
  const auto& f = recipe.geometry.straight_flashes.at(0);
  const double L = 0.5 * (f.length_mm.min + f.length_mm.max);
  const double face = c.golden_top_z_mm(f.start_mm[0], f.start_mm[1]);
  o.tool = find_tool(recipe, "ball-12");
  o.path_noise_mm = 0.0;
  fettle::Trajectory t;
  for (double s : {-8.0, L + 8.0}) {
    fettle::TrajectoryPoint q;
    q.T_base_tool.position_mm = c.T_base_part() * fettle::Vec3(f.start_mm[0] + s, f.start_mm[1], face + clearance_mm);
    q.speed_mm_s = 20;
    q.spindle_rpm = 9000;
    t.points.push_back(q);
  }
  if (length_mm != nullptr) *length_mm = L + 16.0;
  if (face_mm != nullptr) *face_mm = face;
  return grind(c, t, o);
}

TEST(SimGrind, BallSweepAlongTheStraightFlashRemovesItAndRecordsAGougeWhenTooLow) {
  const auto recipe = sim_test::pump_body();
  const auto& f = recipe.geometry.straight_flashes.at(0);
  const double L = 0.5 * (f.length_mm.min + f.length_mm.max);
  for (double clearance : {0.0, -0.3}) {
    Casting c = Casting::make(recipe, 1, CastingOptions{.vary = false});
    double face = 0;
    auto res = straight_pass(c, GrindOptions{}, nullptr, &face, clearance);
    ASSERT_TRUE(res.ok()) << res.error().message;
    double left = 0;
    for (const auto& r : res->after)
      if (r.name == f.region) left = r.volume_mm3;
    EXPECT_LT(left, 0.01 * res->removed_mm3()) << "clearance " << clearance;
    if (clearance == 0.0) {
      EXPECT_TRUE(res->gouges.empty());
    } else {
      ASSERT_EQ(res->gouges.size(), 1u);
      EXPECT_NEAR(res->gouges[0].depth_mm, 0.3, 0.01);
      EXPECT_NEAR(res->gouges[0].position_mm.z(), face - 0.3, 0.01);
      EXPECT_NEAR(c.surface_z_mm(f.start_mm[0] + L / 2, f.start_mm[1]), face - 0.3, 0.02);
    }
  }
}

TEST(SimGrind, ACalibrationBiasCutsThatDeepAndOnlyCutsBeyondTheThresholdAreGouges) {
  const auto recipe = sim_test::pump_body();
  // the bias is in the base frame; the unvaried casting sits level, so base z is part z
  for (const double bias : {-0.01, -0.03, -0.1}) {
    Casting c = Casting::make(recipe, 1, CastingOptions{.vary = false});
    GrindOptions o;
    o.path_bias_mm = fettle::Vec3(0.0, 0.0, bias);
    double face = 0;
    auto res = straight_pass(c, o, nullptr, &face);
    ASSERT_TRUE(res.ok()) << res.error().message;
    if (-bias <= o.gouge_threshold_mm) {
      EXPECT_TRUE(res->gouges.empty()) << "bias " << bias << " is within the " << o.gouge_threshold_mm << " mm threshold";
    } else {
      ASSERT_EQ(res->gouges.size(), 1u) << "bias " << bias;
      EXPECT_NEAR(res->gouges[0].depth_mm, -bias, 0.005) << "bias " << bias;
      EXPECT_NEAR(res->gouges[0].position_mm.z(), face + bias, 0.01) << "bias " << bias;
    }
  }
  // and a lateral bias moves the cut sideways: the groove's centre follows it
  Casting c = Casting::make(recipe, 1, CastingOptions{.vary = false});
  GrindOptions o;
  o.path_bias_mm = fettle::Vec3(0.0, 0.0, -0.2);
  auto centred = straight_pass(c, o);
  ASSERT_TRUE(centred.ok());
  Casting d = Casting::make(recipe, 1, CastingOptions{.vary = false});
  o.path_bias_mm = fettle::Vec3(0.0, 1.0, -0.2);
  auto shifted = straight_pass(d, o);
  ASSERT_TRUE(shifted.ok());
  ASSERT_EQ(centred->gouges.size(), 1u);
  ASSERT_EQ(shifted->gouges.size(), 1u);
  const auto& f = recipe.geometry.straight_flashes.at(0);
  const fettle::Vec3 part_c = c.T_base_part().inverse() * centred->gouges[0].position_mm;
  const fettle::Vec3 part_s = d.T_base_part().inverse() * shifted->gouges[0].position_mm;
  EXPECT_NEAR(part_c.y(), f.start_mm[1], 0.3);
  EXPECT_NEAR(part_s.y() - part_c.y(), 1.0, 0.3);
}

// A casting whose body stands over the nominal (its form deviation): a flat tool held 0.05 mm
// over the nominal face cuts into the casting's own body by the rest, and is no gouge against
// the nominal; held 0.05 mm over its own face it cuts neither.
TEST(SimGrind, ACutIntoTheCastingsOwnBodyIsMeasuredApartFromTheNominal) {
  auto recipe = sim_test::pump_body();
  recipe.geometry.variation.form_deviation_mm = 0.5;
  // a place on the pad's top (nominal z = 45) clear of the riser where the body stands 0.2 mm
  // or more over the nominal (a 6 mm flat tool there)
  std::optional<Casting> found;
  fettle::Vec3 at = fettle::Vec3::Zero();
  for (std::uint64_t seed = 1; seed <= 40 && !found; ++seed) {
    Casting c = Casting::make(recipe, seed);
    for (const double x : {-104.0, -61.0})
      for (const double y : {16.0, 79.0})
        if (!found && c.form_deviation_mm(x, y) >= 0.2) found = c, at = fettle::Vec3(x, y, 45.0);
  }
  ASSERT_TRUE(found) << "no casting of 40 stands 0.2 mm over the nominal at a corner of the pad";
  double form = -1.0;  // the highest the body stands under the tool's 3 mm radius
  for (double dx = -3.0; dx <= 3.0; dx += 0.1)
    for (double dy = -3.0; dy <= 3.0; dy += 0.1)
      if (dx * dx + dy * dy <= 9.0) form = std::max(form, found->form_deviation_mm(at.x() + dx, at.y() + dy));
  GrindOptions o = disc();
  o.tool.diameter_mm = 6.0;
  Casting nominal_face = *found;
  auto low = grind(nominal_face, plunge(nominal_face, at + fettle::Vec3(0.0, 0.0, 0.05)), o);
  ASSERT_TRUE(low.ok()) << low.error().message;
  EXPECT_TRUE(low->gouges.empty()) << "above the nominal";
  EXPECT_NEAR(low->deepest_body_cut.depth_mm, form - 0.05, 0.01);
  Casting own_face = *found;
  auto high = grind(own_face, plunge(own_face, at + fettle::Vec3(0.0, 0.0, form + 0.05)), o);
  ASSERT_TRUE(high.ok()) << high.error().message;
  EXPECT_TRUE(high->gouges.empty());
  EXPECT_EQ(high->deepest_body_cut.depth_mm, 0.0);
}

// A riser is cast with the body: it stands on the casting's own face, form deviation and all.
// Where the form deviation lowers the face 0.2 mm or more under the riser, a wheel held at the
// nominal face leaves a stub down to the own face (on the nominal, the riser floated over an air
// gap and the wheel took all of it: the cut looked deeper than the wheel went).
TEST(SimGrind, ARiserStandsOnTheCastingsOwnFace) {
  auto recipe = sim_test::pump_body();
  recipe.geometry.variation.form_deviation_mm = 0.5;
  const auto& f = recipe.geometry.risers.at(0);
  const double x = f.center_mm[0], y = f.center_mm[1];
  std::optional<Casting> found;
  for (std::uint64_t seed = 1; seed <= 60 && !found; ++seed) {
    Casting c = Casting::make(recipe, seed);
    if (c.form_deviation_mm(x, y) <= -0.2) found = c;
  }
  ASSERT_TRUE(found) << "no casting of 60 has its pad 0.2 mm under the nominal at the riser";
  Casting& c = *found;
  const double nominal = c.golden_top_z_mm(x, y);
  ASSERT_GT(c.surface_z_mm(x, y), nominal + 2.0) << "the riser stands there";
  auto res = grind(c, plunge(c, {x, y, nominal}), disc());
  ASSERT_TRUE(res.ok()) << res.error().message;
  EXPECT_NEAR(c.surface_z_mm(x, y), nominal, 0.02) << "the stub between the own face and the wheel is left";
  EXPECT_GT(riser_volume(c), 0.0);
  EXPECT_EQ(res->deepest_body_cut.depth_mm, 0.0);
}

// A disc's rim, tilted, dips 0.1 mm into the flat pad face under the riser at a point between
// two of the 24 rim samples (the tool turned 7.5 deg about its axis): the sampled rim alone sags
// 0.107 mm there and saw no gouge; the gouge depth must be the rim's.
TEST(SimGrind, ATiltedDiscsRimBetweenSamplesGougesAsDeepAsItCuts) {
  const auto recipe = sim_test::pump_body();
  const auto& f = recipe.geometry.risers.at(0);
  for (const double dip : {0.1, 0.01}) {
    Casting c = Casting::make(recipe, 1, CastingOptions{.vary = false});
    GrindOptions o = disc();  // 50 mm disc
    o.only_when_spindle_on = true;
    const double r = 0.5 * o.tool.diameter_mm;
    const fettle::Quat q_part_tool(Eigen::AngleAxisd(fettle::deg_to_rad(30.0), fettle::Vec3::UnitX()) *
                                   Eigen::AngleAxisd(fettle::deg_to_rad(7.5), fettle::Vec3::UnitZ()));
    // the rim's lowest point, tool frame: found finely
    fettle::Vec3 low = fettle::Vec3::Zero();
    for (int k = 0; k < 36000; ++k) {
      const double a = 2 * pi() * k / 36000;
      const fettle::Vec3 p = q_part_tool * fettle::Vec3(r * std::cos(a), r * std::sin(a), 0.0);
      if (p.z() < low.z()) low = p;
    }
    const double face = c.golden_top_z_mm(f.center_mm[0], f.center_mm[1]);
    for (double dx : {-2.0, 2.0})
      for (double dy : {-2.0, 2.0})
        ASSERT_NEAR(c.golden_top_z_mm(f.center_mm[0] + dx, f.center_mm[1] + dy), face, 1e-6) << "not flat around the riser";
    const fettle::Vec3 tcp_part = fettle::Vec3(f.center_mm[0], f.center_mm[1], face - dip) - low;
    fettle::Trajectory t;
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = c.T_base_part() * tcp_part;
    p.T_base_tool.orientation = fettle::Quat(c.T_base_part().linear()) * q_part_tool;
    p.speed_mm_s = 10;
    p.spindle_rpm = 0;  // no cutting: only the gouge check
    t.points = {p, p};
    auto res = grind(c, t, o);
    ASSERT_TRUE(res.ok()) << res.error().message;
    if (dip <= o.gouge_threshold_mm) {
      EXPECT_TRUE(res->gouges.empty()) << "dip " << dip;
    } else {
      ASSERT_EQ(res->gouges.size(), 1u) << "dip " << dip;
      EXPECT_NEAR(res->gouges[0].depth_mm, dip, 0.005);
      const fettle::Vec3 at = c.T_base_part().inverse() * res->gouges[0].position_mm;
      EXPECT_NEAR(at.x(), f.center_mm[0], 0.5);
      EXPECT_NEAR(at.y(), f.center_mm[1], 0.5);
    }
  }
}

// The executed path's noise: a ball dipping 0.2 mm into the flat pad face (by a bias) 400
// times, lifting 1 mm in between (one pose per point: interpolation coarser than the moves),
// spindle off (nothing cut, only the gouges measured): the gouge depths spread with the
// configured sigma about 0.2 mm.
TEST(SimGrind, PathNoiseHasTheConfiguredSigma) {
  const auto recipe = sim_test::pump_body();
  const auto& f = recipe.geometry.risers.at(0);
  Casting c = Casting::make(recipe, 1, CastingOptions{.vary = false});
  const double face = c.golden_top_z_mm(f.center_mm[0], f.center_mm[1]);
  constexpr int kDips = 400;
  fettle::Trajectory t;
  for (int k = 0; k < 2 * kDips; ++k) {
    fettle::TrajectoryPoint p;
    p.T_base_tool.position_mm = c.T_base_part() * fettle::Vec3(f.center_mm[0], f.center_mm[1], face + (k % 2 ? 1.0 : 0.0));
    p.speed_mm_s = 10;
    p.spindle_rpm = 0;
    t.points.push_back(p);
  }
  for (const double sigma : {0.02, 0.05}) {
    GrindOptions o;
    o.tool = find_tool(recipe, "ball-12");
    o.path_noise_mm = sigma;
    o.path_bias_mm = fettle::Vec3(0.0, 0.0, -0.2);
    o.interpolation_mm = 5.0;
    auto res = grind(c, t, o);
    ASSERT_TRUE(res.ok()) << res.error().message;
    ASSERT_EQ(res->poses, static_cast<std::size_t>(2 * kDips));
    ASSERT_EQ(res->gouges.size(), static_cast<std::size_t>(kDips)) << "one per dip";
    double mean = 0, var = 0;
    for (const auto& g : res->gouges) mean += g.depth_mm;
    mean /= kDips;
    for (const auto& g : res->gouges) var += (g.depth_mm - mean) * (g.depth_mm - mean);
    const double sd = std::sqrt(var / (kDips - 1));
    EXPECT_NEAR(mean, 0.2, 0.2 * sigma) << "sigma " << sigma;
    EXPECT_NEAR(sd, sigma, 0.15 * sigma) << "sigma " << sigma;
  }
}

// A wheel keeps the deepest of the noisy poses that sweep over a point: a ball pass commanded
// onto the face cuts below it along its whole length, by well over one sigma of the path noise
// and within the 3 sigma a robot states as its repeatability. So the planner's bound adds the
// repeatability to the systematic errors rather than in quadrature
// (Compensation.PlacementUncertaintyShrinksAlongWhatTheCellLearnedOnly).
TEST(SimGrind, PathNoiseDeepensTheCutOneSided) {
  const auto recipe = sim_test::pump_body();
  const auto& f = recipe.geometry.straight_flashes.at(0);
  constexpr double kSigma = 0.05;
  Casting c = Casting::make(recipe, 1, CastingOptions{.vary = false});
  const double face = c.golden_top_z_mm(f.start_mm[0], f.start_mm[1]);
  GrindOptions o;
  o.tool = find_tool(recipe, "ball-12");
  o.path_noise_mm = kSigma;
  o.gouge_threshold_mm = 1.0;  // the cut's depth is read from the surface below
  fettle::Trajectory t;
  for (const double s : {-8.0, 48.0}) {
    fettle::TrajectoryPoint q;
    q.T_base_tool.position_mm = c.T_base_part() * fettle::Vec3(f.start_mm[0] + s, f.start_mm[1], face);
    q.speed_mm_s = 20;
    q.spindle_rpm = 9000;
    t.points.push_back(q);
  }
  ASSERT_TRUE(grind(c, t, o).ok());
  std::vector<double> depth;
  for (double s = 0.0; s <= 40.0; s += 0.5) depth.push_back(face - c.surface_z_mm(f.start_mm[0] + s, f.start_mm[1]));
  std::sort(depth.begin(), depth.end());
  EXPECT_GT(depth.front(), 0.0) << "no point of the groove is left at the commanded depth";
  EXPECT_GT(depth[depth.size() / 2], 1.0 * kSigma);
  EXPECT_LT(depth[depth.size() / 2], 3.0 * kSigma);
}

TEST(SimGrind, PosesAreInterpolatedAtMostTheConfiguredSpacingApart) {
  const auto recipe = sim_test::pump_body();
  for (const double step : {0.1, 0.05}) {
    Casting c = Casting::make(recipe, 1, CastingOptions{.vary = false});
    GrindOptions o;
    o.interpolation_mm = step;
    double length = 0;
    auto res = straight_pass(c, o, &length);
    ASSERT_TRUE(res.ok()) << res.error().message;
    EXPECT_EQ(res->poses, 1u + static_cast<std::size_t>(std::ceil(length / step))) << "step " << step;
  }
  // A turn in place: the tool's far end (hypot(radius, length) from the TCP) moves at most the
  // spacing between poses.
  Casting c = Casting::make(recipe, 1, CastingOptions{.vary = false});
  GrindOptions o = disc();
  fettle::Trajectory t = plunge(c, {0.0, 0.0, 200.0});  // in the air
  t.points[1].T_base_tool.orientation = t.points[0].T_base_tool.orientation *
                                        fettle::Quat(Eigen::AngleAxisd(0.5, fettle::Vec3::UnitX()));
  auto res = grind(c, t, o);
  ASSERT_TRUE(res.ok()) << res.error().message;
  const double reach = std::hypot(0.5 * o.tool.diameter_mm, o.tool.length_mm);
  EXPECT_EQ(res->poses, 1u + static_cast<std::size_t>(std::ceil(0.5 * reach / o.interpolation_mm)));
}

TEST(SimGrind, PathNoiseIsSeededAndDeterministic) {
  const auto recipe = sim_test::pump_body();
  const auto& f = recipe.geometry.risers.at(0);
  auto run = [&](std::uint64_t seed) {
    Casting c = Casting::make(recipe, 3);
    const double face = c.golden_top_z_mm(f.center_mm[0], f.center_mm[1]);
    auto o = disc();
    o.path_noise_mm = 0.05;
    o.noise_seed = seed;
    auto t = plunge(c, {f.center_mm[0] - 5, f.center_mm[1], face + 0.02});
    t.points[1].T_base_tool.position_mm += fettle::Vec3(10, 0, 0);
    return grind(c, t, o).value();
  };
  const auto a = run(1), b = run(1), d = run(2);
  EXPECT_EQ(a.removed_mm3(), b.removed_mm3());
  EXPECT_EQ(a.gouges.size(), b.gouges.size());
  EXPECT_NE(a.max_gouge_depth_mm(), d.max_gouge_depth_mm());
}

// The grinder visits only the cells a pose can reach (tile bounds, the tool's exact lowest point
// and footprint, a cheap inside test before the exact one). A wrong bound would leave material or
// body standing inside the tool: cylinders, cones and a ball at many axes (tilted, vertical,
// horizontal, pointing up), as single poses (no neighbouring pose hides a skipped cell) and as
// sweeps along x and y, over the riser, the face and the ring flash, must leave exactly what the
// reference mode (every cell of each pose's bounding box tested) leaves.
TEST(SimGrind, ToolsAtAnyAxisCutTheSameAsTheExhaustiveReference) {
  using fettle::Vec3;
  using Shape = fettle::config::ToolShape;
  const auto recipe = sim_test::pump_body();
  const auto& riser = recipe.geometry.risers.at(0);
  const auto& ring = recipe.geometry.ring_flashes.at(0);
  const Casting original = Casting::make(recipe, 1, CastingOptions{.vary = false});
  const Vec3 rc(riser.center_mm[0], riser.center_mm[1], 0);
  const double face = original.golden_top_z_mm(rc.x(), rc.y());  // the face the riser stands on
  const double rr = 0.5 * riser.diameter_mm.min;  // inside the riser's edge on every casting
  const Vec3 ring_side(ring.cylinder.center_mm[0] + ring.cylinder.radius_mm + 0.5, ring.cylinder.center_mm[1], ring.parting_z_mm);
  struct Case {
    const char* what;
    Shape shape;
    double diameter_mm, length_mm, cone_deg;
    Vec3 axis, start, end;  // tip (ball: lowest point) path, part frame
    bool cuts_body;
  };
  const Vec3 x30(30, 0, 0), y30(0, 30, 0), up(0, 0, 1);
  const Case cases[] = {
      {"chamfer disc at 45 deg swept along x over the riser", Shape::cylinder, 40, 6, 0, Vec3(1, 0, 1),
       rc - x30 + (face + 15) * up, rc + x30 + (face + 15) * up, false},
      {"cup wheel tilted across its path, along x", Shape::cylinder, 16, 10, 0, Vec3(0, 1, 2),
       rc - x30 + (face + 3) * up, rc + x30 + (face + 3) * up, true},
      {"cone tilted both ways, along y", Shape::cone, 16, 12, 30, Vec3(0.3, -0.4, 1),
       rc - y30 + (face - 0.3) * up, rc + y30 + (face - 0.3) * up, true},
      {"ball along y", Shape::ball, 12, 0, 0, up, rc - y30 + (face - 0.4) * up, rc + y30 + (face - 0.4) * up, true},
      {"vertical cylinder, one pose on the riser's edge", Shape::cylinder, 16, 10, 0, up,
       rc + Vec3(rr, 0, face - 0.3), rc + Vec3(rr, 0, face - 0.3), true},
      {"vertical cone, one pose beside the riser", Shape::cone, 16, 12, 30, up,
       rc + Vec3(0, -rr - 6, face - 3), rc + Vec3(0, -rr - 6, face - 3), true},
      {"tilted cone, one pose on the riser", Shape::cone, 20, 12, 40, Vec3(-1, 1, 1),
       rc + Vec3(0, 0, face + 1.5), rc + Vec3(0, 0, face + 1.5), false},
      {"cylinder pointing up (axis z < 0), one pose on the riser's edge", Shape::cylinder, 16, 6, 0, Vec3(0.3, 0, -1),
       rc + Vec3(-rr, 0, face + 6), rc + Vec3(-rr, 0, face + 6), true},
      {"horizontal cylinder, one pose on the ring flash", Shape::cylinder, 16, 10, 0, Vec3(1, 0, 0), ring_side, ring_side, false},
      {"horizontal cylinder along the ring flash (y)", Shape::cylinder, 16, 10, 0, Vec3(1, 0, 0),
       ring_side - Vec3(0, 8, 0), ring_side + Vec3(0, 8, 0), false},
  };
  for (const auto& k : cases) {
    SCOPED_TRACE(k.what);
    GrindOptions o;
    o.tool.shape = k.shape;
    o.tool.diameter_mm = k.diameter_mm;
    o.tool.length_mm = k.length_mm;
    o.tool.cone_angle_deg = k.cone_deg;
    o.path_noise_mm = 0.0;
    o.interpolation_mm = 0.25;  // fewer poses: the reference mode is slow
    const Vec3 a = k.axis.normalized();
    const fettle::Quat q_base_tool(original.T_base_part().linear() * fettle::Quat::FromTwoVectors(Vec3::UnitZ(), a).toRotationMatrix());
    fettle::Trajectory t;
    for (const Vec3& p_part : {k.start, k.end}) {
      fettle::TrajectoryPoint p;
      p.T_base_tool.position_mm = original.T_base_part() * p_part;
      p.T_base_tool.orientation = q_base_tool;
      p.speed_mm_s = 20;
      p.spindle_rpm = 9000;
      t.points.push_back(p);
    }
    Casting fast = original, reference = original;
    auto res = grind(fast, t, o);
    o.exhaustive = true;
    auto ref = grind(reference, t, o);
    ASSERT_TRUE(res.ok()) << res.error().message;
    ASSERT_TRUE(ref.ok()) << ref.error().message;
    EXPECT_GT(ref->removed_mm3(), 1.0) << "the case must cut material";
    ASSERT_EQ(res->after.size(), ref->after.size());
    for (std::size_t i = 0; i < ref->after.size(); ++i) {
      EXPECT_EQ(res->after[i].volume_mm3, ref->after[i].volume_mm3) << ref->after[i].name;
      EXPECT_EQ(res->after[i].max_height_mm, ref->after[i].max_height_mm) << ref->after[i].name;
    }
    // The surface (body and material tops) everywhere the tool could reach.
    const double reach = 0.5 * k.diameter_mm + k.length_mm + 1;
    int lowered = 0, body_lowered = 0, differ = 0;
    for (double sy = std::min(k.start.y(), k.end.y()) - reach; sy <= std::max(k.start.y(), k.end.y()) + reach; sy += 0.1)
      for (double sx = std::min(k.start.x(), k.end.x()) - reach; sx <= std::max(k.start.x(), k.end.x()) + reach; sx += 0.1) {
        const double zf = fast.surface_z_mm(sx, sy), zr = reference.surface_z_mm(sx, sy), z = original.surface_z_mm(sx, sy);
        if (zr < z - 0.05) {
          ++lowered;
          // no material there (the casting does not vary: its body is the golden one)
          if (std::abs(z - original.golden_top_z_mm(sx, sy)) < 1e-3) ++body_lowered;
        }
        if (!(zf == zr || (std::isnan(zf) && std::isnan(zr))) && differ++ < 5)
          ADD_FAILURE() << "at x " << sx << ", y " << sy << ": " << zf << " mm, the reference " << zr << " mm";
      }
    EXPECT_EQ(differ, 0);
    EXPECT_GT(lowered, 100);
    if (k.cuts_body) {
      EXPECT_GT(body_lowered, 100) << "the case must cut the body";
    }
  }
}

TEST(SimGrind, TrajectoriesWithNaNOrOutsideTheCellAreRejectedAndNotExecuted) {
  const auto recipe = sim_test::pump_body();
  Casting c = Casting::make(recipe, 1);
  const double before = riser_volume(c);
  const auto& f = recipe.geometry.risers.at(0);
  auto t = plunge(c, {f.center_mm[0], f.center_mm[1], 40.0});
  t.points[1].T_base_tool.position_mm.z() = std::nan("");
  auto r = grind(c, t, disc());
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(r.error().message, HasSubstr("point 1"));
  EXPECT_THAT(r.error().message, HasSubstr("NaN"));
  t = plunge(c, {f.center_mm[0], f.center_mm[1], 40.0});
  t.points[0].T_base_tool.position_mm.x() = 5000.0;
  r = grind(c, t, disc());
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(r.error().message, HasSubstr("outside the cell"));
  EXPECT_EQ(riser_volume(c), before);
}

TEST(SimGrind, TrajectoryFilesRoundTripAndBadFilesNameTheLine) {
  const auto dir = std::filesystem::temp_directory_path() / ("fettle-sim-traj-" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  const auto recipe = sim_test::pump_body();
  Casting c = Casting::make(recipe, 1);
  auto t = plunge(c, {0, 0, 80});
  t.segment_regions = {"riser"};
  ASSERT_TRUE(write_trajectory_json(dir / "t.json", t).ok());
  const auto back = read_trajectory(dir / "t.json");
  ASSERT_EQ(back.points.size(), 2u);
  EXPECT_EQ(back.segment_regions, t.segment_regions);
  EXPECT_TRUE(back.points[1].T_base_tool.position_mm.isApprox(t.points[1].T_base_tool.position_mm));
  std::ofstream(dir / "t.csv") << "x,y,z,qw,qx,qy,qz,speed_mm_s,spindle_rpm,segment\n"
                                  "0,0,100,1,0,0,0,10,8000,0\n"
                                  "0,0,nan,1,0,0,0,10,8000,0\n";
  const auto csv = read_trajectory(dir / "t.csv");
  ASSERT_EQ(csv.points.size(), 2u);
  EXPECT_FALSE(validate_trajectory(csv, CellLimits{}).ok());
  std::ofstream(dir / "bad.csv") << "x,y,z,qw,qx,qy,qz,speed_mm_s,spindle_rpm,segment\n"
                                    "0,0,100,1,0,0,0,10,8000,0\n"
                                    "0,0,abc,1,0,0,0,10,8000,0\n";
  try {
    (void)read_trajectory(dir / "bad.csv");
    FAIL() << "accepted a non-number";
  } catch (const fettle::UserError& e) {
    EXPECT_THAT(e.what(), HasSubstr("bad.csv:3"));
  }
  std::filesystem::remove_all(dir);
}

TEST(SimEvaluate, CountsPointsOverEachThresholdInsideTheRoiOnly) {
  fettle::config::Region r;
  r.name = "box";
  r.roi_center_mm = {0, 0, 0};
  r.roi_size_mm = {10, 10, 10};
  const std::vector<Eigen::Vector3f> pts{{0, 0, 0.1f}, {0, 0, 0.35f}, {0, 0, 0.45f}, {0, 0, 0.6f}, {0, 0, 4.0f},
                                         {20, 0, 1.0f}};
  const auto e = evaluate_region(r, pts, [](const fettle::Vec3& p) { return p.z(); });
  EXPECT_EQ(e.roi_points, 5u);
  EXPECT_EQ(e.over_0_3, 4u);
  EXPECT_EQ(e.over_0_4, 3u);
  EXPECT_EQ(e.over_0_5, 2u);
  EXPECT_NEAR(e.max_residual_mm, 4.0, 1e-6);
}

TEST(SimEvaluate, TemplateComparisonSeesTheRiserBeforeGrindingAndNotAfterAPerfectGrind) {
  const auto recipe = sim_test::pump_body();
  Casting c = Casting::make(recipe, 5);
  auto cfg = sim_test::small_scanner();
  cfg.noise.enabled = false;
  const Scanner scanner(cfg);
  const auto before = evaluate_against_template(recipe, {scanner.capture(c, 0.0)}, c);
  c.remove_all_material();
  const auto after = evaluate_against_template(recipe, {scanner.capture(c, 0.0)}, c);
  ASSERT_EQ(before.regions.size(), recipe.regions.size());
  for (std::size_t i = 0; i < before.regions.size(); ++i) {
    EXPECT_GT(before.regions[i].roi_points, 100u) << before.regions[i].name;
    EXPECT_GT(before.regions[i].over_0_5, 10u) << before.regions[i].name;
    EXPECT_LT(after.regions[i].over_0_3, before.regions[i].over_0_3 / 10 + 5) << after.regions[i].name;
  }
  EXPECT_THAT(format_table({before}), HasSubstr("riser"));
}

// The paper's second comparison: one ground casting's scan against another ground casting of
// the batch. Both ground perfectly, they differ only by their form deviation (+-0.2 mm each):
// nothing over 0.5 mm. Against a reference that still carries its riser, the riser's stub is
// over 0.5 mm; against itself, nothing over 0.3 mm.
TEST(SimEvaluate, BatchConsistencyComparesAGroundCastingWithAnother) {
  const auto recipe = sim_test::pump_body();
  Casting a = Casting::make(recipe, 5), b = Casting::make(recipe, 9);
  Casting b_unground = Casting::make(recipe, 9);
  a.remove_all_material();
  b.remove_all_material();
  auto cfg = sim_test::small_scanner();
  cfg.noise.enabled = false;
  const auto scan_a = std::vector<Capture>{Scanner(cfg).capture(a, 0.0)};
  const auto batch = evaluate_against_part(recipe, scan_a, b);
  const auto self = evaluate_against_part(recipe, scan_a, a);
  const auto unground = evaluate_against_part(recipe, scan_a, b_unground);
  ASSERT_EQ(batch.regions.size(), recipe.regions.size());
  for (std::size_t i = 0; i < batch.regions.size(); ++i) {
    const auto& r = batch.regions[i];
    EXPECT_GT(r.roi_points, 20u) << r.name;  // the flange's ring: a few dozen, its wall is vertical
    EXPECT_LE(r.over_0_5, r.roi_points / 200) << r.name << ": two ground castings differ only by their form";
    EXPECT_LE(self.regions[i].over_0_3, self.regions[i].roi_points / 200) << r.name << " against itself";
    if (r.name == "riser") {
      // the stub fills about a tenth of its ROI (which takes the face around it)
      EXPECT_GT(unground.regions[i].over_0_5, unground.regions[i].roi_points / 20) << "the reference's riser is still there";
      EXPECT_GT(unground.regions[i].over_0_5, 10 * (r.over_0_5 + 10));
    }
  }
  EXPECT_THAT(format_table({batch}), HasSubstr("riser"));
}

}  // namespace
