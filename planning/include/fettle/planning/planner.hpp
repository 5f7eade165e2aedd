#pragma once
// fettle::planning - per-region grinding trajectories and their safety validation.
//
// Frames: base (robot base, table top z = 0, z up), part (the casting's frame; recipe ROIs are
// in it), camera. T_target_source maps source points into target. Millimetres and radians.
// Tool convention (same as the simulator): every pose is T_base_tool of the TCP, which sits at
// the tool tip; the tool z axis points from the tip toward the spindle (away from the part).
// A ball tool's sphere centre is TCP + R·z; a cylinder tool occupies TCP + [0, length]·z with
// radius R. See docs/planning.md.
#include <cmath>
#include <functional>
#include <string>
#include <type_traits>
#include <vector>

#include "fettle/config/cell.hpp"
#include "fettle/config/part.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"
#include "fettle/core/trajectory.hpp"
#include "fettle/planning/fit.hpp"

namespace fettle::planning {

/// Signed distance (mm) of a part-frame point to the template solid: > 0 outside, < 0 inside.
/// Built from any callable double(const Vec3&); a provider that can answer cheaper far from the
/// surface (the signed-distance grid) also gives near().
class SignedDistance {
 public:
  using Fn = std::function<double(const Vec3& p_part)>;
  /// near(p, near_mm): the signed distance where it is within ±near_mm; farther, any value of
  /// the right sign whose size is the true distance's within a bound and beyond near_mm.
  using NearFn = std::function<double(const Vec3& p_part, double near_mm)>;

  SignedDistance() = default;
  template <class F>
    requires(std::is_invocable_r_v<double, const F&, const Vec3&> && !std::is_same_v<std::decay_t<F>, SignedDistance>)
  SignedDistance(F f) : fn_(std::move(f)) {}  // NOLINT(google-explicit-constructor): any callable is one
  SignedDistance(Fn fn, NearFn near) : fn_(std::move(fn)), near_(std::move(near)) {}

  double operator()(const Vec3& p_part) const { return fn_(p_part); }
  /// Exact (as operator()) wherever the distance is within ±near_mm. Tool probes ask this: a
  /// probe farther from the template than any clearance cannot decide a penetration.
  [[nodiscard]] double near(const Vec3& p_part, double near_mm) const {
    return near_ ? near_(p_part, near_mm) : fn_(p_part);
  }
  explicit operator bool() const { return static_cast<bool>(fn_); }

