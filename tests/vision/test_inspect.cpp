// The vision stage on a synthetic casting with known placement and known excess material:
// per-region poses, excess volume, template cache, multi-view fusion, failures.
#include <gtest/gtest.h>

#include <chrono>
#include <unistd.h>

#include <numbers>
#include <random>

#include "fettle/vision/excess.hpp"
#include "fettle/vision/inspect.hpp"
#include "fettle/vision/multiview.hpp"
#include "fettle/vision/preprocess.hpp"
#include "test_support.hpp"
#include "../support/draws.hpp"

using namespace fettle::vision;
using fettle::Transform;
using fettle::Vec3;

namespace {

constexpr double kRiserRadius = 8.0;
constexpr double kRiserHeight = 10.0;
const Eigen::Vector2f kRiserAt(-30.0f, -15.0f);

/// A block 120 x 80 x 40 with an off-centre boss (so its pose is unique), sampled on the
/// surfaces a camera above sees (top faces and walls), normals outward. `riser` adds a
/// cylinder of excess material on the top face. `random` samples at random positions
/// (a scan) instead of on a grid (a template).
Cloud casting(double spacing, bool riser, std::mt19937_64* random) {
  Cloud c;
  auto add = [&](const Eigen::Vector3f& p, const Eigen::Vector3f& n) {
    c.points.push_back(p);
    c.normals.push_back(n);
  };
  auto in_boss = [](float x, float y) { return x >= 10 && x <= 40 && y >= 0 && y <= 25; };
  auto in_riser = [&](float x, float y) { return riser && (Eigen::Vector2f(x, y) - kRiserAt).norm() <= kRiserRadius; };
  // Samples a rectangle [a0,a1] x [b0,b1] mapped by f(a, b).
  auto patch = [&](float a0, float a1, float b0, float b1, auto&& f) {
    const double area = static_cast<double>((a1 - a0) * (b1 - b0));
    if (random != nullptr) {
      std::uniform_real_distribution<float> ua(a0, a1);
      std::uniform_real_distribution<float> ub(b0, b1);
      const auto n = static_cast<std::size_t>(area / (spacing * spacing));
      for (std::size_t i = 0; i < n; ++i) {
        const float b = ub(*random);  // sequenced as gcc drew them (tests/support/draws.hpp)
        const float a = ua(*random);
        f(a, b);
      }
    } else {
      const auto s = static_cast<float>(spacing);
      for (float a = a0; a <= a1; a += s)
        for (float b = b0; b <= b1; b += s) f(a, b);
    }
  };
  const Eigen::Vector3f up = Eigen::Vector3f::UnitZ();
  patch(-60, 60, -40, 40, [&](float x, float y) {
    if (!in_boss(x, y) && !in_riser(x, y)) add({x, y, 40}, up);
  });
  patch(10, 40, 0, 25, [&](float x, float y) { add({x, y, 55}, up); });
  patch(-60, 60, 0, 40, [&](float x, float z) { add({x, -40, z}, -Eigen::Vector3f::UnitY()); });
  patch(-60, 60, 0, 40, [&](float x, float z) { add({x, 40, z}, Eigen::Vector3f::UnitY()); });
  patch(-40, 40, 0, 40, [&](float y, float z) { add({-60, y, z}, -Eigen::Vector3f::UnitX()); });
  patch(-40, 40, 0, 40, [&](float y, float z) { add({60, y, z}, Eigen::Vector3f::UnitX()); });
  patch(10, 40, 40, 55, [&](float x, float z) { add({x, 0, z}, -Eigen::Vector3f::UnitY()); });
  patch(10, 40, 40, 55, [&](float x, float z) { add({x, 25, z}, Eigen::Vector3f::UnitY()); });
  patch(0, 25, 40, 55, [&](float y, float z) { add({10, y, z}, -Eigen::Vector3f::UnitX()); });
  patch(0, 25, 40, 55, [&](float y, float z) { add({40, y, z}, Eigen::Vector3f::UnitX()); });
  if (riser) {
    const auto r = static_cast<float>(kRiserRadius);
    patch(-r, r, -r, r, [&](float x, float y) {
      if (x * x + y * y <= r * r) add({kRiserAt.x() + x, kRiserAt.y() + y, 40.0f + static_cast<float>(kRiserHeight)}, up);
    });
    const auto circumference = static_cast<float>(2.0 * std::numbers::pi * kRiserRadius);
    patch(0, circumference, 40, 40 + static_cast<float>(kRiserHeight), [&](float s, float z) {
      const float a = s / r;
      const Eigen::Vector3f n(std::cos(a), std::sin(a), 0.0f);
      add({kRiserAt.x() + r * n.x(), kRiserAt.y() + r * n.y(), z}, n);
    });
  }
  return c;
}

fettle::config::PartRecipe recipe() {
  fettle::config::PartRecipe r;
  r.id = "synthetic-block";
  r.template_source.voxel_mm = 0.5;
  r.vision.crop_min_mm = {-150, -150, -20};
  r.vision.crop_max_mm = {150, 150, 150};
  r.vision.cache = false;
  fettle::config::Region riser;
  riser.name = "riser";
  riser.roi_center_mm = {-30, -15, 50};
  riser.roi_size_mm = {36, 36, 30};
  fettle::config::Region boss;
  boss.name = "boss";
  boss.roi_center_mm = {25, 12, 45};
  boss.roi_size_mm = {50, 45, 30};
  r.regions = {riser, boss};
  return r;
}

/// A scan of the casting placed at T_fixture_part on a table (z = 0), with noise.
Cloud scan(const Transform& T_fixture_part, std::mt19937_64& rng, double sigma) {
  Cloud part = transformed(casting(0.35, true, &rng), T_fixture_part);
  std::uniform_real_distribution<float> u(-120.0f, 120.0f);
  for (int i = 0; i < 60000; ++i) {
    const auto xy = fettle::test::draws<2>(u, rng);
    const Eigen::Vector3f p(xy[0], xy[1], 0.0f);
    const Eigen::Vector3f q = (T_fixture_part.inverse() * p.cast<double>()).cast<float>();
    if (std::abs(q.x()) < 61 && std::abs(q.y()) < 41) continue;  // under the part
    part.points.push_back(p);
  }
  part.normals.clear();
  std::normal_distribution<float> g(0.0f, static_cast<float>(sigma));
  for (auto& p : part.points) p.z() += g(rng);
  return part;
}

/// The template of the excess tests: the plane z = 0 from -20 to 20 mm on a 0.5 mm grid.
PreparedCloud flat_template() {
  PrepareSettings ps;
  ps.features = false;
  return PreparedCloud::prepare(test::flat_square(20.0f), ps);
}

/// A flat template, the plane z = 0 over +-half mm on a 0.5 mm grid, without features.
PreparedCloud flat_template(float half) {
  PrepareSettings ps;
  ps.features = false;
  return PreparedCloud::prepare(test::flat_square(half), ps);
}

/// What a camera sees over the grid x in [-half_x, half_x], y in [-half_y, half_y], `step` apart:
/// height(x, y) plus 0.02 mm of noise drawn from `seed`.
template <class Height>
Cloud grid_scene(float half_x, float half_y, float step, std::uint64_t seed, Height height) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> noise(0.0f, 0.02f);
  Cloud scene;
  for (float x = -half_x; x <= half_x; x += step)
    for (float y = -half_y; y <= half_y; y += step) scene.points.emplace_back(x, y, height(x, y) + noise(rng));
  return scene;
}

