// The grinding process: executed path = commanded + noise + bias, interpolated, the tool's
// swept volume removes material (dexels) and cuts the body from the top; cuts into the
// golden body deeper than the threshold are gouges.
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "casting_model.hpp"
#include "fettle/core/error.hpp"

namespace fettle::sim {
namespace {

struct ToolSolid {
  config::ToolShape shape;
  double radius = 1, length = 1, tan_half = 1;
};

/// Interval [lo, hi] of z where the vertical line through (x, y) is inside the tool
/// (cylinder/cone tip or ball centre c, axis a toward the spindle). False if the line misses.
bool line_interval(const ToolSolid& tool, const Vec3& c, const Vec3& a, double x, double y, double& lo, double& hi) {
  const Vec3 q0(x - c.x(), y - c.y(), -c.z());  // q(z) = q0 + z ez
  if (tool.shape == config::ToolShape::ball) {
    const double B = q0.z(), C = q0.squaredNorm() - tool.radius * tool.radius;
    const double disc = B * B - C;
    if (disc < 0) return false;
    const double s = std::sqrt(disc);
    lo = -B - s, hi = -B + s;
    return true;
  }
  const double s0 = a.dot(q0), az = a.z();
  // axial range s in [0, L]
  double zlo = -1e300, zhi = 1e300;
  if (std::abs(az) < 1e-12) {
    if (s0 < 0 || s0 > tool.length) return false;
  } else {
    double z1 = (0 - s0) / az, z2 = (tool.length - s0) / az;
    if (z1 > z2) std::swap(z1, z2);
    zlo = z1, zhi = z2;
  }
  // radial: rho^2(z) = A z^2 + B z + C0
  const double A = 1 - az * az, B = 2 * (q0.z() - s0 * az), C0 = q0.squaredNorm() - s0 * s0;
  auto quad_le = [&](double qa, double qb, double qc, double& l, double& h) -> int {
    // solutions of qa z^2 + qb z + qc <= 0: 0 none, 1 interval [l, h], 2 complement (-inf, l] U [h, inf), 3 all
    if (std::abs(qa) < 1e-12) {
      if (std::abs(qb) < 1e-12) return qc <= 0 ? 3 : 0;
      const double r = -qc / qb;
      if (qb > 0) l = -1e300, h = r;
      else l = r, h = 1e300;
      return 1;
    }
    const double disc = qb * qb - 4 * qa * qc;
    if (disc < 0) return qa > 0 ? 0 : 3;
    const double sq = std::sqrt(disc);
    double r1 = (-qb - sq) / (2 * qa), r2 = (-qb + sq) / (2 * qa);
    if (r1 > r2) std::swap(r1, r2);
    l = r1, h = r2;
    return qa > 0 ? 1 : 2;
  };
  double l = 0, h = 0;
  const int cyl = quad_le(A, B, C0 - tool.radius * tool.radius, l, h);
  if (cyl == 0) return false;
  if (cyl == 1) zlo = std::max(zlo, l), zhi = std::min(zhi, h);
  if (zlo > zhi) return false;
  if (tool.shape == config::ToolShape::cone) {
    const double t2 = tool.tan_half * tool.tan_half;
    // rho^2 - t2 s^2 <= 0 with s = s0 + az z
    const int k = quad_le(A - t2 * az * az, B - 2 * t2 * s0 * az, C0 - t2 * s0 * s0, l, h);
    if (k == 0) return false;
    if (k == 1) zlo = std::max(zlo, l), zhi = std::min(zhi, h);
    if (k == 2) {
      // two pieces; keep the one on the tool's nappe (inside [zlo, zhi], which has s >= 0)
      const double a1 = std::max(zlo, -1e300), b1 = std::min(zhi, l);
      const double a2 = std::max(zlo, h), b2 = std::min(zhi, 1e300);
      if (b1 - a1 >= b2 - a2) zlo = a1, zhi = b1;
      else zlo = a2, zhi = b2;
    }
    if (zlo > zhi) return false;
  }
  lo = zlo, hi = zhi;
  return true;
}

/// Conservative test that the point q may lie inside the tool (tip or ball centre c, axis a):
/// the cylinder of radius r and length L contains the cone, and a margin of 1e-6 mm keeps
/// rounding from rejecting a point that line_interval would place on the boundary. Cheap
/// (no square root), so it filters the cells before line_interval is asked for the exact span.
bool maybe_inside(const ToolSolid& tool, const Vec3& c, const Vec3& a, const Vec3& q) {
  constexpr double eps = 1e-6;
  const Vec3 d = q - c;
  const double r = tool.radius + eps;
  if (tool.shape == config::ToolShape::ball) return d.squaredNorm() <= r * r;
  const double s = a.dot(d);
  if (s < -eps || s > tool.length + eps) return false;
  return d.squaredNorm() - s * s <= r * r;
}

/// Max heights over square tiles of a grid, so a tool pose can skip every tile it stays above.
/// Grinding only lowers heights: bounds computed before a trajectory stay upper bounds.
struct TileMax {
  static constexpr int kTile = 16;
  int tx = 0, ty = 0;
  std::vector<float> max;
  template <class Height>
  TileMax(int nx, int ny, Height height)
      : tx((nx + kTile - 1) / kTile), ty((ny + kTile - 1) / kTile),
        max(static_cast<std::size_t>(tx) * static_cast<std::size_t>(ty), -std::numeric_limits<float>::infinity()) {
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) {
        float& m = max[index(i / kTile, j / kTile)];
        m = std::max(m, height(i, j));
      }
  }
  [[nodiscard]] std::size_t index(int ti, int tj) const { return static_cast<std::size_t>(tj) * static_cast<std::size_t>(tx) + static_cast<std::size_t>(ti); }
  [[nodiscard]] float at(int ti, int tj) const { return max[index(ti, tj)]; }
};

/// Calls f(i, j) for the cells of [i0, i1] x [j0, j1] whose tile may reach up to zlo (all of
/// them if `all`).
template <class F>
void for_cells_above(const TileMax& tiles, int i0, int i1, int j0, int j1, double zlo, bool all, F&& f) {
  constexpr int T = TileMax::kTile;
  for (int tj = j0 / T; tj <= j1 / T; ++tj)
    for (int ti = i0 / T; ti <= i1 / T; ++ti) {
      if (!all && tiles.at(ti, tj) < zlo) continue;
      const int jb = std::max(j0, tj * T), je = std::min(j1, tj * T + T - 1);
      const int ib = std::max(i0, ti * T), ie = std::min(i1, ti * T + T - 1);
      for (int j = jb; j <= je; ++j)
        for (int i = ib; i <= ie; ++i) f(i, j);
    }
}

/// The tool's surface for the gouge depth: a profile of (radius, axial) nodes from the tip
/// outward, turned about the tool axis (tool frame). A cylinder: its end face from the centre to
/// the rim, then its side; a cone: its side. Balls need none (the centre distance is exact).
struct ToolProfile {
  std::vector<Eigen::Vector2d> nodes;  ///< at most kMaxNodes
  static constexpr int kAngles = 24;
  static constexpr std::size_t kMaxNodes = 8;

