#pragma once
// Rigid registration: a cloud prepared once (downsampled, normals, FPFH features, search
// trees), coarse alignment (FPFH correspondences + RANSAC with pre-rejection, optionally
// bounded by a pose prior) and fine point-to-plane ICP. Results are values.
//
// Convention: T_scene_template maps template points into the scene. `fitness` is the
// fraction of template points that have a scene point within the inlier distance, `rmse`
// the RMS distance of those inliers (Open3D's definitions with the template as source).
#include <cstdint>
#include <filesystem>
#include <memory>
#include <optional>
#include <string_view>

#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"
#include "fettle/vision/cloud.hpp"

namespace fettle::vision {

struct PrepareSettings {
  double coarse_voxel = 3.0;     ///< voxel of the coarse (feature) cloud
  double feature_radius = 15.0;  ///< FPFH support radius
  double normal_radius = 0.0;    ///< coarse normals radius; 0 = 2 * coarse_voxel
  int fine_normal_neighbours = 12;  ///< k for the normals of the fine cloud when it has none
  int threads = 0;               ///< 0 = one per core
  bool features = true;          ///< false: no coarse cloud or FPFH (fine ICP only)
  /// > 0: a dense lookup grid of this cell size answers ICP's nearest-point queries within
  /// `nearest_grid_band` of the fine points (one memory read instead of a tree search).
  double nearest_grid_cell = 0.0;
  double nearest_grid_band = 0.0;
};

/// A cloud with everything registration needs, computed once (templates are prepared at
/// recipe load and cached; scenes every cycle). Cheap to copy (shared, immutable).
class PreparedCloud {
 public:
  PreparedCloud();
  static PreparedCloud prepare(const Cloud& fine, const PrepareSettings& settings);

  [[nodiscard]] const Cloud& fine() const;    ///< full resolution, with normals
  [[nodiscard]] const Cloud& coarse() const;  ///< downsampled, with normals
  [[nodiscard]] const PrepareSettings& settings() const;
  [[nodiscard]] bool empty() const;
  /// Median spacing of the fine points (nearest-neighbour distance).
  [[nodiscard]] double fine_spacing() const;

  /// Binary cache of clouds, normals and features (search trees are rebuilt on load, which
  /// takes milliseconds). The file carries `key` (what it was built from); load() returns
  /// nullopt when the file is missing, damaged or holds another key. save() writes a
  /// temporary file of this process and renames it into place.
  void save(const std::filesystem::path& file, std::string_view key = {}) const;
  static std::optional<PreparedCloud> load(const std::filesystem::path& file, std::string_view key = {});

  struct Impl;
  [[nodiscard]] const Impl& impl() const { return *impl_; }

