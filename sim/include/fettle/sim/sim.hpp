#pragma once
// fettle::sim - the simulated casting, structured-light scanner and grinding process.
//
// Frames (docs/simulator.md):
//   base    robot base = cell world frame; the fixture table top is z = 0, z up.
//   part    the casting's own frame (the template frame; recipe ROIs are in it),
//           bottom on z = 0. The true placement is T_base_part.
//   camera  OpenCV convention: z along the optical axis, x right, y down in the image.
//           T_base_camera(s) = T_base_slide(s) * T_slide_camera for slide position s.
// Millimetres and radians everywhere. Same seed and inputs -> byte-identical outputs.
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "fettle/config/cell.hpp"
#include "fettle/config/part.hpp"
#include "fettle/core/cloud.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"
#include "fettle/core/trajectory.hpp"
#include "fettle/core/trajectory_io.hpp"

namespace fettle::sim {

/// Called by long jobs: (done, total, what).
using Progress = std::function<void(std::size_t done, std::size_t total, const std::string& what)>;

// ---------------------------------------------------------------------------------------------
// Casting and golden template

/// A surface sample in the part frame with its outward unit normal.
struct SurfacePoint {
  Eigen::Vector3f position_mm;
  Eigen::Vector3f normal;
};

/// Material still to be removed in one recipe region (ground truth).
struct RegionTruth {
  std::string name;                       ///< recipe region name
  config::RegionType type = config::RegionType::riser;
  double volume_mm3 = 0.0;                ///< removable material left
  double max_height_mm = 0.0;             ///< largest height above the golden surface along the removal direction
  Eigen::Vector3d removal_direction{0, 0, 1};  ///< part frame; radial regions report +z here and use `radial`
  bool radial = false;                    ///< ring/circle flash: height measured radially from `axis_center_mm`
  Eigen::Vector3d axis_center_mm{0, 0, 0};
};

/// A cut into the golden body deeper than the gouge threshold.
struct Gouge {
  Eigen::Vector3d position_mm;  ///< part frame, deepest point of the cut
  double depth_mm = 0.0;
  std::size_t pose_index = 0;   ///< interpolated pose where it was deepest
};

struct CastingOptions {
  bool vary = true;  ///< false: every range at its midpoint, no form deviation, nominal placement
};

/// The other hand of a left/right pair: the recipe with its [geometry] mirrored in x (blocks,
/// cylinders, flashes, risers). Castings of it are the wrong part for that recipe.
config::PartRecipe mirrored_in_x(const config::PartRecipe& recipe);

class CastingModel;  // private implementation

/// One individual casting (the golden body + its form deviation + flash and risers) placed
/// on the fixture. A value type: copies are independent castings (e.g. to grind a copy).
class Casting {
 public:
  /// Builds casting number `seed` of a recipe; throws UserError when the recipe has no
  /// [geometry] or its geometry cannot be built.
  static Casting make(const config::PartRecipe& recipe, std::uint64_t seed, const CastingOptions& options = {});
  /// The golden template: the same part ground to specification (nominal body, no
  /// flash or riser, no form deviation), placed like `make` would place it with `seed`.
  static Casting golden(const config::PartRecipe& recipe, std::uint64_t seed = 0);

  Casting(const Casting& other);
  Casting& operator=(const Casting& other);
  Casting(Casting&&) noexcept;
  Casting& operator=(Casting&&) noexcept;
  ~Casting();

  [[nodiscard]] std::uint64_t seed() const;
  [[nodiscard]] const std::string& part_id() const;
  [[nodiscard]] const Transform& T_base_part() const;
  void set_T_base_part(const Transform& T_base_part);

