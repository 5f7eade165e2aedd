// Per-region grinding trajectories (ring / circle flash, riser, straight flash), region
// ordering, assembly with approach / retract moves, and validation.
#include "fettle/planning/planner.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <map>
#include <numeric>
#include <optional>
#include <sstream>
#include <unordered_map>

#include <Eigen/Eigenvalues>

#include "fettle/config/vision.hpp"

namespace fettle::planning {
namespace {

constexpr std::size_t kMinRegionPoints = 20;
constexpr double kBackoffTolMm = 0.002;  ///< a back-off leaves at most this much more than needed
constexpr double kProbeNearMm = 2.0;     ///< tool_penetration_mm: probes are exact at least this near
/// validate(): a pose nearer the template than the clearance by more than this is a gouge. The
/// planner checks every pose and move sample as validation does and backs off to within
/// kBackoffTolMm of the clearance; the same pose in the base frame differs only by rounding.
constexpr double kValidateTolMm = 0.005;
/// tool_penetration_mm: samples deeper by less than this are ties, and the first one wins. A flat
/// end face over a flat face has many equally deep samples; were rounding to pick among them,
/// the same pose in the part and the base frame would be searched around different samples and
/// read differently beside an edge, where the signed-distance grid is uneven.
constexpr double kTieMm = 1e-9;
/// tool_penetration_mm: a cylinder's samples this near the decision are searched around.
constexpr double kRefineMarginMm = 0.5;
/// plan_straight: a face under a straight flash's pass sloping off the line's normal by up to this
/// is the casting's face (its form deviation, 0.5 mm over a 90 mm wave, slopes it 1-2 degrees);
/// steeper is a wall or a boss the pass ends at.
constexpr double kMaxFaceSlopeRad = 10.0 * std::numbers::pi / 180.0;
/// A riser's rows overlap by at least a fifth of the tool's diameter: the path's noise and a
/// wheel worn a little more than the cell predicts leave no ridge between two rows.
constexpr double kMaxStepoverShare = 0.8;

double face_band_mm(const RegionInput& in) { return config::face_band_mm(in.form_deviation_mm); }

Error region_error(const std::string& region, const std::string& code, const std::string& what) {
  return Error{"planning." + code, "region '" + region + "': " + what};
}

std::string fmt(double v, int precision = 2) {
  std::ostringstream os;
  os.setf(std::ios::fixed);
  os.precision(precision);
  os << v;
  return os.str();
}

std::string fmt(const Vec3& v) { return "(" + fmt(v.x()) + ", " + fmt(v.y()) + ", " + fmt(v.z()) + ")"; }

double tool_radius(const config::Tool& tool) { return tool.diameter_mm / 2.0; }

/// Unit vector perpendicular to `a`.
Vec3 any_perpendicular(const Vec3& a) {
  const Vec3 ref = std::abs(a.x()) < 0.9 ? Vec3::UnitX() : Vec3::UnitY();
  return (ref - ref.dot(a) * a).normalized();
}

Vec3 sdf_gradient(const SignedDistance& sdf, const Vec3& p, double h = 0.5) {
  Vec3 g;
  for (int k = 0; k < 3; ++k) {
    Vec3 dp = Vec3::Zero();
    dp(k) = h;
    g(k) = (sdf(p + dp) - sdf(p - dp)) / (2 * h);
  }
  return g;
}

/// s such that sdf(X0 + s·dir) = level, searching from s = 0 along ±dir (dir points into the
/// body, where sdf decreases). nullopt when no crossing within max_mm.
std::optional<double> find_level(const SignedDistance& sdf, const Vec3& X0, const Vec3& dir, double level,
                                 double max_mm = 60.0, double step_mm = 0.5) {
  auto g = [&](double s) { return sdf(X0 + s * dir) - level; };
  const double g0 = g(0.0);
  if (g0 == 0.0) return 0.0;
  const double sign = g0 > 0 ? 1.0 : -1.0;  // march into the body when outside the level set
  double a = 0.0, ga = g0;
  for (double s = step_mm; s <= max_mm + 1e-9; s += step_mm) {
    const double b = sign * s;
    const double gb = g(b);
    if ((ga > 0) != (gb > 0)) {
      double lo = a, hi = b, glo = ga;
      for (int it = 0; it < 30; ++it) {
        const double mid = 0.5 * (lo + hi);
        const double gm = g(mid);
        if ((gm > 0) == (glo > 0)) lo = mid, glo = gm;
        else hi = mid;
      }
      return 0.5 * (lo + hi);
    }
    a = b, ga = gb;
  }
  return std::nullopt;
}

Transform frame_from(const Vec3& origin, const Vec3& z_axis, const Vec3& x_hint) {
  const Vec3 z = z_axis.normalized();
  Vec3 x = x_hint - x_hint.dot(z) * z;
  x = x.norm() > 1e-9 ? x.normalized() : any_perpendicular(z);
  const Vec3 y = z.cross(x);
  Transform T = Transform::Identity();
  T.linear().col(0) = x;
  T.linear().col(1) = y;
  T.linear().col(2) = z;
  T.translation() = origin;
  return T;
}

/// Moves the tool along `dir` by the smallest distance (≤ max_mm, to within kBackoffTolMm) at
/// which it keeps at least `clearance_mm` from the template. Returns false if there is none.
/// The tool must move at least as far as it still cuts (a distance changes by at most the
/// move), so each step is the remaining penetration divided by the rate it fell at on the last
/// step (a secant step, a few per cent long so that it lands clear), but never shorter than the
/// penetration nor longer than 0.25 mm beyond it: the penetration is not monotonic along `dir`
/// (backing away from one wall can run into another feature), and longer steps could jump a
/// clear position. Where the penetration barely falls it takes that longest step. The last bracket,
/// from the last cutting position plus its penetration, is halved down to kBackoffTolMm. The
/// bench's planning runs made a third of the evaluations of 0.25 mm steps and 12 halvings.
bool back_off(const config::Tool& tool, Transform& T_part_tool, const SignedDistance& sdf, const Vec3& dir,
              double clearance_mm, double max_mm) {
  auto pen = [&](double s) {
    Transform T = T_part_tool;
    T.translation() += s * dir;
    return tool_penetration_mm(tool, T, sdf, nullptr, clearance_mm) + clearance_mm;
  };
  double p = pen(0.0);
  if (p <= 1e-6) return true;
  constexpr double kStep = 0.25, kMinRate = 0.02;
  double lo = 0.0, hi = -1.0, rate = 1.0;
  while (hi < 0.0 && lo < max_mm) {
    // where the penetration barely falls (the rate at its floor) the longest step allowed: a
    // secant step there would crawl by micrometres
    const double step = rate <= kMinRate ? p + kStep : std::max(p, std::min(1.05 * p / rate + 1e-4, p + kStep));
    const double s = std::min(lo + step, max_mm);
    const double q = pen(s);
    if (q <= 1e-6) {
      hi = s;
    } else {
      rate = std::clamp((p - q) / (s - lo), kMinRate, 1.0);
      lo = s, p = q;
    }
  }
  if (hi < 0.0) return false;
  lo = std::min(hi, lo + p);  // nothing nearer than lo + p can be clear (hi is the tested answer)
  while (hi - lo > kBackoffTolMm) {
    const double mid = 0.5 * (lo + hi);
    (pen(mid) > 1e-6 ? lo : hi) = mid;
  }
  T_part_tool.translation() += hi * dir;
  return true;
}

/// Validation also samples the moves between points (for_each_move_sample). Where the sampled
/// template dips between two clear points, a move can still cut a little: push both ends of
/// such a move out along their retreat directions until every sample of it keeps
/// `clearance_mm` too, and every pose so pushed still keeps it itself (beside an edge the
/// sampled template is uneven, and a pose pushed up can read nearer than where it was).
/// Returns the move (i - 1, i) as i when that takes more than max_mm or more rounds than a dip
/// does (a steep move up onto a higher feature: its ends creep up by the cut's depth a round),
/// nullopt when every move keeps the clearance.
std::optional<std::size_t> clear_moves(const config::Tool& tool, std::vector<Transform>& poses,
                                       const std::vector<Vec3>& retreats, const SignedDistance& sdf,
                                       double clearance_mm, double max_mm) {
  constexpr int kRounds = 25;
  std::vector<double> pushed(poses.size(), 0.0);
  std::vector<std::size_t> pushed_by(poses.size(), 1);  // the move that last pushed the pose
  std::size_t last_cut = 1;
  for (int round = 0; round < kRounds; ++round) {
    bool moved = false;
    for (std::size_t i = 0; i < poses.size(); ++i) {
      if (pushed[i] <= 0.0) continue;  // as placed (backed off by the caller)
      const Vec3 at = poses[i].translation();
      if (!back_off(tool, poses[i], sdf, retreats[i], clearance_mm, max_mm - pushed[i])) return pushed_by[i];
      if (const double d = (poses[i].translation() - at).norm(); d > 0.0) pushed[i] += d, moved = true;
    }
    for (std::size_t i = 1; i < poses.size(); ++i) {
      double worst = -std::numeric_limits<double>::infinity();
      for_each_move_sample(Pose::from_transform(poses[i - 1]), Pose::from_transform(poses[i]), [&](const Pose& m) {
        worst = std::max(worst, tool_penetration_mm(tool, m.to_transform(), sdf, nullptr, clearance_mm) + clearance_mm);
        return true;
      });
      if (worst <= 1e-6) continue;
      const double step = worst + 0.01;
      for (std::size_t j : {i - 1, i}) {
        if (pushed[j] + step > max_mm) return i;
        poses[j].translation() += step * retreats[j];
        pushed[j] += step;
        pushed_by[j] = i;
      }
      last_cut = i;
      moved = true;
    }
    if (!moved) return std::nullopt;
  }
  return last_cut;
}

TrajectoryPoint make_point(const Transform& T_base_part, const Transform& T_part_tool, double speed, double rpm,
                           int segment, MoveKind kind) {
  TrajectoryPoint p;
  p.T_base_tool = Pose::from_transform(T_base_part * T_part_tool);
  p.speed_mm_s = speed;
  p.spindle_rpm = rpm;
  p.segment = segment;
  p.kind = kind;
  return p;
}

// --- ring / circle flash ----------------------------------------------------------------------

/// A flash loop's ring: the parting plane, the ellipse on it and its 2-D basis's origin.
struct LoopFit {
  Plane plane;
  Conic conic;
  Vec3 origin;
};

/// The ring fitted to the region's flash (the parting plane through the fin standing out of a
/// template wall, the ellipse on it), checked to outline a ring in the region's ROI.
Result<LoopFit> fit_loop(const RegionInput& in, const PlannerSettings& settings) {
  const auto& region = *in.region;
  RansacOptions plane_opts = settings.ransac;
  plane_opts.inlier_mm = std::max(plane_opts.inlier_mm, 1.0);
  // A parting line's fin stands out of a wall the parting plane cuts: the template surface
  // nearest a fin point faces along the plane (its normal within 30 degrees of it). Excess on a
  // face the plane would lie on is not flash: the body's form deviation read as excess (0.5 mm
  // over the body's top under a flange) outnumbers the fin and drew the plane, and then the ring,
  // onto that face (test RingPlan.FormDeviationOnTheFaceBelowDoesNotTakeThePartingPlane).
  std::vector<Vec3> wall_normal(in.excess_points_part.size());
  for (std::size_t i = 0; i < wall_normal.size(); ++i)
    wall_normal[i] = sdf_gradient(in.template_sdf, in.excess_points_part[i]);
  const auto against_a_wall = [&](std::size_t i, const Vec3& n) {
    return std::abs(wall_normal[i].dot(n)) <= 0.5 * std::max(1e-9, wall_normal[i].norm());
  };
  auto plane = fit_plane_ransac(in.excess_points_part, plane_opts, against_a_wall);
  if (!plane)
    return region_error(region.name, "fit",
                        "no parting plane could be fitted to the " + std::to_string(in.excess_points_part.size()) +
                            " excess points standing out of a template wall; check the region's ROI and the scan");
  if (plane->normal.z() < 0) plane->normal = -plane->normal, plane->d = -plane->d;
  // The ring is fitted to the flash on the parting plane only: excess elsewhere in the ROI
  // (the body's form deviation read as excess, 15 mm below a flange's fin) pulled the ellipse
  // off the flange when the camera saw a short arc of fin.
  std::vector<Vec3> pts;
  pts.reserve(in.excess_points_part.size());
  for (std::size_t i = 0; i < in.excess_points_part.size(); ++i)
    if (std::abs(plane->signed_distance(in.excess_points_part[i])) <= plane_opts.inlier_mm &&
        against_a_wall(i, plane->normal))
      pts.push_back(in.excess_points_part[i]);
  if (pts.size() < 5)
    return region_error(region.name, "fit",
                        "only " + std::to_string(pts.size()) +
                            " excess points stand out of a template wall on the parting plane: no flash to fit a ring to");
  const Vec3 w = plane->normal;
  Vec3 centroid = Vec3::Zero();
  for (const auto& p : pts) centroid += p;
  centroid /= static_cast<double>(pts.size());
  const Vec3 origin = plane->project(centroid);
  const Vec3 e1 = any_perpendicular(w);
  const Vec3 e2 = w.cross(e1);
  std::vector<Eigen::Vector2d> uv;
  uv.reserve(pts.size());
  for (const auto& p : pts) uv.emplace_back((p - origin).dot(e1), (p - origin).dot(e2));
  RansacOptions conic_opts = settings.ransac;
  conic_opts.inlier_mm = std::max(conic_opts.inlier_mm, settings.flash_band_mm);
  auto conic = fit_ellipse_ransac(uv, conic_opts);
  if (!conic || !conic->is_ellipse())
    return region_error(region.name, "fit",
                        "no ellipse could be fitted to the flash points projected onto the parting plane; "
                        "check the region's ROI and the scan");
  const auto geom = ellipse_geometry(*conic);
  if (!geom) return region_error(region.name, "fit", "the fitted conic is not an ellipse");
  // A ring fitted to a short arc is ill-posed (a re-grind's leftover pieces, a region the camera
  // barely sees): five points on 40 degrees fit an ellipse of any size. The flash must outline
  // the ring (round, on a third of it at least: a fin with gaps, partly hidden, still does), and
  // the ring must lie in the region's ROI, before a tool is put to it.
  {
    constexpr int kSectors = 36;
    std::array<bool, kSectors> seen{};
    for (const auto& q : uv) {
      const Eigen::Vector2d d = q - geom->center;
      const double a = std::atan2(d.y(), d.x()) + std::numbers::pi;
      seen[static_cast<std::size_t>(std::clamp(static_cast<int>(a / (2 * std::numbers::pi) * kSectors), 0, kSectors - 1))] = true;
    }
    const auto covered = std::count(seen.begin(), seen.end(), true);
    const Vec3 c3 = origin + geom->center.x() * e1 + geom->center.y() * e2;
    const Vec3 roi_c(region.roi_center_mm[0], region.roi_center_mm[1], region.roi_center_mm[2]);
    const Vec3 roi_half = 0.5 * Vec3(region.roi_size_mm[0], region.roi_size_mm[1], region.roi_size_mm[2]);
    if (geom->semi_minor < 0.5 * geom->semi_major)
      return region_error(region.name, "fit",
                          "the ellipse fitted to the " + std::to_string(pts.size()) + " flash points is elongated (" +
                              fmt(geom->semi_major) + " x " + fmt(geom->semi_minor) +
                              " mm): the points do not outline a ring (too short an arc?); "
                              "check that the scan sees the flash all round");
    if (3 * covered < kSectors)
      return region_error(region.name, "fit",
                          std::to_string(pts.size()) + " flash points cover " + std::to_string(covered * 10) +
                              " of the ring's 360 degrees: too short an arc to fit the ring (at least 120 degrees); "
                              "check that the scan sees the flash all round");
    if (((c3 - roi_c).cwiseAbs().array() > roi_half.array()).any() || geom->semi_major > roi_half.head<2>().norm())
      return region_error(region.name, "fit",
                          "the fitted ring (centre " + fmt(c3) + ", semi-axes " + fmt(geom->semi_major) + " x " +
                              fmt(geom->semi_minor) + " mm, part frame) does not lie in the region's ROI; "
                              "check the ROI and the scan");
  }
  return LoopFit{*plane, *conic, origin};
}

Result<RegionPlan> plan_flash_loop(const RegionInput& in, const PlannerSettings& settings, RegionPlan plan) {
  const auto& region = *in.region;
  const auto& tool = *in.tool;
  // A re-grind follows the first plan's ring (RegionInput::first): the fin's leftover pieces on
  // a short arc fit no ring, or a wrong one. The contact points come from the template's wall
  // inward of the ring either way.
  const bool again = in.first != nullptr && in.first->type == region.type && in.first->conic.is_ellipse();
  auto fit = again ? Result<LoopFit>(LoopFit{in.first->plane, in.first->conic, in.first->conic_origin})
                   : fit_loop(in, settings);
  if (!fit) return fit.error();
  plan.plane = fit->plane;
  plan.conic = fit->conic;
  plan.conic_origin = fit->origin;
  const Vec3 w = plan.plane.normal;
  const Vec3 origin = plan.conic_origin;
  const Vec3 e1 = any_perpendicular(w);
  const Vec3 e2 = w.cross(e1);
  const Conic& conic = plan.conic;
  const auto geom = ellipse_geometry(conic);
  if (!geom) return region_error(region.name, "fit", "the fitted conic is not an ellipse");

  // arc length along the ellipse, then contact points at the configured spacing (≤ 1 mm)
  const double spacing = std::clamp(region.point_spacing_mm, 0.05, 1.0);
  const int dense = std::max(2000, static_cast<int>(2 * std::numbers::pi * geom->semi_major / 0.05));
  std::vector<double> cum(static_cast<std::size_t>(dense) + 1, 0.0);
  for (int k = 1; k <= dense; ++k) {
    const double t0 = 2 * std::numbers::pi * (k - 1) / dense, t1 = 2 * std::numbers::pi * k / dense;
    cum[static_cast<std::size_t>(k)] = cum[static_cast<std::size_t>(k) - 1] + (geom->point(t1) - geom->point(t0)).norm();
  }
  const double perimeter = cum.back();
  const double total = perimeter + std::max(0.0, region.overlap_mm);
  const auto count = static_cast<std::size_t>(std::ceil(total / spacing));
  const double R = tool_radius(tool);
  const double theta = deg_to_rad(region.chamfer_deg);
  std::vector<Transform> poses;
  std::vector<Vec3> normals, retreats;
  poses.reserve(count + 1);
  for (std::size_t i = 0; i <= count; ++i) {
    // travel along t = n × w, i.e. clockwise about w: walk the parameter backwards
    const double s = std::fmod(perimeter - std::min(total, static_cast<double>(i) * spacing) + 2 * perimeter, perimeter);
    const auto it = std::lower_bound(cum.begin(), cum.end(), s);
    const auto k = static_cast<std::size_t>(std::clamp<std::ptrdiff_t>(it - cum.begin(), 1, dense));
    const double f = (s - cum[k - 1]) / std::max(1e-12, cum[k] - cum[k - 1]);
    const double t = 2 * std::numbers::pi * (static_cast<double>(k) - 1 + f) / dense;
    const Eigen::Vector2d q = geom->point(t);
    Eigen::Vector2d g = conic.gradient(q);
    if ((q - geom->center).dot(g) < 0) g = -g;  // outward
    const Vec3 P0 = origin + q.x() * e1 + q.y() * e2;
    const Vec3 n = (g.x() * e1 + g.y() * e2).normalized();
    const auto s_in = find_level(in.template_sdf, P0, -n, region.allowance_mm, 3.0 * settings.flash_band_mm + 20.0);
    if (!s_in)
      return region_error(region.name, "no_surface",
                          "no template surface inward of contact point " + std::to_string(i) + " at " + fmt(P0) +
                              " (part frame); the ellipse does not surround the part's edge");
    const Vec3 P = P0 - *s_in * n;
    Transform T_part_tool;
    Vec3 retreat;
    if (region.contact == config::FlashContact::periphery) {
      // the side of the tool against the wall at P, tool axis along w, the tool's height
      // centred on the parting plane (a ball: its equator)
      const double half = tool.shape == config::ToolShape::ball ? R : 0.5 * std::max(0.0, tool.length_mm);
      T_part_tool = frame_from(P + R * n - half * w, w, n.cross(w));
      retreat = n;
    } else {
      const ChamferPose cp = chamfer_pose(P, n, w, R, theta);
      T_part_tool = cp.T_part_tool;
      retreat = cp.tool_axis;
    }
    if (!back_off(tool, T_part_tool, in.template_sdf, retreat, region.allowance_mm, settings.max_backoff_mm)) {
      Transform T_far = T_part_tool;
      T_far.translation() += settings.max_backoff_mm * retreat;
      Vec3 where = Vec3::Zero();
      const double depth = tool_penetration_mm(tool, T_far, in.template_sdf, &where, region.allowance_mm);
      return region_error(region.name, "gouge",
                          "contact point " + std::to_string(i) + " at " + fmt(P) +
                              ": the tool cannot reach it without cutting the template (backed off " +
                              fmt(settings.max_backoff_mm) + " mm, the tool still reaches " + fmt(depth + region.allowance_mm) +
                              " mm into the template and its allowance at " + fmt(where) +
                              "); use a smaller tool, another chamfer_deg or contact");
    }
    poses.push_back(T_part_tool);
    normals.push_back(n);
    retreats.push_back(retreat);
  }
  if (const auto cut = clear_moves(tool, poses, retreats, in.template_sdf, region.allowance_mm, settings.max_backoff_mm))
    return region_error(region.name, "gouge",
                        "the move between contact points " + std::to_string(*cut - 1) + " and " + std::to_string(*cut) +
                            " at " + fmt(poses[*cut - 1].translation()) +
                            " cannot keep the allowance from the template (pushed out up to " +
                            fmt(settings.max_backoff_mm) + " mm); use a smaller tool, another chamfer_deg or contact");
  const double feed = region.feed_mm_s, rpm = region.spindle_rpm;
  auto lead = [&](const Transform& T, const Vec3& n) {
    Transform L = T;
    L.translation() += settings.lead_mm * n;
    return L;
  };
  plan.points.push_back(make_point(in.T_base_part, lead(poses.front(), normals.front()), feed, rpm, 0, MoveKind::grind));
  for (const auto& T : poses) plan.points.push_back(make_point(in.T_base_part, T, feed, rpm, 0, MoveKind::grind));
  plan.points.push_back(make_point(in.T_base_part, lead(poses.back(), normals.back()), feed, rpm, 0, MoveKind::grind));
  plan.segments = 1;
  return plan;
}

// --- riser and straight flash: layered passes ----------------------------------------------------

struct LayerFrame {
  Vec3 up;       ///< removal direction (template face normal)
  Vec3 base;     ///< a point on the template face
};

std::optional<LayerFrame> layer_frame(const RegionInput& in, const Vec3& at) {
  Vec3 up = sdf_gradient(in.template_sdf, at);
  if (!(up.norm() > 0.5)) return std::nullopt;
  up.normalize();
  const auto s = find_level(in.template_sdf, at, -up, 0.0, 80.0);
  if (!s) return std::nullopt;
  return LayerFrame{up, at - *s * up};
}

/// Air points lifting off after `from` and coming down onto `to` (part frame tool poses), at
/// least lift_mm up and high enough that the move between them keeps the region's allowance
/// from the template (a feature between the two, e.g. a wall beside a riser's pad). The way up
/// and the way down must keep it too (nothing overhangs the two poses). An error when no lift
/// up to kMaxLiftMm does, naming the move and where the template is in the way.
std::optional<Error> add_lift(RegionPlan& plan, const RegionInput& in, const Transform& from, const Transform& to,
                              const Vec3& up, double lift_mm, double speed, double rpm, int segment) {
  constexpr double kMaxLiftMm = 300.0;
  const double clearance = in.region->allowance_mm;
  double lift = lift_mm;
  auto lifted = [&](const Transform& T) {
    Transform L = T;
    L.translation() += lift * up;
    return L;
  };
  // a leg cuts where it comes nearer than the allowance by more than a back-off's tolerance (a
  // pose backed off beside a wall parallel to `up` keeps its clearance all the way up, give or
  // take the grid's rounding)
  auto cuts = [&](const Transform& T) {
    return tool_penetration_mm(*in.tool, T, in.template_sdf, nullptr, clearance) + clearance > kBackoffTolMm;
  };
  auto refused = [&](const std::string& what) {
    return region_error(in.region->name, "gouge",
                        "the air move lifting off at " + fmt(from.translation()) + " and coming down onto " +
                            fmt(to.translation()) + " (part frame): " + what);
  };
  for (int round = 0;; ++round) {
    const Transform a = lifted(from), b = lifted(to);
    double need = 0.0;  // how much higher the worst sample of the move between them must be
    Vec3 blocked = Vec3::Zero();
    auto check = [&](const Pose& m) {
      Transform T = m.to_transform();
      const Vec3 at = T.translation();
      const double raise = back_off(*in.tool, T, in.template_sdf, up, clearance, kMaxLiftMm)
                               ? (T.translation() - at).dot(up)
                               : kMaxLiftMm;
      if (raise > need) need = raise, blocked = at;
      return true;
    };
    check(Pose::from_transform(a));
    check(Pose::from_transform(b));
    for_each_move_sample(Pose::from_transform(a), Pose::from_transform(b), check);
    if (need <= 0.0) break;
    if (lift >= kMaxLiftMm)
      return refused("no lift up to " + fmt(lift, 0) + " mm keeps the allowance over the template (at " + fmt(blocked) +
                     ")");
    // a millimetre more than the worst sample needs; the last round tries the highest lift
    lift = round >= 4 ? kMaxLiftMm : std::min(kMaxLiftMm, lift + need + 1.0);
  }
  // the ways up and down, sampled as validation samples them
  for (const bool going_up : {true, false}) {
    const Pose lo = Pose::from_transform(going_up ? from : lifted(to));
    const Pose hi = Pose::from_transform(going_up ? lifted(from) : to);
    std::optional<Vec3> hit;
    for_each_move_sample(lo, hi, [&](const Pose& m) {
      if (cuts(m.to_transform())) hit = m.position_mm;
      return !hit;
    });
    if (hit)
      return refused(std::string("the template overhangs it: on the way ") + (going_up ? "up" : "down") +
                     " the tool reaches it at " + fmt(*hit));
  }
  plan.points.push_back(make_point(in.T_base_part, lifted(from), speed, rpm, segment, MoveKind::air));
  plan.points.push_back(make_point(in.T_base_part, lifted(to), speed, rpm, segment, MoveKind::air));
  return std::nullopt;
}

Result<RegionPlan> plan_riser(const RegionInput& in, const PlannerSettings& settings, RegionPlan plan) {
  const auto& region = *in.region;
  const auto& tool = *in.tool;
  const auto& pts = in.excess_points_part;
  Vec3 centroid = Vec3::Zero();
  for (const auto& p : pts) centroid += p;
  centroid /= static_cast<double>(pts.size());
  const auto frame = layer_frame(in, centroid);
  if (!frame) return region_error(region.name, "no_surface", "no template face below the riser points at " + fmt(centroid));
  std::vector<double> heights;
  heights.reserve(pts.size());
  for (const auto& p : pts) heights.push_back(in.template_sdf(p));
  plan.max_excess_mm = *std::max_element(heights.begin(), heights.end());
  plan.layer_levels_mm = layer_levels(heights, region.depth_per_pass_mm, region.allowance_mm);
  if (plan.layer_levels_mm.empty()) return plan;

  const Vec3 up = frame->up;
  const Vec3 e1 = any_perpendicular(up);
  const Vec3 e2 = up.cross(e1);
  double amin = 1e300, amax = -1e300, bmin = 1e300, bmax = -1e300;
  for (const auto& p : pts) {
    const double a = (p - frame->base).dot(e1), b = (p - frame->base).dot(e2);
    amin = std::min(amin, a), amax = std::max(amax, a), bmin = std::min(bmin, b), bmax = std::max(bmax, b);
  }
  amin -= region.margin_mm, amax += region.margin_mm, bmin -= region.margin_mm, bmax += region.margin_mm;
  // Rows at most kMaxStepoverShare of the tool's diameter apart: a worn wheel (ProcessOptions::
  // tool_wear_mm) narrower than the recipe's stepover would leave a ridge between two rows
  // (test RiserPlan.AWornWheelsRowsCloseUp).
  const double narrowest = std::max(0.05, tool_radius(tool) - std::max(0.0, in.tool_worn_more_mm));
  const double step = std::max(0.1, std::min(region.stepover_mm, kMaxStepoverShare * 2.0 * narrowest));
  const double spacing = std::clamp(region.point_spacing_mm, 0.05, step);
  const auto rows = static_cast<int>(std::ceil((bmax - bmin) / step - 1e-9)) + 1;
  const auto cols = static_cast<int>(std::ceil((amax - amin) / spacing - 1e-9)) + 1;
  const double feed = region.feed_mm_s, rpm = region.spindle_rpm;
  const double air = std::min(settings.air_speed_mm_s, settings.max_speed_mm_s);
  const double lift = plan.max_excess_mm + 5.0;
  // Footprint points in the layer plane: a raster point whose tool covers none of them grinds
  // only the margin.
  std::vector<Eigen::Vector2d> footprint;
  footprint.reserve(pts.size());
  for (const auto& p : pts) footprint.emplace_back((p - frame->base).dot(e1), (p - frame->base).dot(e2));
  const double R = tool_radius(tool);
  // the highest excess point under the tool at (a, b) in the layer plane, if any
  auto material_under = [&](double a, double b) {
    std::optional<std::size_t> best;
    for (std::size_t k = 0; k < footprint.size(); ++k)
      if ((footprint[k] - Eigen::Vector2d(a, b)).squaredNorm() <= R * R && (!best || heights[k] > heights[*best]))
        best = k;
    return best;
  };
  // The layers follow the casting's face (the template moved onto it) under each raster point,
  // not its height under the centroid alone: under a riser 40 mm wide a sand-cast face curves by
  // up to 0.4 mm, and a flat last layer left that much over its low side (test
  // RiserPlan.TheLastLayerFollowsTheCastingsFaceUnderTheRiser). A face farther from the
  // centroid's than twice the form deviation is another feature (a wall's top, the fixture):
  // there the layer stays flat and back_off lifts it where it must.
  const double follow = face_band_mm(in);
  std::vector<double> face_dz(static_cast<std::size_t>(rows) * static_cast<std::size_t>(cols), 0.0);
  if (follow > 0.0)
    for (int r = 0; r < rows; ++r)
      for (int c = 0; c < cols; ++c) {
        const double a = std::min(amax, amin + c * spacing), b = std::min(bmax, bmin + r * step);
        const double top = follow + 1.0;  // the search starts this far over the centroid's face
        const auto d = find_level(in.template_sdf, frame->base + a * e1 + b * e2 + top * up, -up, 0.0, 2.0 * top, 0.25);
        if (d && std::abs(top - *d) <= follow) face_dz[static_cast<std::size_t>(r * cols + c)] = top - *d;
      }
  int segment = 0;
  for (double level : plan.layer_levels_mm) {
    // The bounding box's corners can reach over a neighbouring feature the tool cannot pass
    // (a wall beside the pad): a raster point there that covers no material, or none higher
    // than leave_unreachable_mm (noise at the pad's edge) or the casting's form deviation (its
    // own face beside the pad), is left out (the highest such
    // material in left_mm) and the tool lifts over the gap; higher material is an error.
    std::vector<std::pair<Transform, bool>> layer;  // pose, lifted onto (after a left-out point or an uncleared move)
    bool gap = false;
    for (int r = 0; r < rows; ++r) {
      const double b = std::min(bmax, bmin + r * step);
      for (int c = 0; c < cols; ++c) {
        const int cc = (r % 2 == 0) ? c : cols - 1 - c;  // boustrophedon raster
        const double a = std::min(amax, amin + cc * spacing);
        const double dz = face_dz[static_cast<std::size_t>(r * cols + cc)];
        Transform T = frame_from(frame->base + a * e1 + b * e2 + (level + dz) * up, up, (r % 2 == 0) ? e1 : Vec3(-e1));
        if (!back_off(tool, T, in.template_sdf, up, region.allowance_mm, settings.max_backoff_mm)) {
          const auto k = material_under(a, b);
          if (!k || heights[*k] <= std::max(settings.leave_unreachable_mm, in.form_deviation_mm)) {
            if (k && heights[*k] > plan.left_mm) plan.left_mm = heights[*k], plan.left_at = pts[*k];
            gap = true;
            continue;
          }
          return region_error(region.name, "gouge",
                              "layer " + std::to_string(segment) + " raster point at " + fmt(T.translation()) +
                                  ": the tool cannot reach the riser material there without cutting the template "
                                  "(excess point at " + fmt(pts[*k]) + ", " + fmt(heights[*k]) +
                                  " mm above the template, part frame)");
        }
        layer.emplace_back(T, gap && !layer.empty());
        gap = false;
      }
    }
    if (layer.empty())
      return region_error(region.name, "gouge",
                          "layer " + std::to_string(segment) + ": no raster point lets the tool pass without cutting the template");
    // The moves between directly connected raster points (a row, the step to the next row) keep
    // the allowance too, as validation samples them: beside the pad's edge a sample between two
    // clear points can come nearer than they do, and clear_moves pushes the run up out of such a
    // dip (test RiserPlan.LayersCoverTheFootprintAndLeaveTheAllowance). A move it cannot clear
    // (steeply up onto a higher feature the raster reaches over) becomes a gap the tool lifts
    // over, and the run is cleared again in two (test RiserPlan.AMoveUpOntoAHigherBlockBesideThePadIsLiftedOver).
    for (std::size_t k0 = 0; k0 < layer.size();) {
      std::size_t k1 = k0 + 1;
      while (k1 < layer.size() && !layer[k1].second) ++k1;
      std::vector<Transform> run;
      for (std::size_t k = k0; k < k1; ++k) run.push_back(layer[k].first);
      if (const auto cut = clear_moves(tool, run, std::vector<Vec3>(run.size(), up), in.template_sdf,
                                       region.allowance_mm, settings.max_backoff_mm)) {
        layer[k0 + *cut].second = true;
        continue;
      }
      for (std::size_t k = k0; k < k1; ++k) layer[k].first = run[k - k0];
      k0 = k1;
    }
    if (segment > 0) {
      const Transform from = plan.points.empty() ? layer.front().first
                                                 : in.T_base_part.inverse() * plan.points.back().T_base_tool.to_transform();
      if (auto e = add_lift(plan, in, from, layer.front().first, up, lift, air, rpm, segment)) return *e;
    }
    for (std::size_t k = 0; k < layer.size(); ++k) {
      if (layer[k].second)
        if (auto e = add_lift(plan, in, layer[k - 1].first, layer[k].first, up, lift, air, rpm, segment)) return *e;
      plan.points.push_back(make_point(in.T_base_part, layer[k].first, feed, rpm, segment, MoveKind::grind));
    }
    ++segment;
  }
  plan.segments = segment;
  return plan;
}

Result<RegionPlan> plan_straight(const RegionInput& in, const PlannerSettings& settings, RegionPlan plan) {
  const auto& region = *in.region;
  const auto& tool = *in.tool;
  const auto& pts = in.excess_points_part;
  RansacOptions opts = settings.ransac;
  opts.inlier_mm = std::max(opts.inlier_mm, settings.flash_band_mm);
  // The line is the fin's: fitted to the points standing at least half as high as the highest.
  // Lower excess beside it (a face standing proud of the template by the casting's form
  // deviation, 0.2 mm over a broad patch) is no fin, and drew a line 5 degrees across the fin
  // on an unseen casting (test StraightPlan.ALowPatchBesideTheFinDoesNotTiltTheLine).
  double top = -std::numeric_limits<double>::infinity();
  std::vector<double> h_all(pts.size());
  for (std::size_t k = 0; k < pts.size(); ++k) top = std::max(top, h_all[k] = in.template_sdf(pts[k]));
  std::vector<Vec3> crest;
  for (std::size_t k = 0; k < pts.size(); ++k)
    if (h_all[k] >= 0.5 * top) crest.push_back(pts[k]);
  auto line = fit_line_ransac(crest.size() >= 2 ? crest : pts, opts);
  if (!line) return region_error(region.name, "fit", "no line could be fitted to the flash points");
  plan.line = *line;
  const auto frame = layer_frame(in, line->point);
  if (!frame) return region_error(region.name, "no_surface", "no template face below the flash line at " + fmt(line->point));
  const Vec3 up = frame->up;
  Vec3 t = line->direction - line->direction.dot(up) * up;
  if (t.norm() < 1e-6) return region_error(region.name, "fit", "the fitted flash line is along the face normal");
  t.normalize();
  // The flash along the line: its inliers by position along it, split into pieces at gaps
  // longer than flash_gap_mm; the passes run from the first to the last piece holding at least
  // a tenth of the inliers, and every excess point within that stretch sets the height (also
  // those off the line's band: a tall or wavy fin).
  std::vector<std::pair<double, std::size_t>> along;
  for (std::size_t k = 0; k < pts.size(); ++k)
    if (line->distance(pts[k]) <= opts.inlier_mm) along.emplace_back((pts[k] - frame->base).dot(t), k);
  if (along.empty()) return region_error(region.name, "fit", "no flash point lies on the fitted line");
  std::sort(along.begin(), along.end());
  std::vector<std::pair<std::size_t, std::size_t>> pieces;  // [first, last] into along
  for (std::size_t k = 0; k < along.size(); ++k)
    if (k == 0 || along[k].first - along[k - 1].first > settings.flash_gap_mm) pieces.emplace_back(k, k);
    else pieces.back().second = k;
  const std::size_t keep = std::max<std::size_t>(1, along.size() / 10);
  double smin = 1e300, smax = -1e300;
  for (const auto& [first, last] : pieces)
    if (last - first + 1 >= keep) smin = std::min(smin, along[first].first), smax = std::max(smax, along[last].first);
  if (smin > smax) smin = along.front().first, smax = along.back().first;  // no piece holds a tenth: all of them
  std::vector<double> heights;
  for (const auto& p : pts)
    if (const double s = (p - frame->base).dot(t); s >= smin - 1e-9 && s <= smax + 1e-9)
      heights.push_back(in.template_sdf(p));
  plan.max_excess_mm = *std::max_element(heights.begin(), heights.end());
  if (plan.max_excess_mm <= region.allowance_mm) return plan;
  const int passes = std::max(1, region.passes);
  for (int k = 1; k <= passes; ++k)
    plan.layer_levels_mm.push_back(plan.max_excess_mm - k * (plan.max_excess_mm - region.allowance_mm) / passes);

  // The pass follows the face under the line (its point along -up below each station), the tool
  // tip `level` above it. A station fits where the tool there keeps the allowance from the whole
  // template: beside a wall, a boss or a clamp's face it does not, and the pass ends before it
  // (no back-off up a wall: that would ramp the tool over material it cannot reach). The pass
  // runs over the material [smin, smax] and a lead of the tool radius plus lead_mm beyond each
  // end, each side cut at its first station that does not fit, walking out from the material's
  // middle (tests StraightPlan.AFinThatRunsIntoAWallIsGroundUpToItAndTheRestIsLeft,
  // Validate.ALeadOutIntoAWallOutsideTheRoiIsRefused).
  const double ext = tool_radius(tool) + settings.lead_mm;
  const double spacing = std::clamp(region.point_spacing_mm, 0.05, 1.0);
  const double R = tool_radius(tool);
  auto station = [&](double s, double level) -> std::optional<Transform> {
    const Vec3 above = frame->base + s * t;
    const auto d = find_level(in.template_sdf, above, -up, 0.0, 3.0 * settings.flash_band_mm + 10.0, 0.25);
    if (!d) return std::nullopt;  // no face under the line here (past the part's edge)
    const Vec3 face = above - *d * up;
    if (std::abs(*d) > settings.flash_band_mm + level) return std::nullopt;  // a step: another face
    Transform T = frame_from(face + level * up, up, t);
    if (tool_penetration_mm(tool, T, in.template_sdf, nullptr, region.allowance_mm) + region.allowance_mm <= kBackoffTolMm)
      return T;
    // The face here slopes off `up` (the casting's own face under the line, not the nominal):
    // the tool `level` above it along `up` comes nearer it than the level. It is lifted by what
    // that slope explains for this tool, (R + level)(1/cos - 1) for a ball, R tan + level(1/cos - 1)
    // for a flat end, and no more: anything nearer is a wall (test
    // StraightPlan.AFinOnAFaceSlopingOffTheLinesNormalIsGroundEndToEnd).
    const Vec3 g = sdf_gradient(in.template_sdf, face);
    if (!(g.norm() > 0.5)) return std::nullopt;
    const double c = std::clamp(g.normalized().dot(up), 0.0, 1.0);
    if (c < std::cos(kMaxFaceSlopeRad)) return std::nullopt;
    const double sec = 1.0 / c, tan = std::sqrt(std::max(0.0, sec * sec - 1.0));
    const double lift = tool.shape == config::ToolShape::ball ? (R + level) * (sec - 1.0) : R * tan + level * (sec - 1.0);
    if (!back_off(tool, T, in.template_sdf, up, region.allowance_mm, lift + kBackoffTolMm)) return std::nullopt;
    return T;
  };
  const double smid = 0.5 * (smin + smax);
  const double lowest = plan.layer_levels_mm.back();
  if (!station(smid, lowest))
    return region_error(region.name, "gouge",
                        "the tool '" + tool.name + "' cannot reach the flash at " + fmt(frame->base + smid * t) +
                            " (part frame) without coming nearer the template than allowance_mm = " +
                            fmt(region.allowance_mm, 3) + " mm");
  // the reach of each side at the lowest level (the levels above reach at least as far): the
  // last station that fits, walking out from the middle
  auto reach = [&](double dir) {
    const double limit = dir > 0 ? smax + ext : smin - ext;
    double last = smid;
    for (double s = smid + dir * spacing; dir > 0 ? s <= limit + 1e-9 : s >= limit - 1e-9; s += dir * spacing) {
      if (!station(s, lowest)) break;
      last = s;
    }
    return last;
  };
  const double s_lo = reach(-1.0), s_hi = reach(+1.0);
  // Material the tool cannot reach: excess points beyond either end of the pass farther than the
  // tool reaches at their height (a ball's half-width there, a cylinder's radius). Its length is
  // the stretch it spans before the pass's start plus the stretch after its end.
  constexpr double kNone = std::numeric_limits<double>::infinity();
  std::array<std::pair<double, double>, 2> left_span{{{kNone, -kNone}, {kNone, -kNone}}};  // before, after
  for (std::size_t k = 0; k < pts.size(); ++k) {
    const double sp = (pts[k] - frame->base).dot(t);
    if (sp < smin - 1e-9 || sp > smax + 1e-9) continue;
    const double h = in.template_sdf(pts[k]) - lowest;
    if (h <= 0.0) continue;
    const double half = tool.shape == config::ToolShape::ball && h < R ? std::sqrt(h * (2 * R - h)) : R;
    if (sp > s_lo - half && sp < s_hi + half) continue;
    auto& [first, last] = left_span[sp >= s_hi + half ? 1 : 0];
    first = std::min(first, sp), last = std::max(last, sp);
    if (h + lowest > plan.left_mm) plan.left_mm = h + lowest, plan.left_at = pts[k];
  }
  for (const auto& [first, last] : left_span)
    if (last >= first) plan.left_length_mm += last - first;
  const auto n = static_cast<int>(std::ceil((s_hi - s_lo) / spacing - 1e-9)) + 1;
  const double feed = region.feed_mm_s, rpm = region.spindle_rpm;
  const double air = std::min(settings.air_speed_mm_s, settings.max_speed_mm_s);
  int segment = 0;
  for (double level : plan.layer_levels_mm) {
    std::vector<Transform> pass;
    const bool forward = segment % 2 == 0;
    for (int i = 0; i < n; ++i) {
      const double s = forward ? std::min(s_hi, s_lo + i * spacing) : std::max(s_lo, s_hi - i * spacing);
      auto T = station(s, level);
      if (!T)  // a higher level reaches as far as the lowest unless a face overhangs the line
        return region_error(region.name, "gouge",
                            "pass " + std::to_string(segment) + " at " + fmt(frame->base + s * t + level * up) +
                                " (part frame): the tool cannot pass without coming nearer the template than "
                                "allowance_mm = " + fmt(region.allowance_mm, 3) + " mm (an overhang above the flash?)");
      pass.push_back(*T);
    }
    if (segment > 0)
      if (auto e = add_lift(plan, in, in.T_base_part.inverse() * plan.points.back().T_base_tool.to_transform(),
                            pass.front(), up, plan.max_excess_mm + 5.0, air, rpm, segment))
        return *e;
    for (const auto& T : pass) plan.points.push_back(make_point(in.T_base_part, T, feed, rpm, segment, MoveKind::grind));
    ++segment;
  }
  plan.segments = segment;
  return plan;
}

Vec3 first_position(const RegionPlan& p) { return p.points.front().T_base_tool.position_mm; }
Vec3 last_position(const RegionPlan& p) { return p.points.back().T_base_tool.position_mm; }

double plans_top_z(const std::vector<RegionPlan>& plans) {
  double top = -std::numeric_limits<double>::infinity();
  for (const auto& p : plans)
    for (const auto& q : p.points) top = std::max(top, q.T_base_tool.position_mm.z());
  return top;
}

double air_hop(const Vec3& from, const Vec3& to, double z_safe) {
  return std::max(0.0, z_safe - from.z()) + (to - from).head<2>().norm() + std::max(0.0, z_safe - to.z());
}

}  // namespace

PlannerSettings PlannerSettings::from(const config::SafetySection& safety) {
  PlannerSettings s;
  s.workspace_min_mm = Vec3(safety.workspace_min_mm[0], safety.workspace_min_mm[1], safety.workspace_min_mm[2]);
  s.workspace_max_mm = Vec3(safety.workspace_max_mm[0], safety.workspace_max_mm[1], safety.workspace_max_mm[2]);
  s.tool_axis_cone_rad = deg_to_rad(safety.tool_axis_cone_deg);
  s.max_speed_mm_s = safety.max_speed_mm_s;
  s.max_spindle_rpm = safety.max_spindle_rpm;
  s.safe_height_mm = safety.safe_height_mm;
  s.min_clearance_mm = safety.min_clearance_mm;
  s.repeatability_mm = safety.robot_repeatability_mm;
  s.air_speed_mm_s = std::min(s.air_speed_mm_s, safety.max_speed_mm_s);
  return s;
}

ChamferPose chamfer_pose(const Vec3& P, const Vec3& n_in, const Vec3& w_in, double tool_radius_mm,
                         double chamfer_rad) {
  ChamferPose cp;
  cp.w = w_in.normalized();
  cp.n = (n_in - n_in.dot(cp.w) * cp.w).normalized();
  cp.t = cp.n.cross(cp.w);
  cp.tool_axis = std::cos(chamfer_rad) * cp.n + std::sin(chamfer_rad) * cp.w;
  cp.tool_center = P + tool_radius_mm * cp.tool_axis;
  cp.T_part_tool = frame_from(cp.tool_center - tool_radius_mm * cp.tool_axis, cp.tool_axis, cp.t);
  return cp;
}

std::vector<double> layer_levels(const std::vector<double>& heights_mm, double depth_per_pass_mm,
                                 double allowance_mm) {
  std::vector<double> levels;
  std::vector<double> h = heights_mm;
  const double depth = std::max(1e-3, depth_per_pass_mm);
  for (int guard = 0; guard < 10000; ++guard) {
    const double D = h.empty() ? 0.0 : *std::max_element(h.begin(), h.end());
    if (D <= allowance_mm + 1e-9) break;
    // ⌈(D − allowance)/depth⌉ evenly spaced layers: the count drops by one per layer
    const double layers = D <= depth ? 1.0 : std::max(1.0, std::ceil((D - allowance_mm) / depth - 1e-9));
    const double level = std::max(allowance_mm, D - (D - allowance_mm) / layers);
    levels.push_back(level);
    for (auto& v : h) v = std::min(v, level);  // the layer removes everything above its level
  }
  return levels;
}

double tool_penetration_mm(const config::Tool& tool, const Transform& T_part_tool, const SignedDistance& sdf,
                           Vec3* deepest, double exact_within_mm) {
  const double R = tool_radius(tool);
  const Vec3 z = T_part_tool.linear().col(2);
  const Vec3 tip = T_part_tool.translation();
  if (tool.shape == config::ToolShape::ball) {
    const Vec3 centre = tip + R * z;
    const double d = sdf(centre);
    if (deepest != nullptr) {  // the ball's point toward the nearest surface
      const Vec3 g = sdf_gradient(sdf, centre, 0.05);
      *deepest = centre - R * (g.norm() > 1e-9 ? Vec3(g.normalized()) : Vec3(-z));
    }
    return R - d;  // exact for a true distance
  }
  // cylinder and disc (cones conservatively as cylinders): the profile from the end face's
  // centre out to the rim and up the side, turned about the axis. Each probe's distance matters
  // only within the clearance or penetration being decided (exact_within_mm, at least
  // kProbeNearMm); a probe farther off reads farther either way.
  const double near_mm = std::max(kProbeNearMm, std::abs(exact_within_mm));
  const double L = std::max(0.0, tool.length_mm);
  const std::array<Eigen::Vector2d, 5> nodes{Eigen::Vector2d(0.0, 0.0), Eigen::Vector2d(0.5 * R, 0.0),
                                             Eigen::Vector2d(R, 0.0), Eigen::Vector2d(R, 0.5 * L),
                                             Eigen::Vector2d(R, L)};
  constexpr std::array<int, 5> kAngles{1, 8, 24, 24, 24};
  const Vec3 x = T_part_tool.linear().col(0), y = T_part_tool.linear().col(1);
  // the surface point at profile parameter t (node index, fractional between nodes) and angle a
  auto surface = [&](double t, double a) {
    t = std::clamp(t, 0.0, static_cast<double>(nodes.size() - 1));
    const auto i = std::min(static_cast<std::size_t>(t), nodes.size() - 2);
    const Eigen::Vector2d rz = nodes[i] + (t - static_cast<double>(i)) * (nodes[i + 1] - nodes[i]);
    return Vec3(tip + rz.x() * (std::cos(a) * x + std::sin(a) * y) + rz.y() * z);
  };
  double worst = -std::numeric_limits<double>::infinity(), wt = 0.0, wa = 0.0;
  auto probe = [&](double t, double a) {
    const Vec3 p = surface(t, a);
    const double pen = -sdf.near(p, near_mm);
    if (pen > worst + kTieMm) {
      worst = pen, wt = t, wa = a;
      if (deepest != nullptr) *deepest = p;
    }
  };
  for (std::size_t i = 0; i < nodes.size(); ++i)
    for (int k = 0; k < kAngles[i]; ++k) probe(static_cast<double>(i), 2 * std::numbers::pi * k / kAngles[i]);
  // Near the decision, the deepest sample's neighbourhood: between two rim samples 15 degrees
  // apart the rim of a 40 mm disc sags 0.17 mm, and a convex template edge can reach the end
  // face between the rings. First in angle, then along the profile (test
  // ToolPenetration.ACylinderBetweenItsSamplesIsFound).
  if (worst > -(std::abs(exact_within_mm) + kRefineMarginMm)) {
    const double t0 = wt;
    const double da = 2 * std::numbers::pi / 24.0;
    if (t0 > 0.5) {
      const double a0 = wa;
      for (int k = -8; k <= 8; ++k)
        if (k != 0) probe(t0, a0 + k * da / 8.0);
    }
    const double a1 = wa, t1 = wt;
    for (int k = -8; k <= 8; ++k)
      if (const double t = t1 + k / 8.0; k != 0 && t >= 0.0 && t <= static_cast<double>(nodes.size() - 1)) probe(t, a1);
  }
  return worst;
}

Transform flange_pose(const Transform& T_base_tool, const config::Tool& tool) {
  // flange z points out of the flange toward the tip (ISO 9787); the tool z points back toward
  // the spindle, so the tool frame is the TCP frame turned half a turn about x
  Transform T_flange_tool = Transform::Identity();
  T_flange_tool.translation() = Vec3(tool.tcp_mm[0], tool.tcp_mm[1], tool.tcp_mm[2]);
  T_flange_tool.linear() = Eigen::AngleAxisd(std::numbers::pi, Vec3::UnitX()).toRotationMatrix();
  return T_base_tool * T_flange_tool.inverse();
}

namespace {

/// The casting's own face against the template (RegionInput::form_offset_mm, which the caller
/// checks is set): under it by no more than face_band_mm(), an offset lower than that not being
/// the casting's face as the cell sees it (the vision's face samples end there).
std::function<double(const Vec3&)> face_offset(const RegionInput& in) {
  return [offset = in.form_offset_mm, lowest = -face_band_mm(in)](const Vec3& p) {
    return std::max(lowest, offset(p));
  };
}

/// The input with the template's surface moved along z by move(p).
RegionInput moved_along_z(const RegionInput& in, std::function<double(const Vec3&)> move) {
  RegionInput out = in;
  const auto base = in.template_sdf;
  out.template_sdf = SignedDistance([base, move](const Vec3& p) { return base(p) - move(p); },
                                    [base, move](const Vec3& p, double near_mm) {
                                      const double r = move(p);
                                      return base.near(p, near_mm + std::abs(r)) - r;
                                    });
  return out;
}

/// The input with the template's surface moved to the casting's own face (face_offset): the
/// passes that end on a face end on the casting's face, which stands up to the form deviation
/// over or under the nominal.
RegionInput on_the_castings_face(const RegionInput& in) {
  if (!in.form_offset_mm) return in;
  return moved_along_z(in, face_offset(in));
}

/// The surface validate() keeps every pose's clearance from: the template, lowered where the
/// casting's own face is under it (the passes end there), never raised.
RegionInput validated_against(const RegionInput& in) {
  if (!in.form_offset_mm) return in;
  return moved_along_z(in, [face = face_offset(in)](const Vec3& p) { return std::min(0.0, face(p)); });
}

/// What a re-grind's leftover fin shows (RegionInput::leftover_part): how near the wall the
/// wheel's side may come beside it. The first grind kept the bound k0 = sqrt(u^T M u) along the
/// wall's outward normal u and left a fin r wide: the wheel's side stood r off the wall, so its
/// placement error along u is known to within the path's repeatability, and the bound along u
/// shrinks to k0 - (r - repeatability). Along another normal n = (n.u) u + n_perp the fin tells
/// nothing of the error across u: the bound is (n.u) (k0 - s) + sqrt(n_perp^T M n_perp) where
/// smaller than sqrt(n^T M n) (a face under the fin, n across u, keeps its bound). Per point,
/// the third smallest such bound of the leftover points within kRadiusMm of it in the parting
/// plane (one stray point moves nothing), of those at the fin's level (within flash_band_mm of
/// the first plan's plane).
class LeftoverFin {
 public:
  static constexpr double kRadiusMm = 1.0;
  static constexpr std::size_t kRank = 3;