 private:
  Fn fn_;
  NearFn near_;
};

struct RegionPlan;

/// Everything the planner needs for one region (the daemon adapts the vision output to this).
struct RegionInput {
  const config::Region* region = nullptr;
  const config::Tool* tool = nullptr;
  Transform T_base_part = Transform::Identity();  ///< e.g. T_base_camera * T_camera_part
  std::vector<Vec3> excess_points_part;            ///< material above the template, part frame
  SignedDistance template_sdf;                     ///< the template surface, part frame
  /// The casting's own surface over the template's faces here, mm along the face normal (vision's
  /// FormOffset; empty: the nominal). A riser's and a straight flash's passes end that far over
  /// the template (under it where it is negative, by at most form_deviation_mm), so they end on
  /// the casting's own face and leave no riser stub where the face sits under the nominal (test
  /// RiserPlan.TheLastPassEndsOnTheCastingsOwnFaceNotTheNominal).
  std::function<double(const Vec3& p_part)> form_offset_mm;
  /// How far the tool may really cut from where it is told (part frame, mm^2): the bound along a
  /// unit n is sqrt(n^T M n). Where it exceeds the region's allowance, every pose keeps the bound
  /// from the template along the surface's normal instead (test
  /// RegionPlanning.EveryPoseKeepsThePlacementBoundAlongTheSurfacesNormal).
  Eigen::Matrix3d placement_bound_mm2 = Eigen::Matrix3d::Zero();
  /// The casting's stated form deviation (the recipe's [vision] form_deviation_mm): a riser's
  /// excess the tool cannot reach that is no higher than this over the template may be the
  /// casting's own face, and is left and reported like PlannerSettings::leave_unreachable_mm's.
  double form_deviation_mm = 0.0;
  /// A re-grind: the region's plan in the cycle's first grind (part frame; nullptr otherwise). A
  /// ring or circle flash is ground again along that plan's ring and parting plane, fitted to
  /// the whole fin: what a grind leaves of a fin is pieces on a short arc (110 of 360 degrees)
  /// that fit no ring, or a wrong one (test RingPlan.AReGrindFollowsTheFirstPlansRing).
  const RegionPlan* first = nullptr;
  /// A re-grind of a flash ground at the wheel's side (contact = "periphery", with `first`): the
  /// re-scan's points of the fin the first grind left (part frame) and how far each stands off
  /// the template. The wheel's side stopped there, so where the fin stands further out than the
  /// path's repeatability the placement error the bound keeps sideways is seen, and the loop
  /// comes that much nearer the wall than the bound, never nearer than the allowance
  /// (test CirclePlan.AReGrindComesNearerTheWallWhereTheFirstLeftTheFin). It takes the frames the
  /// part was located in for the first grind, the verification and this plan to agree: a
  /// registration that differs between them along the wall's normal moves the wheel that much.
  std::vector<Vec3> leftover_part;
  std::vector<double> leftover_mm;
  /// The wheel may be up to this much smaller in radius than `tool` says (its wear is known
  /// within a range, process::WearRange): a riser's rows close up for it.
  double tool_worn_more_mm = 0.0;
};

/// Planner limits and tunables (safety limits come from the cell's [safety]).
struct PlannerSettings {
  Vec3 workspace_min_mm{-1000.0, -1000.0, -100.0};
  Vec3 workspace_max_mm{1000.0, 1000.0, 1200.0};
  double tool_axis_cone_rad = deg_to_rad(60.0);  ///< tool axis within this of straight down
  double max_speed_mm_s = 250.0;
  double max_spindle_rpm = 12000.0;
  double safe_height_mm = 100.0;    ///< air moves this far above the highest planned point
  /// Every pose of a trajectory, and every move between two, keeps the tool at least this far
  /// from the template (validate()): the cell's [safety] min_clearance_mm. A region whose
  /// allowance_mm is smaller is refused (its last pass would grind nearer than the cell can
  /// place the surface).
  double min_clearance_mm = 0.05;
  /// The robot's path repeatability ([safety] robot_repeatability_mm): a re-grind keeps it where
  /// the first grind's leftover shows the rest of the placement error (RegionInput::leftover_part).
  double repeatability_mm = 0.0;
  double air_speed_mm_s = 100.0;    ///< approach / air / retract (clamped to max_speed_mm_s)
  double lead_mm = 5.0;             ///< lead-in / lead-out length of flash loops and passes
  double max_backoff_mm = 10.0;     ///< how far a pose may back off to avoid a gouge
  /// Riser raster: excess material no higher than this above the template under a point the
  /// tool cannot reach is left there (RegionPlan::left_mm says how high); higher is an error.
  /// The verification's first threshold: less than this is not counted as left material.
  double leave_unreachable_mm = 0.3;
  double flash_band_mm = 2.0;       ///< inlier band of the flash ellipse / line fits (flash width)
  /// A straight flash's line inliers more than this apart along the line are separate pieces;
  /// the passes run over the pieces holding at least a tenth of the inliers (stray excess points
  /// along the line, e.g. at the ROI's end, do not stretch them)
  double flash_gap_mm = 5.0;
  RansacOptions ransac{};
  static PlannerSettings from(const config::SafetySection& safety);
};

/// The planned grinding moves of one region, in the base frame, without air moves.
struct RegionPlan {
  std::string region;
  config::RegionType type = config::RegionType::riser;
  std::vector<TrajectoryPoint> points;  ///< segment ids are local (0, 1, ...) until assembled
  int segments = 0;
  // diagnostics
  Plane plane;                    ///< ring/circle: fitted parting plane (part frame)
  Conic conic;                    ///< ring/circle: fitted ellipse in the plane's 2-D basis
  /// ring/circle: that basis's origin on the plane (its axes follow from the plane's normal alone)
  Vec3 conic_origin = Vec3::Zero();
  Line line;                      ///< straight flash: fitted line (part frame)
  double max_excess_mm = 0.0;     ///< riser/straight: D, largest height above the template
  std::vector<double> layer_levels_mm;  ///< riser/straight: heights above the template per layer/pass
  /// riser: the highest excess material left under raster points the tool cannot reach (no
  /// higher than PlannerSettings::leave_unreachable_mm; 0: none left). straight flash: the
  /// highest material beyond the ends of the passes, which stop where the tool would come nearer
  /// a wall or another feature than the allowance (any height: it is left, never ground into).
  double left_mm = 0.0;
  Vec3 left_at = Vec3::Zero();    ///< ... where (part frame)
  double left_length_mm = 0.0;    ///< straight flash: the length of the fin so left (both ends together)
};

// --- the pose equations (Zhu et al. 2022, Eqs. 17–21) ---------------------------------------

/// Chamfer grinding pose at contact point P: n the in-plane outward normal (from the conic's
/// gradient), w the parting plane's normal, t = n × w the path tangent. The tool centre is
/// Q = P + R (cos θ n + sin θ w) (θ = 45°: √2/2·R along n and along w).
struct ChamferPose {
  Vec3 n, w, t;
  Vec3 tool_center;   ///< Q
  Vec3 tool_axis;     ///< unit, toward the spindle: cos θ n + sin θ w
  Transform T_part_tool;  ///< TCP frame: z = tool_axis, x = t, TCP = Q − R·z (= P)
};
ChamferPose chamfer_pose(const Vec3& P, const Vec3& n, const Vec3& w, double tool_radius_mm,
                         double chamfer_rad);

/// Riser layers: heights above the template for the layers that take D down to `allowance`
/// (one if D ≤ depth_per_pass, else ⌈D/depth⌉ evenly spaced; D recomputed from the points
/// after each layer). Empty if D ≤ allowance.
std::vector<double> layer_levels(const std::vector<double>& heights_mm, double depth_per_pass_mm,
                                 double allowance_mm);

// --- planning -------------------------------------------------------------------------------

/// Plans one region (no validation, no air moves). Errors name the region.
Result<RegionPlan> plan_region(const RegionInput& input, const PlannerSettings& settings);

/// The order of the regions (indices into `plans`) that minimises the air-move length
/// (exhaustive for ≤ 8 regions, nearest neighbour + 2-opt beyond), starting with the region
/// nearest `start_mm` when given.
std::vector<std::size_t> order_regions(const std::vector<RegionPlan>& plans);
/// Total length of the air moves between the regions in this order (end of one to start of next).
double air_move_length_mm(const std::vector<RegionPlan>& plans, const std::vector<std::size_t>& order);

/// Assembles the region plans in `order` with approach / retract moves at the safe height.
Trajectory assemble(const std::string& part_id, const std::vector<RegionPlan>& plans,
                    const std::vector<std::size_t>& order, const PlannerSettings& settings);

/// validate() samples the moves between points this finely.
inline constexpr double kMoveSampleMm = 1.0;

/// The poses strictly between a and b that validate() checks on a move: every kMoveSampleMm
/// along the straight line, orientation by slerp. fn(m) returns false to stop early; the
/// function returns false then. The planner clears its moves and the verification sweeps the
/// tool's footprint on these same samples.
template <class Fn>
bool for_each_move_sample(const Pose& a, const Pose& b, Fn&& fn) {
  const double len = (b.position_mm - a.position_mm).norm();
  // a move of one step (a raster's point spacing) has no sample between its ends in either
  // frame: the located part's rotation, from single-precision registration, stretches lengths
  // by up to a few 1e-8 from the part frame to the base frame
  const int steps = static_cast<int>(std::ceil(len / kMoveSampleMm - 1e-6));
  for (int k = 1; k < steps; ++k) {
    const double f = static_cast<double>(k) / steps;
    const Pose m{a.position_mm + f * (b.position_mm - a.position_mm), a.orientation.slerp(f, b.orientation).normalized()};
    if (!fn(m)) return false;
  }
  return true;
}

/// Validation rules: "workspace", "tool_axis_cone", "speed", "gouge": at every point and along
/// the move onto it, sampled every 1 mm (approach descents, lifts, leads, lead-outs, the moves
/// between passes and between regions), the tool's whole shape keeps at least
/// settings.min_clearance_mm from the whole template, placed with the point's region's pose and
/// lowered where that region's form offset puts the casting's face under it (by at most its
/// form_deviation_mm: the passes end on that face; never raised).
/// The error names the region, the point index in the trajectory, the rule (code
/// "planning.<rule>") and, for a gouge, the tool's deepest point (part frame) and its depth.
Status validate(const Trajectory& trajectory, const std::vector<RegionInput>& inputs,
                const PlannerSettings& settings);

/// The rules of validate() that need no template, at every point: "finite", "workspace",
/// "tool_axis_cone", "speed" (NaN fails each). fettled runs them again on every trajectory just
/// before it uploads it, against the cell's [safety] limits (PlannerSettings::from), so nothing
/// reaches the robot outside them whatever produced the trajectory. Errors as validate()'s.
Status validate_limits(const Trajectory& trajectory, const PlannerSettings& settings);

/// Plans every region, orders them, assembles and validates. A failing trajectory is never
/// returned.
Result<Trajectory> plan_part(const std::string& part_id, const std::vector<RegionInput>& inputs,
                             const PlannerSettings& settings);

/// The flange pose for a TCP pose: T_base_flange = T_base_tool · T_tool_flange, where
/// T_flange_tool = translation(tool.tcp_mm) · rot_x(180°) (flange z toward the tip, tool z back
/// toward the spindle): the flange sits tcp_mm[2] along the tool z axis from the tip.
Transform flange_pose(const Transform& T_base_tool, const config::Tool& tool);

/// Penetration (mm, > 0 = into the template) of the tool placed at T_part_tool; `deepest`, when
/// given, receives the point of the tool (part frame) that goes deepest. A cylinder's probes ask
/// SignedDistance::near(p, max(2 mm, |exact_within_mm|)): the result is exact wherever it is
/// within ±exact_within_mm (pass the clearance or the allowance being decided); farther, it is
/// only known to be farther.
double tool_penetration_mm(const config::Tool& tool, const Transform& T_part_tool, const SignedDistance& sdf,
                           Vec3* deepest = nullptr, double exact_within_mm = 2.0);

}  // namespace fettle::planning
