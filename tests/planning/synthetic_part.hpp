#pragma once
// A synthetic pump-body-like part for planning tests and the bench: an analytic signed
// distance (boxes and cylinders) and excess points of a ring flash at the flange's top edge,
// a riser on a pad, a small circle flash at a boss's top edge and a straight parting-line fin.
// Excess points are sampled about `pitch_mm` apart (0.5 mm ~ the vision stage's voxel size).
#include <algorithm>
#include <cmath>
#include <numbers>
#include <random>
#include <vector>

#include "fettle/config/part.hpp"
#include "fettle/planning/planner.hpp"

namespace fettle::planning::testing {

inline double sdf_box(const Vec3& p, const Vec3& lo, const Vec3& hi) {
  const Vec3 c = 0.5 * (lo + hi), h = 0.5 * (hi - lo);
  const Vec3 q = (p - c).cwiseAbs() - h;
  return q.cwiseMax(0.0).norm() + std::min(q.maxCoeff(), 0.0);
}

inline double sdf_cylinder(const Vec3& p, double cx, double cy, double r, double z0, double z1) {
  const double dr = std::hypot(p.x() - cx, p.y() - cy) - r;
  const double dz = std::max(z0 - p.z(), p.z() - z1);
  return std::min(std::max(dr, dz), 0.0) + std::hypot(std::max(dr, 0.0), std::max(dz, 0.0));
}

/// The template body (part frame, mm).
inline double part_sdf(const Vec3& p) {
  double d = sdf_box(p, Vec3(-110, -85, 0), Vec3(110, 85, 35));      // base plate
  d = std::min(d, sdf_box(p, Vec3(-110, 22, 0), Vec3(-62, 85, 45)));  // riser pad
  d = std::min(d, sdf_cylinder(p, 0, 0, 45, 0, 50));                   // flange, top edge z = 50
  d = std::min(d, sdf_box(p, Vec3(62, -85, 0), Vec3(110, -22, 40)));  // boss block
  d = std::min(d, sdf_cylinder(p, 82, -48, 7, 0, 47));                 // boss, top edge z = 47
  return d;
}

/// Flash fin at the top edge of a cylinder: an annulus r..r+extent, z top-thickness..top.
inline std::vector<Vec3> ring_fin(double cx, double cy, double r, double top, double extent, double thickness,
                                  double pitch, double gap_fraction = 0.1) {
  std::vector<Vec3> pts;
  const double circ = 2 * std::numbers::pi * r;
  const int na = static_cast<int>(circ / pitch);
  for (int i = 0; i < na; ++i) {
    const double a = 2 * std::numbers::pi * i / na;
    if (a < 2 * std::numbers::pi * gap_fraction) continue;  // a gap without flash
    for (double e = pitch; e <= extent + 1e-9; e += pitch)
      pts.emplace_back(cx + (r + e) * std::cos(a), cy + (r + e) * std::sin(a), top);
    for (double z = top - thickness; z < top; z += pitch)
      pts.emplace_back(cx + (r + extent) * std::cos(a), cy + (r + extent) * std::sin(a), z);
  }
  return pts;
}

/// A riser stub: cylinder of radius r on a face at z = face, top tilted (height h0 ± slope).
inline std::vector<Vec3> riser(double cx, double cy, double r, double face, double h0, double slope, double pitch) {
  std::vector<Vec3> pts;
  for (double x = -r; x <= r; x += pitch)
    for (double y = -r; y <= r; y += pitch)
      if (x * x + y * y <= r * r) pts.emplace_back(cx + x, cy + y, face + h0 + slope * x);
  const int na = static_cast<int>(2 * std::numbers::pi * r / pitch);
  for (int i = 0; i < na; ++i) {
    const double a = 2 * std::numbers::pi * i / na;
    const double x = r * std::cos(a), y = r * std::sin(a);
    for (double z = face + pitch; z < face + h0 + slope * x; z += pitch) pts.emplace_back(cx + x, cy + y, z);
  }
  return pts;
}

/// A straight fin along x at y = y0 on a face at z = face: height h, thickness t.
inline std::vector<Vec3> straight_fin(double x0, double x1, double y0, double face, double h, double t, double pitch) {
  std::vector<Vec3> pts;
  for (double x = x0; x <= x1; x += pitch) {
    for (double y = -t / 2; y <= t / 2 + 1e-9; y += pitch) pts.emplace_back(x, y0 + y, face + h);
    for (double z = face + pitch; z < face + h; z += pitch) {
      pts.emplace_back(x, y0 - t / 2, z);
      pts.emplace_back(x, y0 + t / 2, z);
    }
  }
  return pts;
}

/// Recipe-like regions and tools (the pump body's), kept alive for RegionInput pointers.
struct Scene {
  std::vector<config::Tool> tools;
  std::vector<config::Region> regions;
  std::vector<RegionInput> inputs;
};

inline Scene make_scene(double pitch_mm = 0.5, const Transform& T_base_part = Transform::Identity()) {
  Scene s;
  config::Tool disc;
  disc.name = "chamfer-disc";
  disc.shape = config::ToolShape::cylinder;
  disc.diameter_mm = 40.0;
  disc.length_mm = 6.0;
  disc.tcp_mm = {0, 0, 180};
  config::Tool ball;
  ball.name = "ball-12";
  ball.shape = config::ToolShape::ball;
  ball.diameter_mm = 12.0;
  ball.tcp_mm = {0, 0, 165};
  config::Tool burr = disc;  // a small cylindrical burr: its side runs round the boss
  burr.name = "burr-10";
  burr.diameter_mm = 10.0;
  burr.tcp_mm = {0, 0, 150};
  s.tools = {disc, ball, burr};

  config::Region ring;
  ring.name = "flange-ring";
  ring.type = config::RegionType::ring_flash;
  ring.tool = "chamfer-disc";
  ring.feed_mm_s = 20.0;
  ring.spindle_rpm = 8000.0;
  ring.overlap_mm = 10.0;
  ring.roi_center_mm = {0.0, 0.0, 50.0};  // the ROIs of config/parts/pump-body.toml
  ring.roi_size_mm = {110.0, 110.0, 20.0};
  config::Region rs;
  rs.name = "riser";
  rs.type = config::RegionType::riser;
  rs.tool = "ball-12";
  rs.feed_mm_s = 15.0;
  rs.spindle_rpm = 9000.0;
  rs.depth_per_pass_mm = 2.0;
  rs.stepover_mm = 4.0;
  rs.margin_mm = 3.0;
  rs.allowance_mm = 0.05;
  rs.roi_center_mm = {-82.0, 48.0, 52.0};
  rs.roi_size_mm = {60.0, 60.0, 40.0};
  config::Region boss;
  boss.name = "boss-circle";
  boss.type = config::RegionType::circle_flash;
  boss.tool = "ball-12";
  boss.feed_mm_s = 15.0;
  boss.spindle_rpm = 9000.0;
  boss.roi_center_mm = {82.0, -48.0, 47.0};
  boss.roi_size_mm = {30.0, 30.0, 20.0};
  config::Region side;
  side.name = "side-parting-line";
  side.type = config::RegionType::straight_flash;
  side.tool = "ball-12";
  side.feed_mm_s = 25.0;
  side.spindle_rpm = 9000.0;
  side.passes = 2;
  side.roi_center_mm = {-30.0, -70.0, 37.0};
  side.roi_size_mm = {140.0, 20.0, 12.0};
  s.regions = {ring, rs, boss, side};

  std::vector<std::vector<Vec3>> points = {
      ring_fin(0, 0, 45, 50, 3.0, 1.2, pitch_mm),
      riser(-82, 48, 15, 45, 9.0, std::tan(8.0 * std::numbers::pi / 180.0), pitch_mm),
      ring_fin(82, -48, 7, 47, 2.0, 0.8, pitch_mm, 0.05),
      straight_fin(-95, -5, -70, 35, 2.0, 1.0, pitch_mm),
  };
  for (std::size_t i = 0; i < s.regions.size(); ++i) {
    RegionInput in;
    in.region = &s.regions[i];
    in.tool = &s.tools[i == 0 ? 0 : 1];
    in.T_base_part = T_base_part;
    in.excess_points_part = std::move(points[i]);
    in.template_sdf = part_sdf;
    s.inputs.push_back(std::move(in));
  }
  return s;
}

}  // namespace fettle::planning::testing