/// The excess measured from the casting's own face, with sand-cast iron's 0.5 mm form deviation.
ExcessSettings against_own_face() {
  ExcessSettings own;
  own.form_deviation_mm = 0.5;
  return own;
}

}  // namespace

TEST(Inspect, FindsEveryRegionAtTheTruePoseAndMeasuresTheRiser) {
  const auto rec = recipe();
  const auto templ = PartTemplate::build(rec, casting(0.5, false, nullptr));
  ASSERT_EQ(templ.regions().size(), 2U);
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> off(-3.0, 3.0);
  const double yaw_deg = off(rng);  // sequenced as gcc drew them (tests/support/draws.hpp)
  const auto xy = fettle::test::draws<2>(off, rng);
  const Transform T_fixture_part =
      Eigen::Translation3d(xy[0], xy[1], 0.0) * Eigen::AngleAxisd(fettle::deg_to_rad(yaw_deg), Vec3::UnitZ());
  const auto r = inspect(rec, templ, scan(T_fixture_part, rng, 0.05));
  ASSERT_TRUE(r.ok()) << r.error().message;
  ASSERT_EQ(r->regions.size(), 2U);
  for (const auto& region : r->regions) {
    ASSERT_TRUE(region.ok()) << region.error->message;
    const auto e = test::pose_error(region.registration.T_scene_template, T_fixture_part);
    EXPECT_LT(e.translation, 0.05) << region.name;
    EXPECT_LT(fettle::rad_to_deg(e.rotation_rad), 0.05) << region.name;
    EXPECT_GT(region.registration.fitness, 0.8) << region.name;
  }
  const double truth = std::numbers::pi * kRiserRadius * kRiserRadius * kRiserHeight;
  EXPECT_NEAR(r->regions[0].excess.volume_mm3, truth, 0.1 * truth);
  EXPECT_NEAR(r->regions[0].excess.max_height_mm, kRiserHeight, 0.3);
  EXPECT_NEAR(r->regions[0].excess.footprint_mm2, std::numbers::pi * kRiserRadius * kRiserRadius,
              0.15 * std::numbers::pi * kRiserRadius * kRiserRadius);
  EXPECT_LT(r->regions[1].excess.volume_mm3, 0.02 * truth);  // the boss region is clean
  EXPECT_EQ(r->deviation_mm.size(), r->scene_part.size());
}