  /// Removable material per recipe region (in recipe order).
  [[nodiscard]] std::vector<RegionTruth> material() const;
  /// Top of the current surface at (x, y) in the part frame (NaN off the part).
  [[nodiscard]] double surface_z_mm(double x_mm, double y_mm) const;
  /// The part-frame axis-aligned bounding box of the part (min, max).
  [[nodiscard]] std::pair<Vec3, Vec3> bounds_part_mm() const;
  /// Samples the golden body's visible surface (tops and walls) in the part frame, about
  /// `spacing_mm` apart, with outward normals. Deterministic.
  [[nodiscard]] std::vector<SurfacePoint> sample_golden_surface(double spacing_mm) const;
  /// Distance of a part-frame point to the current (as-cast or ground) surface.
  [[nodiscard]] double distance_to_surface_mm(const Vec3& p_part) const;
  /// RMS of distance_to_surface_mm over every `stride`-th of `points`, mapped into the part
  /// frame by T_part_points (how close a template placed with some pose lies to this surface).
  [[nodiscard]] double rms_distance_to_surface_mm(const std::vector<Eigen::Vector3f>& points,
                                                  const Transform& T_part_points, std::size_t stride = 1) const;
  /// Distance of a part-frame point to the golden surface.
  [[nodiscard]] double distance_to_golden_mm(const Vec3& p_part) const;
  /// Distance of a part-frame point to this casting's own body: the golden surface with this
  /// casting's form deviation, without flash or riser (what a perfect fettling leaves).
  [[nodiscard]] double distance_to_body_mm(const Vec3& p_part) const;
  /// Top of the golden body at (x, y), part frame (NaN off the body).
  [[nodiscard]] double golden_top_z_mm(double x_mm, double y_mm) const;
  /// Removes every bit of flash and riser exactly (an oracle "perfect grind", no tool).
  void remove_all_material();
  /// Takes the part off the fixture: scans show the table, clamps and clutter only (an empty
  /// fixture). The material and surface queries still answer for the part.
  void take_off_fixture();
  [[nodiscard]] bool on_fixture() const;
  /// Signed distance to the golden body solid (negative inside), part frame.
  [[nodiscard]] double golden_sdf_mm(const Vec3& p_part) const;
  /// This casting's form deviation at (x, y), part frame: how far its body's top stands over
  /// the nominal's (0 for a golden casting or one drawn without variation).
  [[nodiscard]] double form_deviation_mm(double x_mm, double y_mm) const;

  [[nodiscard]] const CastingModel& model() const { return *model_; }
  CastingModel& model() { return *model_; }

 private:
  explicit Casting(std::unique_ptr<CastingModel> model);
  std::unique_ptr<CastingModel> model_;
};

// ---------------------------------------------------------------------------------------------
// Scanner

/// Pinhole camera with OpenCV's radial-tangential distortion (k1, k2, p1, p2, k3).
struct CameraIntrinsics {
  int width = 2064;
  int height = 1544;
  double fx = 2300.0, fy = 2300.0;
  double cx = 1031.5, cy = 771.5;
  double k1 = -0.04, k2 = 0.012, p1 = 0.0004, p2 = -0.0003, k3 = 0.0;

  /// Projects a camera-frame point to a distorted pixel (u, v).
  [[nodiscard]] Eigen::Vector2d project(const Vec3& p_camera) const;
  /// The normalized ray (x, y, 1) through distorted pixel (u, v) (iterative undistortion).
  [[nodiscard]] Vec3 ray(double u, double v) const;
  /// The same camera at another resolution (focal length and centre scaled).
  [[nodiscard]] CameraIntrinsics scaled(int new_width, int new_height) const;
};

/// Measurement errors of the scanner.
struct NoiseModel {
  double sigma_z_mm = 0.05;            ///< depth noise at the reference distance, head-on
  double reference_distance_mm = 600.0;
  double distance_exponent = 2.0;      ///< sigma grows with (distance / reference)^exponent
  double grazing_gain = 1.0;           ///< sigma *= 1 + gain * (1/cos(incidence) - 1)
  double dropout_start_deg = 60.0;     ///< dropouts start at this incidence angle ...
  double dropout_full_deg = 78.0;      ///< ... and every pixel drops out beyond this one
  double surface_dropout_fraction = 0.01;  ///< fraction of the surface (patches of ~4 mm) that never returns
  double flying_pixel_fraction = 0.3;  ///< fraction of depth-discontinuity pixels that become flying pixels
  double discontinuity_mm = 3.0;       ///< neighbour depth jump that counts as a discontinuity
  double outlier_fraction = 2e-5;      ///< random outliers (anywhere within +-outlier_range_mm)
  double outlier_range_mm = 60.0;
  bool enabled = true;                 ///< false: ideal range images (tests)
};

struct ScannerConfig {
  CameraIntrinsics intrinsics;
  NoiseModel noise;
  std::vector<double> photo_positions_mm{0.0};  ///< slide.photo_positions_mm of the cell
  /// T_base_slide(s) = translation(slide_origin_mm + s * slide_axis) (axes of base).
  Vec3 slide_origin_mm{-60.0, 0.0, 600.0};
  Vec3 slide_axis{1.0, 0.0, 0.0};
  /// Camera on the slide: looking straight down (camera z = -base z, camera x = base x).
  Transform T_slide_camera = default_T_slide_camera();
  double min_range_mm = 300.0;  ///< no return nearer than this ...
  double max_range_mm = 1100.0;  ///< ... or farther
  int threads = 2;              ///< render threads (the result does not depend on it)

