#pragma once
// The processing pipeline shared by fettled, `fettle plan` and `fettle-sim trial`:
//
//   load_recipe()  once per recipe (setup, throws UserError): recipe + golden template +
//                  vision::PartTemplate + the template's signed distance for planning (both
//                  cached on disk: next to the recipe, or where LoadOptions says).
//   process()      per cycle (values, never throws on bad scans): views (camera frame) ->
//                  base frame -> fused scan -> vision::inspect (locate, extract) ->
//                  planning::plan_part (plan, order, validate) -> one Trajectory.
//   verify()       after grinding: the re-scan of each region against the template ->
//                  per-region counts over 0.3 / 0.4 / 0.5 mm and a verdict OK / REGRIND / NOK.
//
// Frames: base = robot base = fixture frame (table top z = 0, z up); part = the template's
// frame (recipe ROIs are in it); camera = the 3D camera of one view. T_target_source maps
// source points into target. Millimetres and radians.
//
// Golden template (where it comes from, without the daemon knowing the simulator):
//  - [template] source = "scan": the golden scan file `scan` (PLY/PCD, part frame, mm,
//    normals used when present) of the recipe.
//  - [template] source = "simulator": the golden file `<recipe dir>/<recipe stem>.golden.ply`
//    (or `scan` when given), written by `fettle-sim golden --part part.toml` (the simulator's
//    golden part sampled in the part frame with outward normals). A missing file is a
//    UserError naming the file and the command that writes it.
//  - LoadOptions::golden: a golden cloud in memory (fettle-sim trial, tests); no file read.
// See docs/planning.md.
#include <cstddef>
#include <filesystem>
#include <functional>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "fettle/config/cell.hpp"
#include "fettle/config/part.hpp"
#include "fettle/core/cloud.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"
#include "fettle/core/trajectory.hpp"
#include "fettle/planning/io.hpp"
#include "fettle/planning/planner.hpp"
#include "fettle/planning/sdf_grid.hpp"
#include "fettle/vision/cloud.hpp"
#include "fettle/vision/inspect.hpp"

namespace fettle::process {

/// Called by long steps: (done, total, what is running now, e.g. "vision", "plan riser").
using Progress = std::function<void(std::size_t done, std::size_t total, const std::string& step)>;

// ---------------------------------------------------------------------------------------------
// Setup

struct LoadOptions {
  /// Golden cloud in the part frame (mm, outward normals if known). When set, no golden file
  /// is read (fettle-sim trial hands the simulator's golden part over in memory).
  std::optional<vision::Cloud> golden;
  /// Identity of an in-memory golden for the template cache (e.g. "sim:pump-body:0.5").
  std::string golden_identity;
  /// Where the planner's signed-distance grid is cached. Empty: `<recipe dir>/.<recipe
  /// stem>.planning-cache/` when the recipe's vision.cache is on, else not cached. The cache
  /// key is a hash of the golden samples and of the settings, so an in-memory golden can be
  /// cached too (bench, fettle-sim trial).
  std::filesystem::path sdf_cache_dir;
  /// Where the vision template is cached. Empty: `<recipe dir>/.<recipe stem>.vision-cache/`
  /// when the recipe's vision.cache is on, else not cached. Its key names the golden by
  /// `golden_identity` (or the golden file's path, size and time), not by its points.
  std::filesystem::path template_cache_dir;
};

/// Where a recipe's planner grid is cached by default: `<recipe dir>/.<recipe stem>.planning-cache/`
/// (the grid in it: sdf_grid_file()). fettled, fettle-sim soak (which seeds its copy of the
/// recipe with a grid) and the demo agree on it through this.
std::filesystem::path planning_cache_dir(const std::filesystem::path& recipe_file);
/// The grid's file in a planning cache directory.
std::filesystem::path sdf_grid_file(const std::filesystem::path& planning_cache_dir);

/// Everything computed once per recipe.
struct LoadedRecipe {
  config::PartRecipe recipe;
  std::filesystem::path golden_file;  ///< the golden file read (empty when given in memory)
  std::string golden_identity;        ///< cache key of the golden
  vision::PartTemplate templ;         ///< whole-part and per-region templates (vision)
  planning::SignedDistance template_sdf;  ///< signed distance to the template, part frame (planning): a grid
  planning::SdfGridStats sdf_grid;        ///< that grid's size (memory, bricks, exact cells, build time)
  bool sdf_from_cache = false;            ///< the grid was read from the planning cache
  std::vector<Eigen::Vector3f> template_points;  ///< template surface samples, part frame (previews, verify)
  bool template_from_cache = false;
  double load_ms = 0.0;