TEST(Inspect, AScanWithoutThePartFailsAndSaysSo) {
  const auto rec = recipe();
  const auto templ = PartTemplate::build(rec, casting(0.5, false, nullptr));
  std::mt19937_64 rng(1);
  Cloud table;
  std::uniform_real_distribution<float> u(-120.0f, 120.0f);
  std::normal_distribution<float> g(0.0f, 0.05f);
  for (int i = 0; i < 80000; ++i) {
    const float z = g(rng);
    const auto xy = fettle::test::draws<2>(u, rng);
    table.points.emplace_back(xy[0], xy[1], z);
  }
  const auto r = inspect(rec, templ, table);
  ASSERT_FALSE(r.ok());
  // only the table: nothing stands above the fixture plane where the part should be
  EXPECT_EQ(r.error().code, "vision.empty_fixture") << r.error().message;
  EXPECT_NE(r.error().message.find("no part on the fixture"), std::string::npos) << r.error().message;
}

TEST(Inspect, MetresAreRefused) {
  const auto rec = recipe();
  const auto templ = PartTemplate::build(rec, casting(0.5, false, nullptr));
  std::mt19937_64 rng(2);
  const Cloud metres = transformed(scan(Transform::Identity(), rng, 0.05), Transform(Eigen::Scaling(0.001)));
  const auto r = inspect(rec, templ, metres);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().code, "vision.units");
  EXPECT_NE(r.error().message.find("metres"), std::string::npos);
}

TEST(Inspect, SeveralOrganizedViewsRefuseAMissingOrMisSizedViewNamingIt) {
  const auto rec = recipe();
  const auto templ = PartTemplate::build(rec, casting(0.5, false, nullptr));
  fettle::OrganizedCloud good;
  good.width = 2;
  good.height = 2;
  good.points.assign(4, Eigen::Vector3f(0.0f, 0.0f, 600.0f));
  fettle::OrganizedCloud short_of_a_row = good;
  short_of_a_row.points.resize(3);
  const auto none = inspect(rec, templ, std::vector<OrganizedView>{});
  ASSERT_FALSE(none.ok());
  EXPECT_EQ(none.error().code, "vision.no_views");
  const Transform I = Transform::Identity();
  const auto missing = inspect(rec, templ, std::vector<OrganizedView>{{&good, I}, {nullptr, I}});
  ASSERT_FALSE(missing.ok());
  EXPECT_EQ(missing.error().code, "vision.empty_scan");
  EXPECT_NE(missing.error().message.find("view 1"), std::string::npos) << missing.error().message;
  const auto mis_sized = inspect(rec, templ, std::vector<OrganizedView>{{&good, I}, {&short_of_a_row, I}});
  ASSERT_FALSE(mis_sized.ok());
  EXPECT_NE(mis_sized.error().message.find("view 1"), std::string::npos) << mis_sized.error().message;
  EXPECT_NE(mis_sized.error().message.find("2 x 2"), std::string::npos) << mis_sized.error().message;
  fettle::OrganizedCloud all_nan = good;
  all_nan.points.assign(4, fettle::OrganizedCloud::invalid());
  const auto nan = inspect(rec, templ, std::vector<OrganizedView>{{&all_nan, I}, {&all_nan, I}});
  ASSERT_FALSE(nan.ok());
  EXPECT_EQ(nan.error().code, "vision.empty_scan");
  EXPECT_NE(nan.error().message.find("every pixel is NaN"), std::string::npos) << nan.error().message;
}