  [[nodiscard]] Transform T_base_slide(double slide_position_mm) const;
  [[nodiscard]] Transform T_base_camera(double slide_position_mm) const;
  static Transform default_T_slide_camera();
  /// Places the scanner as `cell` says: its photo positions, and the camera where the cell's
  /// calibration file puts it at slide position 0 (T_base_camera), moving along base x. A cell
  /// without a calibration file leaves the pose as it is. Throws config errors as load_cell does.
  void place_in_cell(const config::CellConfig& cell);
};

/// GenICam Coord3D_C16-style range image: Z (camera frame, mm) = value * scale + offset;
/// `invalid_value` marks pixels without a measurement. Row-major, width * height.
struct RangeImage16 {
  std::uint32_t width = 0, height = 0;
  double scale_mm = 0.02;
  double offset_mm = 0.0;
  std::uint16_t invalid_value = 0;
  std::vector<std::uint16_t> data;
};

/// Float range image: Z (camera frame, mm), NaN where invalid.
struct RangeImageF32 {
  std::uint32_t width = 0, height = 0;
  std::vector<float> data;
};

/// Ground truth of one capture.
struct GroundTruth {
  std::string part_id;
  std::uint64_t seed = 0;
  std::size_t view = 0;
  double slide_position_mm = 0.0;
  Transform T_base_camera = Transform::Identity();
  Transform T_base_part = Transform::Identity();
  CameraIntrinsics intrinsics;
  std::vector<RegionTruth> regions;
  std::vector<Gouge> gouges;  ///< cuts into the golden body so far
};

struct Capture {
  OrganizedCloud cloud;  ///< camera frame, mm, NaN = invalid
  RangeImageF32 range;
  RangeImage16 range16;
  GroundTruth truth;
};

/// Renders captures by ray casting the scene (table, clamps, clutter, casting).
class Scanner {
 public:
  explicit Scanner(ScannerConfig config);
  ~Scanner();
  Scanner(Scanner&&) noexcept;
  Scanner& operator=(Scanner&&) noexcept;

