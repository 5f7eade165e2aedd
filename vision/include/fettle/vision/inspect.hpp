#pragma once
// Per-cycle inspection of a part: templates built once per recipe (cached on disk next to
// it), then per scan: preprocessing, fixture-plane removal, coarse localisation within the
// fixture prior, per-region fine ICP and excess material.
#include <filesystem>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "fettle/config/part.hpp"
#include "fettle/core/cloud.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"
#include "fettle/vision/cloud.hpp"
#include "fettle/vision/excess.hpp"
#include "fettle/vision/multiview.hpp"
#include "fettle/vision/registration.hpp"

namespace fettle::vision {

struct RegionTemplate {
  config::Region region;
  PreparedCloud cloud;  ///< golden points inside the region ROI (part frame), normals, tree
};

/// Everything that does not change per cycle.
class PartTemplate {
 public:
  /// From a golden cloud in the part frame (mm). Normals: taken from the cloud, or estimated
  /// and oriented towards `viewpoint` (part frame; the camera above the part by default).
  static PartTemplate build(const config::PartRecipe& recipe, const Cloud& golden_part,
                            const Eigen::Vector3f& viewpoint = Eigen::Vector3f(0.0f, 0.0f, 1000.0f));
  /// Like build(), but reuses a cached template when its key (golden identity + settings)
  /// matches, and writes it otherwise. The cache is `cache_dir`, or when that is empty
  /// `<recipe dir>/.<recipe stem>.vision-cache/` if the recipe's vision.cache is on (else none).
  static PartTemplate load_or_build(const config::PartRecipe& recipe, const Cloud& golden_part,
                                    const std::string& golden_identity, bool* from_cache = nullptr,
                                    const std::filesystem::path& cache_dir = {});

  [[nodiscard]] const PreparedCloud& whole() const { return whole_; }
  [[nodiscard]] const std::vector<RegionTemplate>& regions() const { return regions_; }

 private:
  void find_edges() const;
  PreparedCloud whole_;
  std::vector<RegionTemplate> regions_;
};

struct RegionResult {
  std::string name;
  std::optional<Error> error;  ///< set when the region failed: what and why
  Registration registration;   ///< T_scene_template is T_scene_region (region template = part frame)
  std::size_t scene_points = 0;
  ExcessMaterial excess;
  [[nodiscard]] bool ok() const { return !error.has_value(); }
};

struct Inspection {
  Registration whole;                  ///< T_scene_part after coarse + whole-part ICP
  std::vector<RegionResult> regions;
  Cloud scene_part;                    ///< preprocessed scan in the part frame (for maps)
  std::vector<float> deviation_mm;     ///< signed distance of scene_part to the template
  double seconds = 0.0;
  std::vector<std::pair<std::string, double>> stage_seconds;  ///< time per stage (profiling)
};

/// A region's excess material in a scene in the part frame, the region's template placed at
/// T_part_region: the scene within the region's ROI and 10 mm around it (the casting's face
/// there too), material inside the ROI. `face`: the casting's face to measure from (a
/// re-grind's: the cycle's first scan's); null: fitted on this scene. inspect() measures every
/// region's excess with the same settings, on the crop it registered the region on.
ExcessMaterial measure_region_excess(const config::PartRecipe& recipe, const RegionTemplate& rt, const Cloud& scene_part,
                                     const Transform& T_part_region, const FormOffset* face = nullptr);

/// The recipe's nominal placement of the part in the fixture frame.
Transform nominal_T_fixture_part(const config::PartRecipe& recipe);

/// Runs the vision stage on one scan (mm) given in the fixture frame (T_fixture_scan maps it
/// there). Fails (vision.no_part, vision.units, ...) when the part cannot be found; a region
/// that fails is reported in its RegionResult while the others go on.
Result<Inspection> inspect(const config::PartRecipe& recipe, const PartTemplate& templ, const Cloud& scan,
                           const Transform& T_fixture_scan = Transform::Identity());

/// The same on the camera's organized cloud (camera frame, NaN = invalid): outlier removal
/// uses image neighbours and the voxel grid is filled straight from the pixels (no copy of
/// the scan). T_fixture_camera maps the camera frame into the fixture frame.
Result<Inspection> inspect(const config::PartRecipe& recipe, const PartTemplate& templ, const OrganizedCloud& scan,
                           const Transform& T_fixture_camera);

/// The same on several organized views of one part (the slide's photo positions, their poses
/// refined by register_views()): each view's outliers are measured in its own image with its
/// own mean and spread, and the kept pixels of every view go into one voxel grid, so
/// overlapping views become one surface.
Result<Inspection> inspect(const config::PartRecipe& recipe, const PartTemplate& templ,
                           const std::vector<OrganizedView>& views);

}  // namespace fettle::vision