TEST(TemplateCache, SecondLoadComesFromDiskAndMatches) {
  auto rec = recipe();
  const auto dir = std::filesystem::temp_directory_path() / ("fettle-tcache-" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  rec.source = dir / "block.toml";
  rec.vision.cache = true;
  const Cloud golden = casting(0.5, false, nullptr);
  bool cached = true;
  const auto a = PartTemplate::load_or_build(rec, golden, "golden v1", &cached);
  EXPECT_FALSE(cached);
  const auto b = PartTemplate::load_or_build(rec, golden, "golden v1", &cached);
  EXPECT_TRUE(cached);
  ASSERT_EQ(b.regions().size(), a.regions().size());
  EXPECT_EQ(b.whole().coarse().points, a.whole().coarse().points);
  EXPECT_EQ(b.regions()[1].cloud.fine().points, a.regions()[1].cloud.fine().points);
  // A different golden part (or changed ROIs) invalidates the cache.
  (void)PartTemplate::load_or_build(rec, golden, "golden v2", &cached);
  EXPECT_FALSE(cached);
  std::filesystem::remove_all(dir);
}

TEST(TemplateCache, AnExplicitDirectoryCachesARecipeWithoutASourceAndLeavesNoTemporaryFiles) {
  auto rec = recipe();
  rec.source.clear();
  rec.vision.cache = false;  // the explicit directory wins over both
  const auto dir = std::filesystem::temp_directory_path() / ("fettle-tcache-dir-" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  const Cloud golden = casting(0.5, false, nullptr);
  bool cached = true;
  const auto a = PartTemplate::load_or_build(rec, golden, "in memory", &cached, dir);
  EXPECT_FALSE(cached);
  ASSERT_TRUE(std::filesystem::exists(dir / "whole.bin"));
  for (const auto& e : std::filesystem::directory_iterator(dir))
    EXPECT_EQ(e.path().string().find(".tmp"), std::string::npos) << e.path();
  const auto b = PartTemplate::load_or_build(rec, golden, "in memory", &cached, dir);
  EXPECT_TRUE(cached);
  ASSERT_EQ(b.regions().size(), a.regions().size());
  EXPECT_EQ(b.whole().fine().points, a.whole().fine().points);
  EXPECT_EQ(b.regions()[0].cloud.coarse().points, a.regions()[0].cloud.coarse().points);
  // Without the directory nothing is cached: the recipe has no source and its cache is off.
  (void)PartTemplate::load_or_build(rec, golden, "in memory", &cached);
  EXPECT_FALSE(cached);
  // One region file of another golden (two processes filling the directory at once) makes
  // the whole cache stale: it is rebuilt, not mixed.
  const auto other = dir / "other";
  (void)PartTemplate::load_or_build(rec, golden, "another golden", &cached, other);
  std::filesystem::copy_file(other / "region-0.bin", dir / "region-0.bin", std::filesystem::copy_options::overwrite_existing);
  (void)PartTemplate::load_or_build(rec, golden, "in memory", &cached, dir);
  EXPECT_FALSE(cached);
  std::filesystem::remove_all(dir);
}

TEST(TemplateCache, ARecipeWithItsCacheOffWritesNothingNextToIt) {
  auto rec = recipe();
  const auto dir = std::filesystem::temp_directory_path() / ("fettle-tcache-off-" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  rec.source = dir / "block.toml";
  rec.vision.cache = false;
  bool cached = true;
  (void)PartTemplate::load_or_build(rec, casting(0.5, false, nullptr), "golden v1", &cached);
  EXPECT_FALSE(cached);
  EXPECT_TRUE(std::filesystem::is_empty(dir));
  std::filesystem::remove_all(dir);
}

TEST(Excess, ABumpOnAPlaneHasItsVolumeAndHeight) {
  const auto t = flat_template();
  Cloud scene;
  for (float x = -20; x <= 20; x += 0.25f)
    for (float y = -20; y <= 20; y += 0.25f) {
      const bool bump = std::abs(x) <= 5 && std::abs(y) <= 5;
      scene.points.emplace_back(x, y, bump ? 1.5f : 0.1f);  // 0.1 mm is below the 0.2 mm threshold
    }
  const auto ex = measure_excess(t, scene, {});
  EXPECT_NEAR(ex.max_height_mm, 1.5, 1e-5);
  // The bump covers the template points from -5 to 5 inclusive: 21 x 21 patches of 0.5 mm.
  const double footprint = 10.5 * 10.5;
  EXPECT_NEAR(ex.footprint_mm2, footprint, 0.03 * footprint);
  EXPECT_NEAR(ex.volume_mm3, 1.5 * footprint, 0.03 * 1.5 * footprint);
  for (const auto h : ex.heights_mm) EXPECT_GT(h, 0.2f);
}

// A casting whose face stands 0.3-0.5 mm over the nominal (a smooth form deviation, a tilt
// here) with a bump of material on it: against the nominal the whole face is "material";
// against the casting's own face only the bump is, and the plane of offsets is the tilt's.
TEST(Excess, TheCastingsFormDeviationIsNotMaterial) {
  const auto t = flat_template();
  Cloud scene;
  std::mt19937_64 rng(3);
  std::normal_distribution<float> noise(0.0f, 0.02f);
  const auto face = [](float x, float y) { return 0.4f + 0.005f * x - 0.002f * y; };
  for (float x = -20; x <= 20; x += 0.25f)
    for (float y = -20; y <= 20; y += 0.25f) {
      const bool bump = std::abs(x - 6) <= 3 && std::abs(y) <= 3;
      scene.points.emplace_back(x, y, face(x, y) + (bump ? 1.5f : 0.0f) + noise(rng));
    }
  ExcessSettings nominal;
  const auto against_nominal = measure_excess(t, scene, nominal);
  EXPECT_GT(against_nominal.points.size(), scene.size() / 2) << "the face itself reads as material";
  EXPECT_FALSE(against_nominal.form.fitted);

  ExcessSettings own = nominal;
  own.form_deviation_mm = 0.5;
  const auto ex = measure_excess(t, scene, own);
  ASSERT_TRUE(ex.form.fitted);
  EXPECT_NEAR(ex.form.at_origin_mm, 0.4, 0.01);
  EXPECT_NEAR(ex.form.per_mm_x, 0.005, 0.0005);
  EXPECT_NEAR(ex.form.per_mm_y, -0.002, 0.0005);
  EXPECT_LT(ex.form.rms_mm, 0.03);
  const std::size_t bump_points = 25 * 25;  // 6 x 6 mm at 0.25 mm
  EXPECT_NEAR(static_cast<double>(ex.points.size()), static_cast<double>(bump_points), 0.1 * bump_points);
  for (const auto& p : ex.points) EXPECT_LE(std::abs(p.x() - 6.0f), 3.3f) << "material off the bump";
}

// A face whose form waves +-0.5 mm with a 100 mm wavelength (sand-cast iron's; a plane through
// 120 mm of it misses by more than 0.3 mm, and its crests stand at the template's form
// deviation) with a bump of material on it: the local face follows the wave, so only the bump
// is material.
TEST(Excess, TheLocalFaceFollowsAFormThePlaneCannot) {
  const auto t = flat_template(60.0f);
  const auto face = [](float x) { return 0.5f * std::sin(2.0f * static_cast<float>(std::numbers::pi) * x / 100.0f); };
  const auto on_bump = [](float x, float y) { return std::abs(x - 6) <= 3 && std::abs(y) <= 3; };
  const auto scene = grid_scene(60, 20, 0.25f, 5, [&](float x, float y) { return face(x) + (on_bump(x, y) ? 1.5f : 0.0f); });
  const auto ex = measure_excess(t, scene, against_own_face());
  ASSERT_TRUE(ex.form.fitted);
  double worst = 0.0, worst_plane = 0.0;
  for (float x = -58; x <= 58; x += 0.5f)
    for (float y = -18; y <= 18; y += 0.5f) {
      if (std::abs(x - 6) <= 4 && std::abs(y) <= 4) continue;  // beside the bump
      worst = std::max(worst, std::abs(ex.form.at(x, y) - face(x)));
      worst_plane = std::max(worst_plane, std::abs(ex.form.plane_at(x, y) - face(x)));
    }
  EXPECT_LT(worst, 0.06) << "the local face";
  EXPECT_GT(worst_plane, 0.3) << "a plane cannot follow it";
  const std::size_t bump_points = 25 * 25;  // 6 x 6 mm at 0.25 mm
  EXPECT_NEAR(static_cast<double>(ex.points.size()), static_cast<double>(bump_points), 0.1 * bump_points);
  for (const auto& p : ex.points)
    EXPECT_TRUE(std::abs(p.x() - 6.0f) <= 3.3f && std::abs(p.y()) <= 3.3f)
        << "material off the bump at " << p.x() << ", " << p.y() << ", " << p.z();
}

// The face as the cell sees it: the casting's form (+-0.5 mm, a 100 mm wave) in the part's
// located frame, whose registration error over 120 mm adds a tilt and a lift (0.003 mm/mm,
// 0.25 mm here). The crest stands 0.8 mm over the template and about 0.5 mm over the region's
// plane, and is still face. A face gated at the form deviation of the template (for the plane)
// and of the plane (for the local fit) loses the crest's samples and reads 0.2-0.3 mm low
// there, and a pass over it cuts that deep into the body (a straight flash's lead beyond its
// ROI, `make accuracy`).
TEST(Excess, AFaceFartherFromTheRegionsPlaneThanTheFormDeviationIsStillFollowed) {
  const auto t = flat_template(60.0f);
  const auto face = [](float x) {
    return 0.25f + 0.5f * std::sin(2.0f * static_cast<float>(std::numbers::pi) * x / 100.0f) + 0.003f * x;
  };
  const auto on_bump = [](float x, float y) { return std::abs(x + 30) <= 3 && std::abs(y) <= 3; };
  const auto scene = grid_scene(60, 20, 0.25f, 7, [&](float x, float y) { return face(x) + (on_bump(x, y) ? 1.5f : 0.0f); });
  const auto ex = measure_excess(t, scene, against_own_face());
  ASSERT_TRUE(ex.form.fitted);
  double worst = 0.0, over_plane = 0.0, over_template = 0.0;
  float wx = 0;
  for (float x = -58; x <= 58; x += 0.5f)
    for (float y = -18; y <= 18; y += 0.5f) {
      if (std::abs(x + 30) <= 4 && std::abs(y) <= 4) continue;  // beside the bump
      if (const double e = std::abs(ex.form.at(x, y) - face(x)); e > worst) worst = e, wx = x;
      over_plane = std::max(over_plane, face(x) - ex.form.plane_at(x, y));
      over_template = std::max(over_template, static_cast<double>(face(x)));
    }
  EXPECT_GT(over_template, 0.75) << "the crest stands farther over the template than the form deviation";
  EXPECT_GT(over_plane, 0.45) << "and about as far over the region's plane";
  EXPECT_LT(worst, 0.06) << "the local face at x = " << wx;
  const std::size_t bump_points = 25 * 25;  // 6 x 6 mm at 0.25 mm
  EXPECT_NEAR(static_cast<double>(ex.points.size()), static_cast<double>(bump_points), 0.1 * bump_points);
}

// A riser whose top is tilted so steeply (0.2 mm/mm) that it meets the face: on its low side
// the material rises out of the face on a ramp, the first millimetres of which lie within the
// casting's form deviation and look like face. A plane through a node's neighbourhood there
// tilts up the ramp and reads the face 0.2-0.5 mm high, and the riser's last pass leaves that
// much; left out as the foot of material, the face stays where it is.
TEST(Excess, ARiserMeetingTheFaceOnARampLeavesTheFaceWhereItIs) {
  const auto t = flat_template(40.0f);
  constexpr float face = 0.1f;
  const auto riser = [](float x, float y) {  // material over the face, 0 where there is none
    return x * x + y * y <= 15.0f * 15.0f ? std::max(0.0f, 1.0f + 0.2f * x) : 0.0f;
  };
  const auto scene = grid_scene(40, 40, 0.5f, 11, [&](float x, float y) { return face + riser(x, y); });
  const auto ex = measure_excess(t, scene, against_own_face());
  ASSERT_TRUE(ex.form.fitted);
  double worst = 0.0;
  float wx = 0, wy = 0;
  for (float x = -38; x <= 38; x += 0.5f)
    for (float y = -38; y <= 38; y += 0.5f)
      if (const double e = std::abs(ex.form.at(x, y) - face); e > worst) worst = e, wx = x, wy = y;
  EXPECT_LT(worst, 0.06) << "the face at " << wx << ", " << wy << " (the ramp's foot is at x = -5)";
  std::size_t tall = 0, found = 0;
  for (const auto& p : scene.points) tall += riser(p.x(), p.y()) > 0.3f ? 1 : 0;
  for (const auto& p : ex.points) {
    found += riser(p.x(), p.y()) > 0.3f ? 1 : 0;
    EXPECT_GT(riser(p.x(), p.y()), 0.1f) << "material on the face at " << p.x() << ", " << p.y();
  }
  EXPECT_GE(static_cast<double>(found), 0.95 * static_cast<double>(tall)) << "the riser's material over 0.3 mm";
}

// A riser 40 mm wide on the crest of a 90 mm form wave (+-0.4 mm; the simulator draws 90-200 mm
// and up to the form deviation): the scan sees no face under it. The region's plane there is the
// wave's mean, 0.35 mm under the crest, and the nodes beside it, taking their neighbours' slope
// to the node, stepped between the two; the quadratic of the faces around the riser carries the
// crest across it.
TEST(Excess, TheFaceUnderARiserIsInterpolatedNotExtrapolated) {
  const auto t = flat_template(50.0f);
  const auto face = [](float x) { return 0.4f * std::cos(2.0f * static_cast<float>(std::numbers::pi) * x / 90.0f); };
  const auto on_riser = [](float x, float y) { return x * x + y * y <= 20.0f * 20.0f; };
  const auto scene = grid_scene(50, 50, 0.5f, 13, [&](float x, float y) { return face(x) + (on_riser(x, y) ? 6.0f : 0.0f); });
  const auto ex = measure_excess(t, scene, against_own_face());
  ASSERT_TRUE(ex.form.fitted);
  // under: the riser and its foot, where no face was seen; beside: the face seen around it
  double under = 0.0, beside = 0.0, plane_under = 0.0;
  for (float x = -48; x <= 48; x += 0.5f)
    for (float y = -48; y <= 48; y += 0.5f) {
      const double e = std::abs(ex.form.at(x, y) - face(x));
      if (x * x + y * y < 23.0f * 23.0f) {
        under = std::max(under, e);
        plane_under = std::max(plane_under, std::abs(ex.form.plane_at(x, y) - face(x)));
      } else {
        beside = std::max(beside, e);
      }
    }
  EXPECT_GT(plane_under, 0.3) << "the region's plane under the riser";
  // a quadratic through the faces 23-33 mm from the centre misses the wave's higher terms there
  EXPECT_LT(under, 0.1) << "the face under the riser";
  EXPECT_LT(beside, 0.06) << "the face beside it";
}

// A riser ground down to a 0.3 mm stub (within the casting's 0.5 mm form deviation): fitted on
// the ground casting, the stub is most of the face around it and reads as the face, so a
// re-grind would find nothing; measured from the face the first scan saw, the stub is material.
TEST(Excess, AReGrindMeasuresFromTheFaceTheFirstScanSaw) {
  const auto t = flat_template(40.0f);
  const auto casting = [](float riser_mm) {
    return grid_scene(40, 40, 0.5f, 9, [&](float x, float y) { return 0.1f + (x * x + y * y <= 64.0f ? riser_mm : 0.0f); });
  };
  const ExcessSettings own = against_own_face();
  const auto first = measure_excess(t, casting(3.0f), own);
  ASSERT_TRUE(first.form.fitted);
  const auto ground = casting(0.3f);
  std::size_t stub_points = 0;
  for (const auto& p : ground.points) stub_points += p.x() * p.x() + p.y() * p.y() <= 64.0f ? 1 : 0;
  const auto refitted = measure_excess(t, ground, own);
  EXPECT_LT(static_cast<double>(refitted.points.size()), 0.5 * static_cast<double>(stub_points))
      << "fitted on the ground casting, the stub is taken for the face";
  ExcessSettings from_first = own;
  from_first.face = &first.form;
  const auto stub = measure_excess(t, ground, from_first);
  EXPECT_NEAR(static_cast<double>(stub.points.size()), static_cast<double>(stub_points), 0.1 * static_cast<double>(stub_points));
  EXPECT_NEAR(stub.max_height_mm, 0.4, 0.1);
}

// A scan voxelized in its own frame has the template's pitch but not its grid, and the voxels
// on the rim average the top with the floor around it. Counting the template patches that own
// a material point measures this disc 3 % large (the simulator's riser scans 2-10 % small);
// resampling the nearest scan point onto each patch measures it within 1 %.
TEST(Excess, ADiscSampledOnAnotherGridHasItsWholeFootprint) {
  const auto t = flat_template();
  const double radius = 8.0, height = 3.0;
  const Eigen::Rotation2Dd turn(fettle::deg_to_rad(3.0));
  for (const Eigen::Vector2d& offset : {Eigen::Vector2d(0.21, 0.13), Eigen::Vector2d(0.25, 0.25), Eigen::Vector2d(0.0, 0.0)}) {
    // seen from above, densely, and voxelized at the template's pitch in the scan's frame:
    // the disc's top and the plane around it
    Cloud dense;
    for (int i = -190; i <= 190; ++i)
      for (int j = -190; j <= 190; ++j) {
        const Eigen::Vector2d q(0.1 * i, 0.1 * j);
        const Eigen::Vector2d in_template = turn * q + offset;
        dense.points.emplace_back(static_cast<float>(q.x()), static_cast<float>(q.y()),
                                  in_template.norm() <= radius ? static_cast<float>(height) : 0.0f);
      }
    Transform T_template_scan = Transform::Identity();
    T_template_scan.linear().topLeftCorner<2, 2>() = turn.toRotationMatrix();
    T_template_scan.translation().head<2>() = offset;
    const Cloud scene = transformed(voxel_downsample(dense, 0.5), T_template_scan);
    const auto ex = measure_excess(t, scene, {});
    const double footprint = std::numbers::pi * radius * radius;
    EXPECT_NEAR(ex.footprint_mm2, footprint, 0.02 * footprint) << "offset " << offset.transpose();
    EXPECT_NEAR(ex.volume_mm3, height * footprint, 0.02 * height * footprint) << "offset " << offset.transpose();
  }
}

TEST(MultiView, TwoOverlappingViewsFuseIntoOneLayer) {
  // One surface seen from two slide positions 80 mm apart; the second view's calibration
  // guess is 0.8 mm and 0.5 degrees off.
  std::mt19937_64 rng(3);
  const Cloud surface = casting(0.4, false, &rng);
  Cloud first_frame_surface = surface;
  first_frame_surface.normals.clear();
  Transform T_first_second = Transform::Identity();
  T_first_second.translation() = Vec3(80.0, 0.0, 0.0);
  View v0;
  v0.cloud = crop_box(first_frame_surface, Transform::Identity(), Vec3(-70, -50, -1), Vec3(30, 50, 60));
  View v1;
  const Cloud second_all = transformed(first_frame_surface, T_first_second.inverse());
  v1.cloud = crop_box(second_all, Transform::Identity(), Vec3(-110, -50, -1), Vec3(-10, 50, 60));  // overlap x in [-30, 30] of view 0
  v1.T_first_view = T_first_second * Eigen::Translation3d(0.8, -0.5, 0.3) *
                    Eigen::AngleAxisd(fettle::deg_to_rad(0.5), Vec3::UnitZ());
  FuseSettings fs;
  fs.voxel_mm = 0.5;
  const auto fused = fuse_views({v0, v1}, fs);
  ASSERT_TRUE(fused.ok()) << fused.error().message;
  const auto e = test::pose_error(fused->T_first_view[1], T_first_second);
  EXPECT_LT(e.translation, 0.05);
  EXPECT_LT(fettle::rad_to_deg(e.rotation_rad), 0.05);
  // No doubled layer: on the top face in the overlap every fused point lies on z = 40.
  std::size_t on_top = 0;
  for (const auto& p : fused->cloud.points)
    if (p.x() > -25 && p.x() < 5 && p.y() > -35 && p.y() < -5 && p.z() > 35) {
      ++on_top;
      EXPECT_NEAR(p.z(), 40.0f, 0.05f);
    }
  EXPECT_GT(on_top, 1000U);
  // One point per neighbourhood: the overlap is not denser than the rest.
  EXPECT_LT(fused->cloud.size(), v0.cloud.size() + v1.cloud.size());
}

// A golden scan with many duplicate points (and invalid pixels stored as (0, 0, 0)) built its
// template in quadratic time: normals were estimated on the raw cloud before it was downsampled
// (issue 40, item 3). Eight copies of every point (and 50 000 zeros) must cost about as much
// as the points once: far less than the 64x a quadratic build takes, and give the same template.
TEST(Inspect, ATemplateFromAGoldenWithDuplicatesBuildsInLinearTime) {
  const auto rec = recipe();
  Cloud once = casting(0.5, false, nullptr);
  once.normals.clear();  // a scan: normals estimated
  Cloud dup;
  for (int k = 0; k < 8; ++k) dup.points.insert(dup.points.end(), once.points.begin(), once.points.end());
  dup.points.insert(dup.points.end(), 50000, Eigen::Vector3f::Zero());
  const auto time = [&](const Cloud& c, std::size_t& points) {
    const auto t0 = std::chrono::steady_clock::now();
    const auto t = PartTemplate::build(rec, c);
    points = t.whole().fine().size();
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  std::size_t n_once = 0, n_dup = 0;
  const double s_once = time(once, n_once);
  const double s_dup = time(dup, n_dup);
  EXPECT_EQ(n_dup, n_once) << "the duplicates and the zeros change nothing";
  EXPECT_LT(s_dup, 4.0 * s_once + 0.5) << once.size() << " points once: " << s_once << " s; x8 and zeros: " << s_dup << " s";
}

