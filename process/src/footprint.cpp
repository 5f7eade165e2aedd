// A tool's grown volume at one pose (fettle/process/footprint.hpp).
#include "fettle/process/footprint.hpp"

#include <algorithm>
#include <cmath>

namespace fettle::process {

ToolVolume ToolVolume::of(const config::Tool& tool, const Transform& T_frame_tool, double margin_mm, std::size_t region) {
  ToolVolume v;
  v.radius_mm = 0.5 * tool.diameter_mm;
  v.margin_mm = std::max(0.0, margin_mm);
  v.region = region;
  const Vec3 tip = T_frame_tool.translation(), z = T_frame_tool.linear().col(2);
  v.ball = tool.shape == config::ToolShape::ball;
  if (v.ball) {
    v.a = v.b = tip + v.radius_mm * z;
  } else {
    v.a = tip;
    v.b = tip + std::max(0.0, tool.length_mm) * z;
  }
  return v;
}

bool ToolVolume::contains(const Vec3& q) const {
  const Vec3 ab = b - a;
  const double len = ab.norm();
  const double reach = radius_mm + margin_mm;
  // a ball; a cylinder of no length has no axis to take, and is taken as the sphere round it
  if (ball || len <= 0.0) return (q - a).squaredNorm() <= reach * reach;
  const Vec3 u = ab / len;
  const double t = (q - a).dot(u);
  const double r = (q - a - t * u).norm();
  // the distance from the cylinder's solid: radially beyond its side, axially beyond its end faces
  const double radial = std::max(0.0, r - radius_mm);
  const double axial = t < 0.0 ? -t : std::max(0.0, t - len);
  return radial * radial + axial * axial <= margin_mm * margin_mm;
}

}  // namespace fettle::process