  /// The [[tools]] entry of a region (validated by the loader to exist).
  [[nodiscard]] const config::Tool& tool_for(const config::Region& region) const;
  /// The [[regions]] entry named `name`, or nullptr.
  [[nodiscard]] const config::Region* region(const std::string& name) const;
};

/// Where the golden file of a recipe is expected (see the header comment).
std::filesystem::path golden_path(const config::PartRecipe& recipe);

/// Builds a LoadedRecipe. Throws UserError (file and reason) when the golden cannot be read
/// or the template cannot be built.
LoadedRecipe load_recipe(const config::PartRecipe& recipe, const LoadOptions& options = {});
/// Reads the part file first (config::load_part; ConfigError lists every problem).
LoadedRecipe load_recipe(const std::filesystem::path& part_file, const LoadOptions& options = {});

// ---------------------------------------------------------------------------------------------
// Per cycle

/// One capture of the 3D camera.
struct View {
  OrganizedCloud cloud;                             ///< camera frame, mm, NaN = invalid
  Transform T_base_camera = Transform::Identity();  ///< camera pose at this slide position
  double slide_position_mm = 0.0;
};

/// Time spent in one step of the pipeline.
struct StepTiming {
  std::string step;  ///< "fuse", "vision", "plan", "verify", ...
  double ms = 0.0;
};

/// Per-region outcome of process().
struct RegionMetrics {
  std::string name;
  config::RegionType type = config::RegionType::riser;
  std::size_t scene_points = 0;   ///< scan points in the region's ROI
  double fitness = 0.0;           ///< fine ICP fitness of the region
  double rmse_mm = 0.0;
  std::size_t excess_points = 0;
  double excess_volume_mm3 = 0.0;
  double excess_max_height_mm = 0.0;
  std::size_t trajectory_points = 0;  ///< grinding points planned for the region (0 = nothing to grind)
  int segments = 0;
  double plan_ms = 0.0;
  /// Excess material the tool cannot reach without cutting the template, left on the part
  /// (no higher than the planner's leave_unreachable_mm; process() also logs a warning): its
  /// height in mm (0: none) and where (part frame).
  double material_left_mm = 0.0;
  Vec3 material_left_at = Vec3::Zero();
  double material_left_length_mm = 0.0;  ///< straight flash: the length of fin so left (RegionPlan)
};

/// Each tool's radius lost to wear, mm, by tool name (process::CellBias::tool_wear_mm()).
using ToolWearMm = std::map<std::string, double>;
/// The recipe's tool as worn by `wear`: its diameter less twice its wear (at least 0.1 mm).
config::Tool worn_tool(const config::Tool& tool, const ToolWearMm& wear);

/// One region's own placement, in place of the cycle's (ProcessOptions::cell_bias_mm and
/// placement_bound_mm2 for it): what a re-grind measured on that region's cut.
struct RegionPlacement {
  Vec3 bias_mm = Vec3::Zero();
  Eigen::Matrix3d bound_mm2 = Eigen::Matrix3d::Zero();
};

struct VerificationResult;

struct ProcessOptions {
  /// Regions to plan (names); empty = all. A re-grind plans only what verify() flagged.
  std::vector<std::string> regions;
  /// The cell's learned bias (fettle/process/compensation.hpp), base frame: every path is
  /// commanded shifted by minus it, so that the tool cuts where the plan says. Planning and
  /// validation work in the part frame as located, then place it in the base frame shifted.
  Vec3 cell_bias_mm = Vec3::Zero();
  /// How far the tool may really cut from where it is told (base frame, mm^2; the bound along a
  /// unit n is sqrt(n^T M n)): every region keeps at least this from the template along the
  /// surface's normal where it exceeds the region's allowance (process::placement_uncertainty).
  Eigen::Matrix3d placement_bound_mm2 = Eigen::Matrix3d::Zero();
  /// Regions (by name) placed by their own bias and bound instead (process::RegrindCompensation).
  std::map<std::string, RegionPlacement> region_placement;
  /// A re-grind: the cycle's first inspection. Each region's material is measured from the
  /// casting's face as that scan saw it: on the ground casting, a stub the passes left within
  /// the form deviation fits as the face, and the re-grind would find nothing to grind.
  const vision::Inspection* before = nullptr;
  /// A re-grind: the cycle's first plans (ProcessOutput::plans). A ring or circle flash is
  /// ground again along its first plan's ring (planning::RegionInput::first).
  const std::vector<planning::RegionPlan>* before_plans = nullptr;
  /// A re-grind: the verification that asked for it. The fin a flash's first grind left more
  /// than the verification's first level (0.3 mm) off the wall shows where the wheel's side
  /// stood (planning::RegionInput::leftover_part).
  const VerificationResult* leftover = nullptr;
  /// The wheels' wear as the cell predicts it (process::CellBias::tool_wear): each region is
  /// planned with its tool smaller by the least wear (a worn disc's side is moved in to the
  /// wall by no more than it surely wore), and a riser's rows close up for the most.
  ToolWearMm tool_wear_mm;
  ToolWearMm tool_wear_most_mm;
};

struct ProcessOutput {
  vision::Inspection inspection;   ///< localisation and excess material (part frame)
  Transform T_base_part = Transform::Identity();
  Trajectory trajectory;           ///< validated; empty points when nothing needs grinding
  std::vector<StepTiming> timings;  ///< per step, ms
  std::vector<RegionMetrics> regions;
  std::vector<planning::RegionPlan> plans;  ///< the regions' plans as planned (part frame diagnostics)
  std::vector<planning::PreviewPoint> preview;  ///< scan (base frame) coloured by excess, for preview.png
  double total_ms = 0.0;
};

/// Processes one cycle's views. Never throws on bad scans: an Error whose code is
/// "pipeline.<step>" (or the vision/planning code) and whose message names the step and the
/// region. Safe to call concurrently on the same LoadedRecipe.
Result<ProcessOutput> process(const LoadedRecipe& recipe, const config::CellConfig& cell,
                              const std::vector<View>& views, const Progress& progress = {});
Result<ProcessOutput> process(const LoadedRecipe& recipe, const config::CellConfig& cell,
                              const std::vector<View>& views, const ProcessOptions& options,
                              const Progress& progress = {});

/// The views in the base (= fixture) frame, each without its flying pixels first when
/// jump_edge_mm > 0, fused into one cloud when there are several (vision::fuse_views refines
/// each view's slide pose against the first).
Result<vision::Cloud> fuse_in_base(const std::vector<View>& views, double jump_edge_mm = 0.0);

/// `fettle template build` ([template] source = "scan"): the golden casting's template from
/// views of it lying on the fixture as the castings will.
struct TemplateBuildSettings {
  double voxel_mm = 0.25;        ///< the template's point spacing
  double above_table_mm = 1.0;   ///< points lower than this over the table (the part frame's z = 0) are the table
  double cluster_gap_mm = 2.0;   ///< the casting is the largest piece no gap wider than this divides (clamps, clutter)
  int normal_neighbours = 16;    ///< normals: PCA over this many neighbours
  /// The casting's box in the part frame (from its drawing, with a margin), when given
  /// (box_min_mm < box_max_mm): a clamp 10 mm from the casting is joined to it by the views'
  /// mixed pixels (a veil down each occluding edge), which the largest piece cannot cut.
  Vec3 box_min_mm = Vec3::Zero();
  Vec3 box_max_mm = Vec3::Zero();
};
struct BuiltTemplate {
  vision::Cloud cloud;             ///< part frame (the fixture's nominal), mm, with outward normals
  std::size_t fused_points = 0;    ///< the views' points fused
  std::size_t dropped_points = 0;  ///< above the table but not on the casting (clamps, clutter)
};
/// Fuses the views, takes them into the part frame by the fixture's nominal pose, drops the
/// table and everything not joined to the casting, downsamples to voxel_mm and estimates
/// normals, each turned towards the camera that saw it. An Error (code "template.empty" or the
/// fuse step's) when no casting is seen. Test TemplateBuild.* (tests/process/test_template_build.cpp).
Result<BuiltTemplate> build_template(const config::PartRecipe& recipe, const std::vector<View>& views,
                                     const TemplateBuildSettings& settings = {});

/// Writes trajectory.json, trajectory.csv and preview.png of a processed cycle into `dir`.
Status write_outputs(const std::filesystem::path& dir, const ProcessOutput& output);

// ---------------------------------------------------------------------------------------------
// Verification after grinding

enum class Verdict { ok, regrind, nok };
const char* to_string(Verdict verdict);  ///< "OK", "REGRIND", "NOK"

struct RegionVerification {
  std::string name;
  config::RegionType type = config::RegionType::riser;
  std::size_t roi_points = 0;  ///< re-scanned points inside the region's ROI
  std::size_t over_0_3 = 0;    ///< points farther than 0.3 / 0.4 / 0.5 mm from the template
  std::size_t over_0_4 = 0;
  std::size_t over_0_5 = 0;
  double share_over_0_3_pct = 0.0;
  double share_over_0_4_pct = 0.0;
  double share_over_0_5_pct = 0.0;
  double max_residual_mm = 0.0;      ///< largest |distance| to the template
  double max_above_mm = 0.0;         ///< highest material left above the template (>= 0)
  double max_below_mm = 0.0;         ///< deepest point below the template (>= 0, a gouge)
  /// The casting's own face over the template at the ROI's centre as the scan before grinding
  /// found it (VerifyOptions::before; the region's form offset). 0 when none was fitted.
  double form_offset_mm = 0.0;
  /// Every distance above is measured from the casting's own upward faces as the first scan saw
  /// them (VerifyOptions::before), not from the template.
  bool against_casting = false;
  Verdict verdict = Verdict::ok;
  std::string reason;                ///< why REGRIND / NOK (threshold and value)
  /// The pose that puts roi_points_part into the base frame (the region's own fine pose in the
  /// re-scan, else the whole part's).
  Transform T_base_region = Transform::Identity();
  std::vector<Eigen::Vector3f> roi_points_part;  ///< the ROI points (part frame), for roi_<region>.ply
  std::vector<float> residual_mm;               ///< their signed distances (> 0 = above)
};

/// The deepest place the re-scan shows below the template wherever the tool went (every ROI and
/// the swept footprint of every uploaded pose and move), confirmed by its neighbours.
struct GougeFinding {
  double depth_mm = 0.0;          ///< below the template (median of the confirming points, > 0)
  Vec3 at_part = Vec3::Zero();    ///< where (part frame, mm)
  std::string region;             ///< the region whose ROI holds it, else whose tool went there
  bool in_roi = false;            ///< inside that region's ROI
  std::size_t points = 0;         ///< re-scan points that confirm it
  /// "gouged in region <name> at (x, y, z) mm (part frame), depth d mm" or "gouged outside
  /// region <name> at ..." (outside every ROI, in the footprint of <name>'s tool).
  [[nodiscard]] std::string describe() const;
};

struct VerificationResult {
  Transform T_base_part = Transform::Identity();  ///< where the re-scan found the part
  std::vector<RegionVerification> regions;
  Verdict verdict = Verdict::ok;      ///< NOK if any region is NOK or a gouge deeper than
                                      ///< gouge_depth_mm is found; else REGRIND if any is; else OK
  /// The deepest confirmed place below the template (none: no point of the searched area is
  /// more than gouge_depth_mm below it, or none is confirmed by its neighbours).
  std::optional<GougeFinding> worst_gouge;
  /// The deepest confirmed place below the template in the searched area, gouge or not (0 when
  /// none is more than half of gouge_depth_mm below it).
  double deepest_below_mm = 0.0;
  std::size_t footprint_points = 0;   ///< re-scan points in the swept footprint outside every ROI
  std::vector<StepTiming> timings;
  /// Names of the regions whose verdict is REGRIND (for process() with ProcessOptions).
  [[nodiscard]] std::vector<std::string> regrind_regions() const;
};

struct VerifyOptions {
  /// The first inspection of this casting (ProcessOutput::inspection), or none. With a recipe's
  /// form_deviation_mm its regions' faces (vision::FormOffset) are the casting's own before
  /// grinding, and the re-scan, placed where the camera saw it in the first inspection's frame,
  /// is judged against those: a body that stands 0.4 mm under the nominal is neither a gouge
  /// nor, where it stands over it, material left. Only upward faces move (walls keep the
  /// template). Tests Pipeline.VerifyTheCastingsOwnFace*.
  const vision::Inspection* before = nullptr;
};

/// Compares the re-scan of each region with the template (thresholds from the recipe's
/// [verification] table), and looks for gouges in every ROI and in the swept footprint of
/// every pose of `ground` (the trajectories uploaded in this cycle, base frame): a place more
/// than gouge_depth_mm below the template there makes the verdict NOK. Never throws on bad scans.
Result<VerificationResult> verify(const LoadedRecipe& recipe, const config::CellConfig& cell,
                                  const std::vector<View>& rescan, const std::vector<Trajectory>& ground,
                                  const Progress& progress = {});
Result<VerificationResult> verify(const LoadedRecipe& recipe, const config::CellConfig& cell,
                                  const std::vector<View>& rescan, const std::vector<Trajectory>& ground,
                                  const VerifyOptions& options, const Progress& progress = {});
/// As above with nothing ground (only the ROIs are searched for gouges).
Result<VerificationResult> verify(const LoadedRecipe& recipe, const config::CellConfig& cell,
                                  const std::vector<View>& rescan, const Progress& progress = {});

}  // namespace fettle::process
