#pragma once
// The cell learns its own bias (docs/compensation.md).
//
// A cell's systematic errors (hand-eye calibration, the robot's path offset, a tool length off)
// move every cut the same way. The verification scan shows where the tool really cut: on the
// surfaces it cut, the re-scanned points lie on the tool's surface as it really was, i.e. on the
// commanded tool surface shifted by the cell's offset b. For a re-scan point q there,
//     sd_commanded_tool(q) = n(q) . b          (n: the tool surface's outward normal at q)
// so a least-squares fit over the cut surfaces measures b along every direction their normals
// span, in the base frame and with the camera's own error included (the re-scan sees the cut
// and the part through the same camera, and the next plan is placed through it too).
//
// measure_cut_offset() does that after a cycle; CellBias keeps the estimate across cycles
// (update() takes a share `gain` of each measured residual, bounded by max_offset_mm) and
// process() commands every path shifted by minus the estimate (ProcessOptions::cell_bias_mm).
// Tests: tests/process/test_compensation.cpp; `fettle-sim trial` prints the estimate per casting.
#include <cstddef>
#include <filesystem>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "fettle/config/cell.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"
#include "fettle/core/trajectory.hpp"
#include "fettle/process/pipeline.hpp"

namespace fettle::process {

/// A wheel's radius as its cut shows it: on its side (a disc's or a burr's) and all over a
/// ball the re-scan lies w inside the commanded tool when the wheel is w smaller than commanded.
struct ToolWearMeasured {
  double wear_mm = 0.0;  ///< radius lost beyond the wear it was commanded with
  double std_mm = 0.0;   ///< 1-sigma
  std::size_t points = 0;  ///< re-scan points on the surface its radius cut
};

/// Where one region's tool cut against where it was told to, on that region's cut surfaces
/// alone (base frame). It differs from the whole cut's offset by what is the region's own: a
/// hand-eye rotation moves a cut by its lever (0.05 deg: 0.1 mm between the riser and the side
/// fin 120 mm away), a wheel's wear and its TCP move only its own regions.
struct RegionCutOffset {
  std::string tool;               ///< the region's wheel
  Vec3 offset_mm = Vec3::Zero();  ///< along the observed directions; 0 along the others
  Eigen::Matrix3d observed = Eigen::Matrix3d::Zero();  ///< as CutOffset::observed, for these points
  Vec3 std_mm = Vec3::Zero();
  std::size_t points = 0;
  double rms_mm = 0.0;
};

/// Where the tool cut against where it was told to cut, from one cycle's re-scan (base frame).
struct CutOffset {
  Vec3 offset_mm = Vec3::Zero();  ///< along the observed directions; 0 along the others
  /// Projector onto the directions the cut surfaces fix (their normals span them with at least
  /// min_points points' weight): identity when all three are, 0 when none is.
  Eigen::Matrix3d observed = Eigen::Matrix3d::Zero();
  Vec3 std_mm = Vec3::Zero();     ///< 1-sigma of offset_mm per base axis (0 where unobserved)
  std::size_t points = 0;         ///< re-scan points on cut surfaces that carry the fit
  double rms_mm = 0.0;            ///< their residual to the fitted tool surface
  /// The wheels whose radius the cut showed apart from the offset (by tool name): each fitted on
  /// its own cut surfaces and stub edges with an offset of its own, sd_i = n_i . b_t - c_i w_t,
  /// c_i the share of the surface's normal across the tool's axis (1 on a ball and a cylinder's
  /// side, 0 on its flat end). offset_mm and regions are fitted with the wheels as measured.
  std::map<std::string, ToolWearMeasured> tools;
  /// Each region whose own cut surfaces fix a direction (min_points' weight), by region name.
  std::map<std::string, RegionCutOffset> regions;
  [[nodiscard]] int observed_directions() const;
  /// "(x, y, z) mm +- (sx, sy, sz) from N cut-surface points, k of 3 directions observed"
  [[nodiscard]] std::string describe() const;
};

struct CutOffsetSettings {
  /// Re-scan points farther than this from the commanded tool surface are not on a cut (must
  /// exceed the largest offset to be measured).
  double band_mm = 1.0;
  /// Only re-scan points at least this far below every surface the first scan saw in the same
  /// base-frame x-y cell of column_mm: material was removed there, the tool cut it. A surface
  /// the tool passed by at its allowance is left out: it lies where it was, not on the tool.
  /// Beside a thin fin or round a riser's foot the column holds both the material and the
  /// surface under it; measured against the column's highest point the untouched surface reads
  /// as a cut standing the allowance off the tool, the offset learns that as a bias, the next
  /// plan keeps that much more and the stub grows cycle by cycle (test
  /// Compensation.TheSurfaceBesideAFinIsNotACut). Above the scanner's depth noise.
  double removed_min_mm = 0.15;
  double column_mm = 0.6;
  std::size_t min_points = 50;  ///< a direction needs this many points' weight to be observed
  /// The edge a wheel's side left in a surface it cut part of (a fin's stub round a flange): how
  /// far inside the commanded tool it is looked for (the most a wheel may be worn beyond what it
  /// was commanded with; outside it, band_mm), the bins of the nearest pose's tip it is found
  /// in, the band above the edge whose points are its samples (they lie up to this much nearer
  /// the wall: the radius is measured that much short, never long) and the re-scan's columns
  /// that tell it is cut away.
  double stub_band_mm = 3.0;
  double stub_bin_mm = 4.0;
  double stub_edge_mm = 0.1;
  double stub_column_mm = 0.3;
  /// The surface beyond a stub's edge is gone or at least this much lower in the re-scan: the
  /// wheel's side cut through the material (a ring's fin stands 15 mm over the body). The rim of a
  /// face cut a few tenths deep is no such edge: its step is within a few sigma of the scanner's
  /// noise and places the rim a tenth of a millimetre either way (a cup wheel read 0.12 mm larger
  /// than it is; test Trial.TheCellLearnsAPathBiasFromItsVerificationsAndTheGougesShrink).
  double stub_drop_mm = 1.0;
};

/// The cell's offset measured on the surfaces the tool cut in this cycle. `before`: the cycle's
/// first inspection (where material was); `ground`: the trajectories as commanded (with the
/// bias correction they were sent with); `after`: the verification of the re-scan; `wear`: the
/// wear the tools were planned with (ProcessOptions::tool_wear_mm). An error (code
/// "compensation.no_cut") when no cut surface was seen; cone tools are not measured.
Result<CutOffset> measure_cut_offset(const LoadedRecipe& recipe, const vision::Inspection& before,
                                     const std::vector<Trajectory>& ground, const VerificationResult& after,
                                     const ToolWearMm& wear = {}, const CutOffsetSettings& settings = {});

/// The iron each tool is to remove in a processed cycle (cm3 by tool name): the excess volume
/// the inspection measured over each planned region. It holds the casting's form deviation
/// above the template too; measure_removed_cm3() is what a verification scan shows.
std::map<std::string, double> removed_cm3(const LoadedRecipe& recipe, const ProcessOutput& processed);
/// The iron each tool removed (cm3 by tool name), seen from above: over each region's
/// re-scanned ROI, by how much the re-scan's surface lies below the first scan's, column by
/// column (base-frame x-y columns of column_mm, the re-scan's surface the highest over the
/// column and its neighbours; a column counts from removed_min_mm down, beneath that is the
/// scanner's noise). The casting's form deviation is in both scans and drops out. At most the
/// region's excess volume in `before` (the template's normals): a fin standing out from a wall
/// overhangs air that a column counts as iron, while the excess counts the form deviation;
/// each is a bound the other is not.
std::map<std::string, double> measure_removed_cm3(const LoadedRecipe& recipe, const vision::Inspection& before,
                                                  const VerificationResult& after, const CutOffsetSettings& settings = {});

/// One wheel's wear as the cell predicts it: the iron it removed since it was fitted times its
/// wear rate, the recipe's stated `wear_mm_per_cm3` until its cut has shown its radius, then the
/// rate those measurements fit (through the origin: wear = rate x removed). The rate is the
/// wheel's kind's, kept when a worn wheel is changed for a new one.
/// A wheel's radius lost to wear: the least, the expected and the most it may be. The cell plans
/// with the least (a wheel planned smaller than it is would be moved into the wall; 0 until the
/// wheel's own rate is measured), closes a riser's rows up for the most and asks for a new wheel
/// when the most passes its life.
struct WearRange {
  double least_mm = 0.0;
  double expected_mm = 0.0;
  double most_mm = 0.0;
};

/// How much of a wheel's wear the cell may leave unknown: the verification's first level
/// (0.3 mm: VerificationSettings::ok_max_share_over_0_3_pct) less the largest allowance of the
/// regions whose finished surface the wheel's radius shapes (a cylinder's side, a ball). Planned
/// at its least wear and worn by its most, the wheel leaves a stub that much wider than the
/// allowance: past 0.3 mm off the template, the verification reads it REGRIND, and the re-grind,
/// planned with the same wheel, leaves it again. nullopt: its radius shapes no region's surface
/// (a cup wheel's flat end on a riser). Test Compensation.AWheelWhoseWearIsNotKnownWellEnoughIsChanged.
[[nodiscard]] std::optional<double> wear_slack_mm(const config::PartRecipe& recipe, const config::Tool& tool);

/// A wheel the cell asks to change (CellBias::worn_out()).
struct WornWheel {
  std::string tool;
  std::string why;  ///< e.g. "worn 2.10 mm (up to 2.73; its life: 3.00 mm)"
};

struct ToolWear {
  double removed_cm3 = 0.0;      ///< by this wheel since it was fitted
  double sum_wv = 0.0;           ///< measured wear x removed, summed over the measurements
  double sum_vv = 0.0;           ///< removed squared, summed
  double sum_ww = 0.0;           ///< measured wear squared, summed (the fit's scatter)
  std::size_t measurements = 0;  ///< cycles whose cut showed the radius
  std::size_t changes = 0;       ///< wheels changed for new ones
  /// Whether the wheel's own rate is measured (its cut has shown the radius often enough).
  [[nodiscard]] bool rate_measured() const;
  /// mm of radius per cm3: the measured rate, else the tool's stated one.
  [[nodiscard]] double rate_mm_per_cm3(const config::Tool& tool) const;
  /// The rate's relative uncertainty (two sigma of its fit from kMinWearMeasurements on, else
  /// the tool's stated tolerance).
  [[nodiscard]] double rate_tolerance(const config::Tool& tool) const;
  /// The wear after `more_cm3` more iron.
  [[nodiscard]] WearRange wear(const config::Tool& tool, double more_cm3 = 0.0) const;
};

/// A region's own learned offset (base frame): its place's share of a hand-eye rotation, its
/// wheel's wear and TCP, which the cell's one offset cannot hold for every region at once.
struct RegionBias {
  Vec3 bias_mm = Vec3::Zero();  ///< along `learned`; the cell's bias along the rest
  Eigen::Matrix3d learned = Eigen::Matrix3d::Zero();
  std::string tool;             ///< the wheel it was learned with: forgotten when that one is changed
  std::size_t updates = 0;
};

/// The cell's learned bias: where its tool cuts minus where it is told to (base frame).
struct CellBias {
  Vec3 bias_mm = Vec3::Zero();
  std::size_t updates = 0;        ///< cycles that contributed since the last reset
  /// Projector onto the directions any update observed (the estimate is learned along them).
  Eigen::Matrix3d learned = Eigen::Matrix3d::Zero();
  /// The measurements' scatter about the estimate (mm^2, base frame): an exponentially weighted
  /// mean of (measured - estimate)(measured - estimate)^T along the observed directions, with
  /// the same gain as the estimate.
  Eigen::Matrix3d scatter_mm2 = Eigen::Matrix3d::Zero();
  std::string calibration_id;     ///< the calibration it was learned under (reset when it changes)
  std::string tools_id;           ///< the tools it was learned with (reset when they change)
  std::map<std::string, ToolWear> tools;  ///< each wheel's wear, by tool name
  std::map<std::string, RegionBias> regions;  ///< each region's own, by region name