  LeftoverFin(const RegionInput& in, const PlannerSettings& settings) {
    const auto& region = *in.region;
    if (in.first == nullptr || in.first->type != region.type || region.contact != config::FlashContact::periphery ||
        (region.type != config::RegionType::ring_flash && region.type != config::RegionType::circle_flash) ||
        in.leftover_part.size() != in.leftover_mm.size())
      return;
    const Vec3 w = in.first->plane.normal.normalized();
    origin_ = in.first->conic_origin;
    e1_ = any_perpendicular(w);
    e2_ = w.cross(e1_);
    const double repeatability = std::max(0.0, settings.repeatability_mm);
    for (std::size_t i = 0; i < in.leftover_part.size(); ++i) {
      const Vec3 d = in.leftover_part[i] - origin_;
      if (std::abs(d.dot(w)) > settings.flash_band_mm || !(in.leftover_mm[i] > repeatability)) continue;
      const Vec3 u = sdf_gradient(in.template_sdf, in.leftover_part[i], 0.25);  // out of the wall
      if (!(u.norm() > 1e-9)) continue;
      cells_[key(d.dot(e1_), d.dot(e2_))].push_back({d.dot(e1_), d.dot(e2_), in.leftover_mm[i] - repeatability,
                                                     u.normalized()});
    }
  }
  [[nodiscard]] bool empty() const { return cells_.empty(); }

