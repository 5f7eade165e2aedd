#pragma once
// Vision pipeline settings ([vision] in a part recipe). Lengths in mm, angles in degrees
// (converted at use). Every field has a default that works for the shipped pump body.
#include <algorithm>
#include <array>
#include <string>

namespace fettle::config {

struct VisionSettings {
  // preprocessing
  std::string crop_frame = "fixture";                    ///< frame of the pass-through box: fixture | camera
  std::array<double, 3> crop_min_mm{-250.0, -250.0, -50.0};  ///< pass-through box, lower corner
  std::array<double, 3> crop_max_mm{250.0, 250.0, 300.0};    ///< pass-through box, upper corner
  int outlier_neighbours = 8;          ///< statistical outlier removal: neighbours per point
  double outlier_std_ratio = 2.5;      ///< ... and the allowed spread (standard deviations)
  double jump_edge_mm = 0.0;           ///< flying pixels: drop a pixel whose range jumps more than this
                                       ///< to an image neighbour (0 = off; a flash fin is itself a
                                       ///< 1-3 mm jump, so keep it above the flash height)
  // environment removal (fixture plane, RANSAC with the adaptive count of Eq. 10)
  bool remove_plane = true;
  double plane_distance_mm = 0.5;      ///< inlier band of the fixture plane
  double plane_probability = 0.999;    ///< p in k = log(1-p) / log(1-w^n)
  // localisation
  double coarse_voxel_mm = 3.0;        ///< voxel for FPFH + RANSAC
  double feature_radius_mm = 15.0;     ///< FPFH support radius
  int ransac_max_iterations = 50000;
  std::string icp_method = "point_to_plane";  ///< point_to_plane (the only method so far)
  int icp_max_iterations = 40;
  double min_fitness = 0.6;            ///< a region whose fine fitness is lower fails
  /// The whole part's fitness below this: not this recipe's part (e.g. the other hand of a
  /// left/right pair). The simulated pump body scores 0.55, its mirror image 0.36.
  double min_part_fitness = 0.45;
  int min_region_points = 200;         ///< a region with fewer scene points fails
  // excess material
  int excess_min_cluster_points = 10;  ///< smaller clusters of excess points are noise
  /// The body's form deviation a casting may have (+-, smooth): in each region, the template
  /// faces the scan sees within this of the template give the casting's own surface there (a
  /// plane of offsets fitted to them), and material is what stands out of that surface, not out
  /// of the nominal. 0: material is measured against the nominal template. docs/vision.md,
  /// "Excess relative to the casting".
  double form_deviation_mm = 0.5;
  bool cache = true;                   ///< cache template data on disk next to the recipe
};

/// How far the casting's face may stand off the template as the cell sees it: twice the stated
/// form deviation (the form, and as much again for the tilt and lift of the part's located
/// pose). Vision fits the casting's face to the samples within it (vision::FormOffset); planning
/// lets a riser's layers and the passes' ends follow that face within it. Test
/// Excess.AFaceFartherFromTheRegionsPlaneThanTheFormDeviationIsStillFollowed.
[[nodiscard]] inline double face_band_mm(double form_deviation_mm) { return 2.0 * std::max(0.0, form_deviation_mm); }

}  // namespace fettle::config