  /// Moves the estimate by gain x (measured - estimate) along the measurement's observed
  /// directions, bounded to max_offset_mm, and each measured region's own the same way from
  /// where it stood (region_bias_mm()); returns the cell's step.
  Vec3 update(const CutOffset& measured, const config::CompensationSection& settings);
  /// Where a region is commanded from: its own learned offset along what it learned, the cell's
  /// along the rest.
  [[nodiscard]] Vec3 region_bias_mm(const std::string& region) const;
  /// Every region with an offset of its own, placed by it within `bound_mm2` (the cycle's
  /// placement_uncertainty()): ProcessOptions::region_placement.
  [[nodiscard]] std::map<std::string, RegionPlacement> region_placement(const Eigen::Matrix3d& bound_mm2) const;
  /// Each recipe tool's predicted wear.
  [[nodiscard]] std::map<std::string, WearRange> tool_wear(const config::PartRecipe& recipe) const;
  /// The least of it (ProcessOptions::tool_wear_mm) and the most (ProcessOptions::tool_wear_most_mm).
  [[nodiscard]] ToolWearMm tool_wear_mm(const config::PartRecipe& recipe) const;
  [[nodiscard]] ToolWearMm tool_wear_most_mm(const config::PartRecipe& recipe) const;
  /// Counts a grind's removal (cm3 by tool name, removed_cm3()).
  void add_removed(const std::map<std::string, double>& removed_cm3);
  /// Each wheel in `measured` (a cycle's cut offset, whose paths were planned with the wear
  /// `commanded`) was worn commanded + measured after the removal counted so far: one more
  /// point of its rate's fit.
  void add_wear_measurements(const CutOffset& measured, const ToolWearMm& commanded);
  /// The wheels to change before the next cycle, with why: after one more cycle like the last
  /// (`next_cm3` by tool name) the most a wheel may be worn passes its max_wear_mm, or the
  /// wheel's wear is known less well than its regions leave to the verification
  /// (wear_slack_mm()). Empty: none.
  [[nodiscard]] std::vector<WornWheel> worn_out(const config::PartRecipe& recipe,
                                                const std::map<std::string, double>& next_cm3) const;
  /// A new wheel of the tool's kind is fitted: its removal starts at 0, the rate is kept, and
  /// the regions it grinds forget their own offsets (which hold the old wheel's wear: kept, the
  /// new, larger wheel would cut that much deeper).
  void change_tool(const std::string& name);
  void reset() { *this = CellBias{}; }
  [[nodiscard]] std::string describe() const;  ///< "(x, y, z) mm after N cycles"
};

/// How far from where the plan says the tool may really cut, base frame: the bound along a unit
/// direction n is sqrt(n^T bound_mm2 n). From the cell's stated accuracies ([safety]
/// calibration_accuracy_mm, robot_accuracy_mm and tcp_accuracy_mm as a root sum of squares, the
/// TCP's along the tools' axes only: all of it vertically, sideways by the sine of
/// largest_tool_tilt_deg();
/// plus robot_repeatability_mm: a wheel keeps the deepest of the noisy poses that sweep a point,
/// so the path's noise deepens the cut one-sided by most of its 3 sigma) and what it learned: along
/// the learned directions that sum is replaced by the estimate's own uncertainty, what is left of
/// it after `updates` steps of `gain` plus the measurements' scatter through the estimate's
/// smoothing (gain / (2 - gain) of it). Repeatability stays, as a scatter about the learned depth:
/// learning cannot take the noise itself.
/// Nothing stated: zero (the regions' allowances alone).
/// The planner keeps every path at least this far from the template along the surface's normal
/// (planning::RegionInput::placement_bound_mm2). Tests: Compensation.PlacementUncertainty*.
struct PlacementUncertainty {
  Eigen::Matrix3d bound_mm2 = Eigen::Matrix3d::Zero();
  [[nodiscard]] double along_mm(const Vec3& unit_base) const;
  /// "0.26 mm sideways, 0.16 mm vertically" (the bounds along base x-y and z).
  [[nodiscard]] std::string describe() const;
};
PlacementUncertainty placement_uncertainty(const config::SafetySection& safety, const config::PartRecipe& recipe,
                                           const CellBias& bias, const config::CompensationSection& settings);
/// Whether [safety] states any accuracy (calibration, robot, TCP, repeatability): without one the
/// placement bound is zero and the regions' allowances alone are kept.
bool states_accuracy(const config::SafetySection& safety);
/// How far the recipe's tools lean from the parting plane's normal at most: 90 - chamfer_deg for
/// a flash ground with contact = "chamfer", 0 for every other pose the planner makes (a wheel's
/// side against a wall, a ball or flat end over a face, all along the normal).
double largest_tool_tilt_deg(const config::PartRecipe& recipe);

/// A re-grind in the cycle whose first grind measured `measured`: along the directions that
/// measurement observed it is commanded with the offset measured (this casting, this place, this
/// tool, minutes ago, over thousands of points) and bounded by the stated repeatability and the
/// measurement's own scatter; along the others, as `cell` and placement_uncertainty() have it.
/// The cell's smoothed estimate still holds part of the stated systematic error after a few
/// cycles, and a re-grind bounded by it keeps the stub the first grind left (0.3-0.5 mm on a
/// riser under the realistic error budget). Test Compensation.AReGrindIsBoundedByWhatItsCycleMeasured.
/// A region whose own cut surfaces fixed a direction is commanded along it with its own offset
/// (CutOffset::regions): the whole cut's offset is the riser's where its face holds most of the
/// points, and a fin 120 mm away was cut 0.1-0.15 mm higher than that (test
/// Compensation.AReGrindTakesEachRegionsOwnOffset).
struct RegrindCompensation {
  Vec3 bias_mm = Vec3::Zero();
  PlacementUncertainty placement;
  std::map<std::string, RegionPlacement> regions;  ///< ProcessOptions::region_placement
};
RegrindCompensation regrind_compensation(const config::SafetySection& safety, const config::PartRecipe& recipe,
                                         const CellBias& cell, const CutOffset& measured,
                                         const config::CompensationSection& settings);

/// The wheels' least wear for a re-grind in the cycle whose first grind measured `measured`, its
/// wheels planned worn `commanded`: a wheel whose cut showed its radius is at least commanded +
/// what it measured less two sigma (the measurement errs short: a fin's stub is measured from the
/// points just inside its edge), the others as the cell has them (`cell_least`,
/// CellBias::tool_wear_mm()). The cell's least waits for three measurements to fit the wheel's
/// rate; planned with it, a re-grind leaves the stub the first grind left. Test
/// Compensation.AReGrindTakesTheWearItsCycleMeasured.
ToolWearMm regrind_tool_wear(const ToolWearMm& cell_least, const CutOffset& measured, const ToolWearMm& commanded);

/// The state file: JSON {"bias_mm": [x, y, z], "updates": n, "calibration_id", "tools_id"}.
/// load_cell_bias() returns a zero bias when the file does not exist; a file it cannot read is
/// an Error naming it (the caller starts from zero and says so).
Result<CellBias> load_cell_bias(const std::filesystem::path& file);
Status save_cell_bias(const std::filesystem::path& file, const CellBias& bias);
/// Where the cell keeps it: [compensation] state_file, else <state_dir>/compensation.json.
std::filesystem::path cell_bias_file(const config::CellConfig& cell);
/// A short identity of a recipe's tools (name, shape, size, TCP): fettled resets the learned
/// bias when the tools change (as it does when the calibration's sha256 changes).
std::string tools_identity(const config::PartRecipe& recipe);

}  // namespace fettle::process