  /// The surface point at profile parameter t (node index, fractional between nodes) and angle a.
  [[nodiscard]] Vec3 point(double t, double a) const {
    Eigen::Vector2d rz = nodes.front();
    if (nodes.size() > 1) {
      t = std::clamp(t, 0.0, static_cast<double>(nodes.size() - 1));
      const auto i = std::min(static_cast<std::size_t>(t), nodes.size() - 2);
      rz = nodes[i] + (t - static_cast<double>(i)) * (nodes[i + 1] - nodes[i]);
    }
    return {rz.x() * std::cos(a), rz.x() * std::sin(a), rz.y()};
  }
};

ToolProfile tool_profile(const ToolSolid& t) {
  ToolProfile p;
  if (t.shape == config::ToolShape::ball) return p;
  if (t.shape == config::ToolShape::cylinder) {
    for (double f : {0.0, 0.35, 0.7, 1.0}) p.nodes.emplace_back(f * t.radius, 0.0);
    for (double f : {0.25, 0.5, 1.0}) p.nodes.emplace_back(t.radius, f * t.length);
  } else {
    for (double f : {0.0, 0.25, 0.5, 0.75, 1.0}) {
      const double z = f * t.length;
      p.nodes.emplace_back(std::min(t.radius, z * t.tan_half), z);
    }
  }
  return p;
}

/// The deepest penetration of the tool's surface into the body (depth = -sdf, > 0 inside) and
/// where: the profile nodes at kAngles angles, then a local search around the deepest of them,
/// first in angle (between two samples a rim of radius r tilted by theta sags
/// r sin(theta) (1 - cos 7.5 deg): 0.19 mm for a 50 mm disc at 60 deg), then along the profile
/// (from a point node, the centre of an end face or a cone's tip, along the direction of the
/// deepest sample of the next node). `at(q)` is -sdf at part-frame point q; `to_part` maps
/// tool-frame points.
template <class Depth, class ToPart>
std::pair<double, Vec3> deepest_point(const ToolProfile& prof, Depth&& at, ToPart&& to_part) {
  const double da = 2 * 3.14159265358979323846 / ToolProfile::kAngles;
  double best = -std::numeric_limits<double>::infinity(), bt = 0, ba = 0;
  Vec3 where = to_part(prof.point(0, 0));
  auto visit = [&](double t, double a) {
    const Vec3 q = to_part(prof.point(t, a));
    const double d = at(q);
    if (d > best) best = d, bt = t, ba = a, where = q;
    return d;
  };
  // the deepest angle of each node, for a point node's search below
  std::array<double, ToolProfile::kMaxNodes> node_depth, node_angle{};
  node_depth.fill(-std::numeric_limits<double>::infinity());
  for (std::size_t i = 0; i < prof.nodes.size(); ++i) {
    const int n = prof.nodes[i].x() <= 1e-9 ? 1 : ToolProfile::kAngles;
    for (int k = 0; k < n; ++k)
      if (const double d = visit(static_cast<double>(i), k * da); d > node_depth[i]) node_depth[i] = d, node_angle[i] = k * da;
  }
  const auto node = static_cast<std::size_t>(bt);
  double a_profile = ba;
  if (prof.nodes[node].x() > 1e-9) {
    const double t0 = bt, a0 = ba;
    for (int s = -8; s <= 8; ++s)
      if (s != 0) visit(t0, a0 + s * da / 8);
    a_profile = ba;
  } else if (node + 1 < prof.nodes.size()) {
    a_profile = node_angle[node + 1];  // a point node has no angle of its own: the next node's deepest
  }
  const double t0 = bt;
  const double last = static_cast<double>(prof.nodes.size() - 1);
  for (int s = -8; s <= 8; ++s) {
    const double t = t0 + s / 8.0;
    if (s != 0 && t >= 0.0 && t <= last) visit(t, a_profile);
  }
  return {best, where};
}

}  // namespace