 private:
  explicit PreparedCloud(std::shared_ptr<const Impl> impl);
  std::shared_ptr<const Impl> impl_;
};

struct Registration {
  Transform T_scene_template = Transform::Identity();
  double fitness = 0.0;
  double rmse = 0.0;
  std::size_t inliers = 0;
  /// Template points left out of `fitness`: facing away from the camera, or hidden under
  /// material (FineSettings::viewpoint, covered_mm).
  std::size_t hidden = 0;
  bool converged = false;
  int iterations = 0;
};

/// Where the template is expected in the scene and how far it may be from there.
struct PosePrior {
  Transform T_scene_template = Transform::Identity();
  double position_tolerance = 5.0;    ///< cloud unit
  double rotation_tolerance_rad = 0.09;
};

struct CoarseSettings {
  std::int64_t max_iterations = 50000;
  double probability = 0.999;       ///< stop early by Eq. 10 on the correspondence inlier ratio
  double inlier_distance = 0.0;     ///< 0 = 1.5 * template coarse voxel
  double edge_similarity = 0.9;     ///< pre-rejection: sample edge lengths must agree this well
  std::optional<PosePrior> prior;   ///< hypotheses outside the prior are rejected
  std::uint64_t seed = 42;
  int threads = 0;
};

/// FPFH + RANSAC. Fails with vision.no_match when no hypothesis explains enough points.
Result<Registration> coarse_align(const PreparedCloud& templ, const PreparedCloud& scene, const CoarseSettings& settings);

struct FineSettings {
  double max_distance = 0.0;   ///< first correspondence distance; 0 = 2 * template coarse voxel
  double min_distance = 0.0;   ///< final correspondence distance; 0 = 3 * template fine spacing
  int max_iterations = 40;
  double convergence_translation = 1e-4;  ///< last step below this (relative to the coarse voxel) ...
  double convergence_rotation_rad = 1e-5;  ///< ... and this: converged (at most 8 steps at min_distance)
  double fitness_distance = 0.0;  ///< inlier distance of the reported fitness; 0 = min_distance
  std::size_t coarse_points = 20000;  ///< scene points used before the last distance step
  bool robust = false;         ///< Tukey weights at the final distance (scale from the residuals' MAD):
                               ///< material standing on the surface (flash) does not pull the pose
  /// > 0: at the final distance, scene points more than this outside the template (along its
  /// normal) get no weight and every other point full weight. Excess material is only ever
  /// outside, so this drops it without down-weighting the noisy grazing walls that fix the
  /// pose sideways (Tukey weights did, and cost 0.1 deg of yaw on the whole part).
  double trim_outside_mm = 0.0;
  /// > 0 (with trim_outside_mm): at full resolution, also no weight for the points within
  /// about this distance of a point trimmed in the previous iteration. The root of a fin or
  /// the foot of a riser is material less than trim_outside_mm high: it pulled the whole part
  /// 0.02-0.06 mm sideways (simulator, 16 seeds).
  double trim_neighbourhood_mm = 0.0;
  /// Edge-aware residuals: where the nearest template point sits at an edge of the sampled
  /// surface (a point within two spacings whose normal turns more than 45°), the scene point
  /// is measured against both tangent planes: the larger distance at a convex edge, the
  /// smaller at a concave one. With plain point-to-plane a scan point just inside a top face
  /// whose nearest template point is the wall's top row reads as deep inside the wall, and
  /// the edges of a part seen from above are what fix it sideways.
  bool edge_aware = false;
  /// > 0: a template point on a face flatter than this (its normal within this many degrees
  /// of +z, the template's up) fixes only height, roll and pitch: its residual is the
  /// vertical distance to its tangent plane. A camera above a casting measures such faces'
  /// heights well, but their slope turns any height deviation into a sideways one (0.1 mm on
  /// a 5-degree slope reads as 1.1 mm): with the casting's form deviation they turn the
  /// whole part 0.1-0.2 degrees about z (simulator, ideal fit on 4 seeds), while the walls and
  /// edges that really fix it sideways are a few hundred points against their ten thousand.
  double heights_only_slope_deg = 0.0;
  /// > 1 (with heights_only_slope_deg): at full resolution, after the first iteration, only
  /// every n-th scene point on those flat faces is used, with weight n. They fix three of the
  /// six degrees of freedom with some hundred times the points the walls and edges have.
  int flat_sample = 1;
  /// The reported fitness counts only the template points a camera could have seen (the rest
  /// are counted in Registration::hidden):
  /// - with a viewpoint (scene frame), not those whose outward normal turns more than
  ///   `max_view_angle_deg` away from it (walls seen from above return nothing);
  /// - with covered_mm > 0, not those with no scene point within the fitness distance but one
  ///   along their outward normal within covered_mm: material stands on them (a riser covers
  ///   a third of its pad). At most half of the template is left out this way, so a pose
  ///   sunk into the scene cannot look good.
  std::optional<Eigen::Vector3f> viewpoint;
  /// > 0: directions of the pose the data do not fix stay where `initial` put them. Each
  /// step is solved about the template's centroid with rotations scaled by the template's RMS
  /// radius; a direction whose curvature (eigenvalue of the 6x6 normal matrix) is below this
  /// share of the largest gets no step (Zhang et al., "On degeneration of optimization-based
  /// state estimation problems", ICRA 2016: solution remapping). A boss is a cylinder on a
  /// face: turning about its axis moves none of its surface, so only noise and its flash's
  /// gaps turn it (0.1-0.25 deg from the whole part's pose).
  double degenerate_ratio = 0.0;
  double max_view_angle_deg = 75.0;
  double covered_mm = 0.0;
  /// Occluding-edge points (scene frame, may be null): where a camera's view of a face ends at
  /// a depth jump, the point halfway between the last ray on the face and the first ray past
  /// it, at the face's range (occluding_edges()). The true edge lies anywhere between the two
  /// rays, so that point is on it give or take half a pixel, with no bias. At full resolution
  /// each is measured against the template's wall under the edge: of the nearest template
  /// point and its edge partner (edge_aware), the one whose normal is the more level (the
  /// template's z is up, as for heights_only_slope_deg), if within about 17 degrees of level.
  /// Weight `edge_weight`; points more than trim_outside_mm (else the correspondence
  /// distance) from the wall either way get none (material's outline, a wrong match).
  const Cloud* occluding_edges = nullptr;
  double edge_weight = 1.0;
  int threads = 0;
};

/// Point-to-plane ICP of scene points onto the template surface (template normals and
/// search tree are prepared), starting at `initial`. Fails with vision.too_few_points.
Result<Registration> refine(const PreparedCloud& templ, const Cloud& scene, const Transform& initial,
                            const FineSettings& settings);

/// Fitness and RMSE of a pose: template points with a scene point within `distance`.
Registration evaluate(const Cloud& templ, const Cloud& scene, const Transform& T_scene_template, double distance);

struct LocateSettings {
  std::size_t coarse_points = 3000;  ///< the template is downsampled to about this many points
  double feature_radius_voxels = 5.0;
  CoarseSettings coarse;
  FineSettings fine;
  double min_fitness = 0.3;
};

/// The standalone two-cloud tool (`fettle locate`): any unit, any two clouds. The voxel
/// size follows from the template's point count, so metres and millimetres both work.
Result<Registration> locate(const Cloud& templ, const Cloud& scene, const LocateSettings& settings);

}  // namespace fettle::vision