  /// The bound (mm) beside p (part frame) along the surface's unit normal n there, at most
  /// sqrt(n^T M n).
  [[nodiscard]] double bound_mm(const Vec3& p, const Vec3& n, const Eigen::Matrix3d& M) const {
    const double full = std::sqrt(std::max(0.0, n.dot(M * n)));
    if (cells_.empty()) return full;
    const Vec3 d = p - origin_;
    const double u = d.dot(e1_), v = d.dot(e2_);
    std::array<double, kRank> low;  // the kRank smallest, ascending
    low.fill(full);
    const auto cu = static_cast<std::int64_t>(std::floor(u / kRadiusMm)), cv = static_cast<std::int64_t>(std::floor(v / kRadiusMm));
    for (std::int64_t a = cu - 1; a <= cu + 1; ++a)
      for (std::int64_t b = cv - 1; b <= cv + 1; ++b) {
        const auto it = cells_.find(pack(a, b));
        if (it == cells_.end()) continue;
        for (const auto& q : it->second) {
          if ((q.u - u) * (q.u - u) + (q.v - v) * (q.v - v) > kRadiusMm * kRadiusMm) continue;
          const double along = n.dot(q.across);
          if (along <= 0.0) continue;  // a surface facing away from this wall
          const Vec3 perp = n - along * q.across;
          const double k0 = std::sqrt(std::max(0.0, q.across.dot(M * q.across)));
          const double bound = along * std::max(0.0, k0 - q.less_mm) + std::sqrt(std::max(0.0, perp.dot(M * perp)));
          if (bound >= low.back()) continue;
          low.back() = bound;
          std::sort(low.begin(), low.end());
        }
      }
    return low.back();
  }