double GrindResult::removed_mm3() const {
  double b = 0, a = 0;
  for (const auto& r : before) b += r.volume_mm3;
  for (const auto& r : after) a += r.volume_mm3;
  return b - a;
}

double GrindResult::max_gouge_depth_mm() const {
  double d = 0;
  for (const auto& g : gouges) d = std::max(d, g.depth_mm);
  return d;
}

Result<PlannedGrind> grind_by_region(Casting& casting, const Trajectory& trajectory, const config::PartRecipe& recipe,
                                     const GrindOptions& base, const std::string& tool, const CellLimits& limits,
                                     const Progress& progress) {
  if (recipe.tools.empty()) return Error{"sim.no_tool", recipe.source.string() + ": the recipe has no tools"};
  const auto& pts = trajectory.points;
  PlannedGrind out;
  out.total.before = casting.material();
  std::size_t i = 0;
  while (i < pts.size()) {
    RegionGrind run;
    run.region = trajectory.region_of(pts[i]);
    Trajectory sub;
    sub.part_id = trajectory.part_id;
    sub.segment_regions = trajectory.segment_regions;
    while (i < pts.size() && trajectory.region_of(pts[i]) == run.region) sub.points.push_back(pts[i++]);
    run.tool = tool;
    if (run.tool.empty()) {
      for (const auto& r : recipe.regions)
        if (r.name == run.region) run.tool = r.tool;
      if (run.tool.empty()) run.tool = recipe.tools.front().name;
    }
    GrindOptions go = base;
    try {
      go.tool = find_tool(recipe, run.tool);
    } catch (const UserError& e) {
      return Error{"sim.no_tool", e.what()};
    }
    go.noise_seed = base.noise_seed * 0x9E3779B97F4A7C15ULL + i;  // no two (seed, run) pairs share a stream
    auto g = grind(casting, sub, go, limits, progress);
    if (!g) return Error{g.error().code, "grinding " + (run.region.empty() ? std::string("the trajectory") : run.region) +
                                             ": " + g.error().message};
    for (auto gouge : g->gouges) {
      gouge.pose_index += out.total.poses;  // an index into all the runs' poses
      out.total.gouges.push_back(gouge);
    }
    if (g->deepest_body_cut.depth_mm > out.total.deepest_body_cut.depth_mm) {
      out.total.deepest_body_cut = g->deepest_body_cut;
      out.total.deepest_body_cut.pose_index += out.total.poses;
    }
    out.total.poses += g->poses;
    run.result = std::move(*g);
    out.runs.push_back(std::move(run));
  }
  out.total.after = casting.material();
  return out;
}