  [[nodiscard]] const ScannerConfig& config() const;
  /// One capture at a slide position. `view` selects the noise stream (views differ).
  [[nodiscard]] Capture capture(const Casting& casting, double slide_position_mm, std::size_t view = 0) const;
  /// One capture per configured photo position.
  [[nodiscard]] std::vector<Capture> capture_all(const Casting& casting) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// Range image helpers.
RangeImage16 to_range16(const RangeImageF32& range, double scale_mm = 0.02, double offset_mm = 0.0,
                        std::uint16_t invalid_value = 0);
RangeImageF32 to_range_f32(const RangeImage16& range);
/// Back-projects a range image (Z per pixel) into an organized cloud with the intrinsics.
OrganizedCloud to_cloud(const RangeImageF32& range, const CameraIntrinsics& intrinsics);

// ---------------------------------------------------------------------------------------------
// Files

/// PLY (core's format, fettle/core/ply.hpp) of the valid points; `T` maps them first.
Status write_valid_points_ply(const std::filesystem::path& path, const OrganizedCloud& cloud,
                              const Transform& T = Transform::Identity());
/// PCD (binary, organized width x height, NaN invalid, mm).
Status write_pcd(const std::filesystem::path& path, const OrganizedCloud& cloud);
/// Range images: <stem>.c16 raw uint16 + <stem>.c16.json (width, height, scale, offset,
/// invalid value, pixel format "Coord3D_C16"), <stem>.f32 raw float32 + JSON.
Status write_range_images(const std::filesystem::path& dir, const std::string& stem, const Capture& capture);
/// Ground truth as JSON (camera pose, part pose, intrinsics, per-region volume and height, gouges).
std::string ground_truth_json(const GroundTruth& truth);
/// Writes everything of a capture into `dir` with file names starting with `stem`.
Status write_capture(const std::filesystem::path& dir, const std::string& stem, const Capture& capture);
/// A PNG of the valid points coloured by base-frame height (for docs and eyes).
Status write_height_png(const std::filesystem::path& path, const Capture& capture);

// ---------------------------------------------------------------------------------------------
// Grinding

/// Cell limits a trajectory must respect to be executed.
struct CellLimits {
  Vec3 workspace_min_mm{-600.0, -600.0, -20.0};
  Vec3 workspace_max_mm{600.0, 600.0, 800.0};
  double max_speed_mm_s = 500.0;
  double max_spindle_rpm = 20000.0;
};

/// Trajectory files (JSON or CSV): core's format, fettle/core/trajectory_io.hpp.
using fettle::read_trajectory;
using fettle::write_trajectory_json;
/// Checks a trajectory before execution: finite values, unit quaternions, points inside the
/// cell, speeds and spindle speeds within limits. The error names the first bad point.
Status validate_trajectory(const Trajectory& trajectory, const CellLimits& limits);

struct GrindOptions {
  config::Tool tool;                     ///< tool shape and size (TCP at the tool tip, tool z toward the spindle)
  double path_noise_mm = 0.02;           ///< executed = commanded + N(0, sigma) per axis ...
  Vec3 path_bias_mm{0.0, 0.0, 0.0};      ///< ... + this bias (a calibration error), base frame
  double tcp_length_error_mm = 0.0;      ///< the tool is this much longer than the robot is told (tip further along -z_tool)
  double interpolation_mm = 0.1;         ///< poses at most this far apart
  double gouge_threshold_mm = 0.02;      ///< cuts into the golden body deeper than this are gouges
  std::uint64_t noise_seed = 1;
  bool only_when_spindle_on = true;      ///< spindle off = no cutting (collisions still recorded as gouges)
  /// Reference mode for tests: every cell of each pose's bounding box gets the exact test, none
  /// is skipped by the tile bounds or the cheap inside test. Same result, 5-20x slower.
  bool exhaustive = false;
};

struct GrindResult {
  std::size_t poses = 0;                      ///< interpolated poses executed
  std::vector<RegionTruth> before, after;     ///< material per region
  std::vector<Gouge> gouges;
  /// The deepest the tool went into this casting's own body (the nominal with its form
  /// deviation; `gouges` are against the nominal): where a person sees a cut into the as-cast
  /// face. 0 when it never went below it.
  Gouge deepest_body_cut;
  [[nodiscard]] double removed_mm3() const;
  [[nodiscard]] double max_gouge_depth_mm() const;
};

/// Executes a (validated) trajectory on the casting, removing material inside the swept
/// tool volume. Returns an error (and touches nothing) if the trajectory is invalid.
Result<GrindResult> grind(Casting& casting, const Trajectory& trajectory, const GrindOptions& options,
                          const CellLimits& limits = {}, const Progress& progress = {});

/// One run of a planned trajectory: consecutive points of one region, ground with its tool.
struct RegionGrind {
  std::string region;  ///< from the trajectory's segment_regions ("" if it names none)
  std::string tool;
  GrindResult result;
};

/// A planned trajectory ground run by run.
struct PlannedGrind {
  std::vector<RegionGrind> runs;
  /// All runs together: the material before the first and after the last, the poses summed,
  /// the gouges with pose_index counting all the runs' poses.
  GrindResult total;
};

/// Grinds a planned trajectory run by run: each run of consecutive points of one region (by
/// its segment's entry in segment_regions) with that region's tool from the recipe, or every
/// run with `tool` when it is not empty; a trajectory without region names is one run with the
/// recipe's first tool. A run's path noise is seeded from base.noise_seed and the index of
/// the point after the run, so it does not depend on the other runs. Stops at the first
/// error (naming the region). base.tool is ignored.
Result<PlannedGrind> grind_by_region(Casting& casting, const Trajectory& trajectory, const config::PartRecipe& recipe,
                                     const GrindOptions& base, const std::string& tool = {}, const CellLimits& limits = {},
                                     const Progress& progress = {});

/// Tool by name from the recipe (throws UserError if absent).
const config::Tool& find_tool(const config::PartRecipe& recipe, const std::string& name);

// ---------------------------------------------------------------------------------------------
// Evaluation (Zhu et al. 2022, section 4)

struct RegionEvaluation {
  std::string name;
  std::size_t roi_points = 0;  ///< scanned points inside the region's ROI
  std::size_t over_0_3 = 0;    ///< points farther than 0.3 / 0.4 / 0.5 mm from the reference
  std::size_t over_0_4 = 0;
  std::size_t over_0_5 = 0;
  double max_residual_mm = 0.0;
};

struct Evaluation {
  std::string label;  ///< e.g. "template comparison, seed 3"
  std::vector<RegionEvaluation> regions;
  std::size_t gouge_count = 0;
  double max_gouge_depth_mm = 0.0;
};

/// "Template comparison": scanned points (camera frame, with ground-truth poses) against the
/// golden surface, per recipe region ROI.
Evaluation evaluate_against_template(const config::PartRecipe& recipe, const std::vector<Capture>& captures,
                                     const Casting& casting, const std::vector<Gouge>& gouges = {});
/// "Batch consistency": scanned points of one ground casting against the surface of another
/// (the reference) ground casting, per region ROI.
Evaluation evaluate_against_part(const config::PartRecipe& recipe, const std::vector<Capture>& captures,
                                 const Casting& reference);
/// Points of `points_part` (part frame) inside the region's ROI, counted against a distance function.
RegionEvaluation evaluate_region(const config::Region& region, const std::vector<Eigen::Vector3f>& points_part,
                                 const std::function<double(const Vec3&)>& distance_mm);
/// The paper's table layout (ROI points and counts over 0.3/0.4/0.5 mm per region).
std::string format_table(const std::vector<Evaluation>& evaluations);

}  // namespace fettle::sim