 private:
  struct Point {
    double u, v;
    double less_mm;  // the fin's distance off the wall less the repeatability
    Vec3 across;     // the wall's outward normal beside it
  };
  static std::int64_t pack(std::int64_t a, std::int64_t b) { return (a << 32) ^ (b & 0xFFFFFFFF); }
  static std::int64_t key(double u, double v) {
    return pack(static_cast<std::int64_t>(std::floor(u / kRadiusMm)), static_cast<std::int64_t>(std::floor(v / kRadiusMm)));
  }
  Vec3 origin_ = Vec3::Zero(), e1_ = Vec3::UnitX(), e2_ = Vec3::UnitY();
  std::unordered_map<std::int64_t, std::vector<Point>> cells_;
};

/// The input whose template keeps the placement bound where it exceeds the region's allowance
/// (see RegionInput::placement_bound_mm2): the surface moved out along its normal n by
/// max(0, sqrt(n^T M n) - allowance), so that every pose keeping the allowance from it keeps the
/// bound from the template. n is the distance's gradient (central differences across a grid
/// voxel); where it has none (a medial point) the largest bound. Beside a re-grind's leftover
/// fin (`fin`) a wall keeps as much less as the fin shows (LeftoverFin).
RegionInput kept_from_placement(const RegionInput& in, const LeftoverFin* fin = nullptr) {
  const Eigen::Matrix3d M = 0.5 * (in.placement_bound_mm2 + in.placement_bound_mm2.transpose());
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(M);
  const double allowance = in.region->allowance_mm;
  const double largest = std::sqrt(std::max(0.0, eig.eigenvalues().maxCoeff()));
  if (largest <= allowance) return in;
  const double smallest = std::sqrt(std::max(0.0, eig.eigenvalues().minCoeff()));
  const double most = largest - allowance;
  const auto base = in.template_sdf;
  std::function<double(const Vec3&)> extra;
  const bool beside_fin = fin != nullptr && !fin->empty();
  if (!beside_fin && largest - smallest < 1e-6) {
    extra = [most](const Vec3&) { return most; };
  } else {
    extra = [base, M, allowance, most, fin = beside_fin ? std::optional<LeftoverFin>(*fin) : std::nullopt](const Vec3& p) {
      Vec3 g = sdf_gradient(base, p, 0.25);
      const double n = g.norm();
      if (!(n > 1e-9)) return most;
      g /= n;
      const double bound = fin ? fin->bound_mm(p, g, M) : std::sqrt(std::max(0.0, g.dot(M * g)));
      return std::max(0.0, bound - allowance);
    };
  }
  RegionInput out = in;
  out.template_sdf = SignedDistance([base, extra](const Vec3& p) { return base(p) - extra(p); },
                                    [base, extra, most](const Vec3& p, double near_mm) {
                                      // exact within near_mm + most: moved out by at most `most`
                                      const double b = base.near(p, near_mm + most);
                                      return std::abs(b) > near_mm + most ? b - most : b - extra(p);
                                    });
  return out;
}

}  // namespace

Result<RegionPlan> plan_region(const RegionInput& in, const PlannerSettings& settings) {
  if (in.region == nullptr || in.tool == nullptr || !in.template_sdf)
    return Error{"planning.input", "a region input lacks its region, tool or template (a bug in the caller)"};
  RegionPlan plan;
  plan.region = in.region->name;
  plan.type = in.region->type;
  if (in.tool->diameter_mm <= 0)
    return region_error(plan.region, "input", "tool '" + in.tool->name + "' has no diameter");
  if (in.region->allowance_mm < settings.min_clearance_mm - 1e-9)
    return region_error(plan.region, "clearance",
                        "allowance_mm = " + fmt(in.region->allowance_mm, 3) + " is less than the cell's [safety] "
                        "min_clearance_mm = " + fmt(settings.min_clearance_mm, 3) +
                        ": the last pass would grind nearer the surface than the cell can place it; raise the region's "
                        "allowance_mm");
  // a re-grind of a flash whose first grind left a fin wider than the repeatability goes round
  // again however few excess points the re-scan holds (the fin's stub is a few pixels wide)
  const LeftoverFin fin(in, settings);
  if (in.excess_points_part.size() < kMinRegionPoints && fin.empty()) return plan;  // nothing (left) to grind
  switch (in.region->type) {
    case config::RegionType::ring_flash:
    case config::RegionType::circle_flash:
      // a flash's loop follows the wall, whose form the camera does not see from above
      return plan_flash_loop(kept_from_placement(in, &fin), settings, std::move(plan));
    case config::RegionType::riser:
      return plan_riser(kept_from_placement(on_the_castings_face(in)), settings, std::move(plan));
    case config::RegionType::straight_flash:
      return plan_straight(kept_from_placement(on_the_castings_face(in)), settings, std::move(plan));
  }
  return region_error(plan.region, "input", "unknown region type");
}

double air_move_length_mm(const std::vector<RegionPlan>& plans, const std::vector<std::size_t>& order) {
  const double z_safe = plans_top_z(plans);
  double total = 0.0;
  for (std::size_t k = 1; k < order.size(); ++k)
    total += air_hop(last_position(plans[order[k - 1]]), first_position(plans[order[k]]), z_safe);
  return total;
}

std::vector<std::size_t> order_regions(const std::vector<RegionPlan>& plans) {
  std::vector<std::size_t> idx;
  for (std::size_t i = 0; i < plans.size(); ++i)
    if (!plans[i].points.empty()) idx.push_back(i);
  if (idx.size() <= 2) return idx;  // a reversal costs the same
  std::vector<std::size_t> best = idx;
  double best_len = air_move_length_mm(plans, best);
  if (idx.size() <= 8) {
    std::vector<std::size_t> perm = idx;
    std::sort(perm.begin(), perm.end());
    do {
      const double len = air_move_length_mm(plans, perm);
      if (len < best_len - 1e-9) best_len = len, best = perm;
    } while (std::next_permutation(perm.begin(), perm.end()));
    return best;
  }
  for (std::size_t start = 0; start < idx.size(); ++start) {  // nearest neighbour from each start
    std::vector<std::size_t> order{idx[start]};
    std::vector<bool> used(plans.size(), false);
    used[idx[start]] = true;
    while (order.size() < idx.size()) {
      std::size_t pick = 0;
      double d = std::numeric_limits<double>::infinity();
      for (auto j : idx)
        if (!used[j]) {
          const double dj = (first_position(plans[j]) - last_position(plans[order.back()])).head<2>().norm();
          if (dj < d) d = dj, pick = j;
        }
      used[pick] = true;
      order.push_back(pick);
    }
    const double len = air_move_length_mm(plans, order);
    if (len < best_len - 1e-9) best_len = len, best = order;
  }
  return best;
}

Trajectory assemble(const std::string& part_id, const std::vector<RegionPlan>& plans,
                    const std::vector<std::size_t>& order, const PlannerSettings& settings) {
  Trajectory traj;
  traj.part_id = part_id;
  const double z_safe = plans_top_z(plans) + settings.safe_height_mm;
  const double air = std::min(settings.air_speed_mm_s, settings.max_speed_mm_s);
  for (auto i : order) {
    const auto& plan = plans[i];
    if (plan.points.empty()) continue;
    const int offset = static_cast<int>(traj.segment_regions.size());
    for (int s = 0; s < std::max(1, plan.segments); ++s) traj.segment_regions.push_back(plan.region);
    TrajectoryPoint approach = plan.points.front();
    approach.T_base_tool.position_mm.z() = z_safe;
    approach.speed_mm_s = air;
    approach.kind = MoveKind::approach;
    approach.segment = offset;
    traj.points.push_back(approach);
    for (auto q : plan.points) {
      q.segment += offset;
      traj.points.push_back(q);
    }
    TrajectoryPoint retract = plan.points.back();
    retract.T_base_tool.position_mm.z() = z_safe;
    retract.speed_mm_s = air;
    retract.kind = MoveKind::retract;
    retract.segment = offset + std::max(1, plan.segments) - 1;
    traj.points.push_back(retract);
  }
  return traj;
}

namespace {

Error rule_error(const std::string& region, std::size_t i, const std::string& rule, const std::string& what) {
  return Error{"planning." + rule, "region '" + region + "', point " + std::to_string(i) + ", rule " + rule + ": " + what};
}

/// The rules that need no template at point i: finite pose, workspace box, tool-axis cone,
/// speed and spindle speed. Comparisons are written so that NaN fails them.
std::optional<Error> check_limits(const Trajectory& trajectory, std::size_t i, const PlannerSettings& settings) {
  const auto& p = trajectory.points[i];
  auto fail = [&](const std::string& rule, const std::string& what) {
    return rule_error(trajectory.region_of(p, "?"), i, rule, what);
  };
  const Vec3& x = p.T_base_tool.position_mm;
  const Quat& q = p.T_base_tool.orientation;
  if (!x.allFinite() || !q.coeffs().allFinite() || std::abs(q.norm() - 1.0) > 1e-6)
    return fail("finite", "the pose is not finite or its quaternion is not unit length (a planner bug)");
  if ((x.array() < settings.workspace_min_mm.array()).any() || (x.array() > settings.workspace_max_mm.array()).any())
    return fail("workspace", "position " + fmt(x) + " mm (base) is outside the workspace box " +
                                 fmt(settings.workspace_min_mm) + " .. " + fmt(settings.workspace_max_mm) +
                                 "; check the part placement, T_base_camera and [safety] workspace_*_mm");
  const Vec3 axis = q.toRotationMatrix().col(2);
  if (axis.z() < std::cos(settings.tool_axis_cone_rad) - 1e-9)
    return fail("tool_axis_cone", "the tool axis is " + fmt(rad_to_deg(std::acos(std::clamp(axis.z(), -1.0, 1.0))), 1) +
                                      " deg from straight down, more than tool_axis_cone_deg = " +
                                      fmt(rad_to_deg(settings.tool_axis_cone_rad), 1) + "; lower chamfer_deg or widen the cone");
  if (!(p.speed_mm_s > 0.0 && p.speed_mm_s <= settings.max_speed_mm_s))
    return fail("speed", "speed " + fmt(p.speed_mm_s) + " mm/s is outside (0, " + fmt(settings.max_speed_mm_s) +
                             "] (max_speed_mm_s); lower the region's feed_mm_s");
  if (!(p.spindle_rpm >= 0.0 && p.spindle_rpm <= settings.max_spindle_rpm) ||
      (p.kind == MoveKind::grind && !(p.spindle_rpm > 0.0)))
    return fail("speed", "spindle speed " + fmt(p.spindle_rpm, 0) + " rpm is outside (0, " +
                             fmt(settings.max_spindle_rpm, 0) + "] (max_spindle_rpm); fix the region's spindle_rpm");
  return std::nullopt;
}

}  // namespace

Status validate_limits(const Trajectory& trajectory, const PlannerSettings& settings) {
  for (std::size_t i = 0; i < trajectory.points.size(); ++i)
    if (auto e = check_limits(trajectory, i, settings)) return *e;
  return {};
}

Status validate(const Trajectory& trajectory, const std::vector<RegionInput>& inputs, const PlannerSettings& settings) {
  std::vector<RegionInput> floors;  // validated_against() each input
  floors.reserve(inputs.size());
  for (const auto& in : inputs) floors.push_back(validated_against(in));
  std::map<std::string, const RegionInput*> by_name;
  for (const auto& in : floors)
    if (in.region != nullptr) by_name[in.region->name] = &in;
  const double clearance = settings.min_clearance_mm;
  for (std::size_t i = 0; i < trajectory.points.size(); ++i) {
    const auto& p = trajectory.points[i];
    if (auto e = check_limits(trajectory, i, settings)) return *e;
    const std::string region = trajectory.region_of(p, "?");
    auto fail = [&](const std::string& rule, const std::string& what) { return rule_error(region, i, rule, what); };
    const auto it = by_name.find(region);
    if (it == by_name.end())
      return fail("input", "the segment " + std::to_string(p.segment) + " names no planned region");
    const RegionInput& in = *it->second;
    const Transform T_part_base = in.T_base_part.inverse();
    // The tool's depth into the template (> 0 inside) and its deepest point: a gouge where the
    // tool comes nearer than the clearance, by more than a back-off's tolerance.
    auto gouge = [&](const Pose& m, const std::string& where) -> std::optional<Error> {
      Vec3 deepest = Vec3::Zero();
      const double pen =
          tool_penetration_mm(*in.tool, T_part_base * m.to_transform(), in.template_sdf, &deepest, clearance);
      if (pen + clearance <= kValidateTolMm) return std::nullopt;
      const std::string depth = pen > 0.0 ? "reaches " + fmt(pen, 3) + " mm into the template"
                                          : "comes within " + fmt(-pen, 3) + " mm of the template";
      return fail("gouge", where + "the tool '" + in.tool->name + "' " + depth + " at " + fmt(deepest) +
                               " mm (part frame); every pose must keep [safety] min_clearance_mm = " +
                               fmt(clearance, 3) + " mm from it");
    };
    if (auto e = gouge(p.T_base_tool, "")) return *e;
    // The move onto this point (approach descents, lifts, leads, moves between passes and
    // regions): sampled every kMoveSampleMm with the tool of this point's region.
    if (i > 0) {
      std::optional<Error> hit;
      for_each_move_sample(trajectory.points[i - 1].T_base_tool, p.T_base_tool, [&](const Pose& m) {
        hit = gouge(m, "on the move from point " + std::to_string(i - 1) + ", at " + fmt(m.position_mm) + " mm (base), ");
        return !hit;
      });
      if (hit) return *hit;
    }
  }
  return {};
}

Result<Trajectory> plan_part(const std::string& part_id, const std::vector<RegionInput>& inputs,
                             const PlannerSettings& settings) {
  std::vector<RegionPlan> plans;
  plans.reserve(inputs.size());
  for (const auto& in : inputs) {
    auto plan = plan_region(in, settings);
    if (!plan) return plan.error();
    plans.push_back(std::move(plan.value()));
  }
  Trajectory traj = assemble(part_id, plans, order_regions(plans), settings);
  if (Status st = validate(traj, inputs, settings); !st) return st.error();
  return traj;
}

}  // namespace fettle::planning