const config::Tool& find_tool(const config::PartRecipe& recipe, const std::string& name) {
  for (const auto& t : recipe.tools)
    if (t.name == name) return t;
  std::string names;
  for (const auto& t : recipe.tools) names += (names.empty() ? "" : ", ") + t.name;
  throw UserError(recipe.source.string() + ": no tool named \"" + name + "\" (the recipe has: " + names + ")");
}

Result<GrindResult> grind(Casting& casting, const Trajectory& trajectory, const GrindOptions& opt,
                          const CellLimits& limits, const Progress& progress) {
  if (auto s = validate_trajectory(trajectory, limits); !s) return s.error();
  if (!(opt.interpolation_mm > 0) || !std::isfinite(opt.path_noise_mm) || opt.path_noise_mm < 0 ||
      !opt.path_bias_mm.allFinite())
    return Error{"sim.grind_options", "interpolation must be > 0 and noise/bias finite"};
  auto& m = casting.model();
  GrindResult res;
  res.before = m.truth();

  ToolSolid tool;
  tool.shape = opt.tool.shape;
  tool.radius = 0.5 * opt.tool.diameter_mm;
  tool.length = opt.tool.length_mm;
  tool.tan_half = std::tan(deg_to_rad(std::max(1.0, opt.tool.cone_angle_deg)));
  const auto profile = tool_profile(tool);
  const double reach = tool.shape == config::ToolShape::ball ? tool.radius : std::hypot(tool.radius, tool.length);

  // Interpolated commanded poses.
  struct P {
    Vec3 x;
    Quat q;
    bool cut;
  };
  std::vector<P> poses;
  const auto& pts = trajectory.points;
  for (std::size_t i = 0; i < pts.size(); ++i) {
    const auto& b = pts[i].T_base_tool;
    const bool cut = !opt.only_when_spindle_on || pts[i].spindle_rpm > 0;
    if (i == 0) {
      poses.push_back({b.position_mm, b.orientation.normalized(), cut});
      continue;
    }
    const auto& a = pts[i - 1].T_base_tool;
    const double dist = (b.position_mm - a.position_mm).norm();
    const double ang = a.orientation.normalized().angularDistance(b.orientation.normalized());
    const int n = std::max(1, static_cast<int>(std::ceil(std::max(dist, ang * reach) / opt.interpolation_mm)));
    for (int k = 1; k <= n; ++k) {
      const double f = static_cast<double>(k) / n;
      poses.push_back({a.position_mm + f * (b.position_mm - a.position_mm),
                       a.orientation.normalized().slerp(f, b.orientation.normalized()), cut});
    }
  }
  res.poses = poses.size();

  // Tile bounds: a pose only visits the tiles whose highest body or material point it can reach.
  const TileMax body_tiles(m.body.nx, m.body.ny, [&](int i, int j) { return m.body.at(i, j); });
  std::vector<TileMax> material_tiles;
  material_tiles.reserve(m.materials.size());
  for (const auto& mat : m.materials)
    material_tiles.emplace_back(mat.nx, mat.ny, [&](int i, int j) {
      const auto k = mat.index(i, j);
      return mat.z1[k] > mat.z0[k] ? mat.z1[k] : -std::numeric_limits<float>::infinity();
    });

  Rng rng(opt.noise_seed, 0x6121D);
  const Transform T_part_base = m.T_base_part.inverse();
  int bi0 = m.body.nx, bj0 = m.body.ny, bi1 = -1, bj1 = -1;  // dirty body cells
  bool in_gouge = false;
  Gouge current;
  const std::size_t report_every = std::max<std::size_t>(1, poses.size() / 20);
  for (std::size_t pi = 0; pi < poses.size(); ++pi) {
    const auto& p = poses[pi];
    // z, y, x: gcc's order for Vec3(rng.gaussian(), ...), sequenced so every compiler draws it.
    const double nz = rng.gaussian(), ny = rng.gaussian(), nx = rng.gaussian();
    const Vec3 noise(nx, ny, nz);
    const Vec3 x_base = p.x + opt.path_noise_mm * noise + opt.path_bias_mm - opt.tcp_length_error_mm * (p.q * Vec3::UnitZ());
    const Vec3 a = (T_part_base.linear() * (p.q * Vec3::UnitZ())).normalized();
    // The TCP is the tool tip (docs/planning.md): a ball's centre is R up the tool axis from it.
    const Vec3 c = T_part_base * x_base + (tool.shape == config::ToolShape::ball ? Vec3(tool.radius * a) : Vec3(Vec3::Zero()));
    const Eigen::Matrix3d R_part_tool = T_part_base.linear() * p.q.toRotationMatrix();

    // The tool's deepest penetration into a solid (its signed distance) and where: a ball's
    // point toward the solid's nearest surface (a wall beside it too), found only when deeper
    // than `locate_above` (six more distances).
    const auto penetration = [&](const auto& sdf, double locate_above) -> std::pair<double, Vec3> {
      if (tool.shape != config::ToolShape::ball)
        return deepest_point(
            profile, [&](const Vec3& x) { return -sdf(x); }, [&](const Vec3& x) { return Vec3(c + R_part_tool * x); });
      const double d = tool.radius - sdf(c);
      if (!(d > locate_above)) return {d, c};
      constexpr double h = 0.01;
      Vec3 g;
      for (int k = 0; k < 3; ++k) {
        Vec3 dp = Vec3::Zero();
        dp(k) = h;
        g(k) = sdf(c + dp) - sdf(c - dp);
      }
      return {d, c - tool.radius * (g.norm() > 1e-12 ? Vec3(g.normalized()) : Vec3(Vec3::UnitZ()))};
    };
    // Gouge: deepest penetration of the tool surface into the golden body; the same into this
    // casting's own body (its form deviation kept).
    const auto [depth, deepest] =
        penetration([&](const Vec3& x) { return m.golden_sdf(x); }, opt.gouge_threshold_mm);
    const auto [body_depth, body_deepest] =
        m.form_amp_mm == 0.0 ? std::pair<double, Vec3>{depth, deepest}
                             : penetration([&](const Vec3& x) { return m.body_sdf(x); }, res.deepest_body_cut.depth_mm);
    if (body_depth > res.deepest_body_cut.depth_mm) res.deepest_body_cut = Gouge{body_deepest, body_depth, pi};
    if (depth > opt.gouge_threshold_mm) {
      if (!in_gouge || depth > current.depth_mm) current = Gouge{deepest, depth, pi};
      in_gouge = true;
    } else if (in_gouge) {
      res.gouges.push_back(current);
      in_gouge = false;
    }

    if (p.cut) {
      // Tool AABB in the part frame: the cylinder (which holds the cone) is the hull of its two
      // end discs, and a disc of radius r with unit normal a reaches r * sqrt(1 - a_k^2) along
      // axis k; zlo is the tool's lowest point.
      const bool ball = tool.shape == config::ToolShape::ball;
      const Vec3 tip2 = c + a * (ball ? 0.0 : tool.length);
      auto reach_along = [&](double ak) { return ball ? tool.radius : tool.radius * std::sqrt(std::max(0.0, 1.0 - ak * ak)); };
      const double rx = opt.exhaustive ? tool.radius : reach_along(a.x());
      const double ry = opt.exhaustive ? tool.radius : reach_along(a.y());
      const double rz = reach_along(a.z());
      const double xlo = std::min(c.x(), tip2.x()) - rx, xhi = std::max(c.x(), tip2.x()) + rx;
      const double ylo = std::min(c.y(), tip2.y()) - ry, yhi = std::max(c.y(), tip2.y()) + ry;
      // (the reference mode keeps the looser bounds: the tool's bounding box from its radius)
      const double zlo = opt.exhaustive ? std::min(c.z(), tip2.z()) - tool.radius : std::min(c.z(), tip2.z()) - rz - 1e-6;
      for (std::size_t mi = 0; mi < m.materials.size(); ++mi) {
        auto& mat = m.materials[mi];
        const int i0 = std::max(0, static_cast<int>(std::floor((xlo - mat.x0) / mat.pitch)));
        const int i1 = std::min(mat.nx - 1, static_cast<int>(std::floor((xhi - mat.x0) / mat.pitch)));
        const int j0 = std::max(0, static_cast<int>(std::floor((ylo - mat.y0) / mat.pitch)));
        const int j1 = std::min(mat.ny - 1, static_cast<int>(std::floor((yhi - mat.y0) / mat.pitch)));
        if (i0 > i1 || j0 > j1) continue;
        for_cells_above(material_tiles[mi], i0, i1, j0, j1, zlo, opt.exhaustive, [&](int i, int j) {
          const auto k = mat.index(i, j);
          float& z0 = mat.z0[k];
          float& z1 = mat.z1[k];
          if (z1 <= z0 || z1 < zlo) return;
          double lo = 0, hi = 0;
          if (!line_interval(tool, c, a, mat.cx(i), mat.cy(j), lo, hi)) return;
          if (hi <= z0 || lo >= z1) return;
          if (lo <= z0 && hi >= z1) {
            z1 = z0;
          } else if (lo <= z0) {
            z0 = static_cast<float>(hi);
          } else {
            // cut from the top, or through the middle: the sliver above breaks off with it
            z1 = static_cast<float>(lo);
          }
        });
      }
      // The body is cut from the top (what a scanner above would see): only where the surface
      // point (x, y, h) lies in the tool, i.e. lo < h <= hi.
      auto& B = m.body;
      const int i0 = std::max(0, static_cast<int>(std::floor((xlo - B.x0) / B.pitch)));
      const int i1 = std::min(B.nx - 1, static_cast<int>(std::floor((xhi - B.x0) / B.pitch)));
      const int j0 = std::max(0, static_cast<int>(std::floor((ylo - B.y0) / B.pitch)));
      const int j1 = std::min(B.ny - 1, static_cast<int>(std::floor((yhi - B.y0) / B.pitch)));
      if (i0 <= i1 && j0 <= j1)
        for_cells_above(body_tiles, i0, i1, j0, j1, zlo, opt.exhaustive, [&](int i, int j) {
          float& h = B.at(i, j);
          if (h <= kNoPart || h < zlo) return;
          if (!opt.exhaustive && !maybe_inside(tool, c, a, Vec3(B.cx(i), B.cy(j), h))) return;
          double lo = 0, hi = 0;
          if (!line_interval(tool, c, a, B.cx(i), B.cy(j), lo, hi)) return;
          if (lo < h && hi >= h) {
            h = static_cast<float>(std::max(0.0, lo));
            bi0 = std::min(bi0, i), bj0 = std::min(bj0, j), bi1 = std::max(bi1, i), bj1 = std::max(bj1, j);
          }
        });
      // material changes the surface too
      bi0 = std::min(bi0, i0), bj0 = std::min(bj0, j0), bi1 = std::max(bi1, i1), bj1 = std::max(bj1, j1);
    }
    if (progress && (pi % report_every == 0 || pi + 1 == poses.size())) progress(pi + 1, poses.size(), "grinding");
  }
  if (in_gouge) res.gouges.push_back(current);
  if (bi1 >= 0) m.rebuild_surface(bi0 - 1, bj0 - 1, bi1 + 2, bj1 + 2);
  for (auto& g : res.gouges) m.gouges.push_back(g);
  res.after = m.truth();
  return res;
}

}  // namespace fettle::sim
