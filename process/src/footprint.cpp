// A tool's solid at one pose (fettle/process/footprint.hpp).
#include "fettle/process/footprint.hpp"

#include <algorithm>
#include <cmath>

namespace fettle::process {

ToolSolid ToolSolid::of(const config::Tool& tool, const Transform& T_frame_tool) {
  ToolSolid s;
  s.axis = T_frame_tool.linear().col(2);
  s.radius_mm = 0.5 * tool.diameter_mm;
  s.ball = tool.shape == config::ToolShape::ball;
  s.a = s.ball ? Vec3(T_frame_tool.translation() + s.radius_mm * s.axis) : Vec3(T_frame_tool.translation());
  s.length_mm = s.ball ? 0.0 : std::max(0.0, tool.length_mm);
  return s;
}

double ToolSolid::distance(const Vec3& q, Vec3& normal) const {
  const Vec3 d = q - a;
  if (ball) {
    const double n = d.norm();
    normal = n > 1e-12 ? Vec3(d / n) : Vec3(-axis);
    return n - radius_mm;
  }
  const double s = axis.dot(d);
  const Vec3 radial = d - s * axis;
  const double rho = radial.norm();
  const Vec3 rdir = rho > 1e-12 ? Vec3(radial / rho) : Vec3::Zero();
  const double dx = rho - radius_mm;
  const double half = 0.5 * length_mm;
  const double dz = std::abs(s - half) - half;
  const Vec3 zdir = s < half ? Vec3(-axis) : axis;
  if (dx > 0.0 && dz > 0.0) {  // beyond the rim: the rounded corner
    const double out = std::hypot(dx, dz);
    normal = (dx * rdir + dz * zdir) / out;
    return out;
  }
  if (dx > dz) {
    normal = rdir;
    return dx;
  }
  normal = zdir;
  return dz;
}

Vec3 ToolSolid::box_min(double grow_mm) const {
  return a.cwiseMin(a + length_mm * axis) - Vec3::Constant(radius_mm + grow_mm);
}

Vec3 ToolSolid::box_max(double grow_mm) const {
  return a.cwiseMax(a + length_mm * axis) + Vec3::Constant(radius_mm + grow_mm);
}

ToolVolume ToolVolume::of(const config::Tool& tool, const Transform& T_frame_tool, double margin_mm, std::size_t region) {
  return ToolVolume{ToolSolid::of(tool, T_frame_tool), std::max(0.0, margin_mm), region};
}

}  // namespace fettle::process
