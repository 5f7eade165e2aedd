#pragma once
// Multi-view fusion: views from several slide positions into the first view's frame.
#include <vector>

#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"
#include "fettle/vision/cloud.hpp"

namespace fettle::vision {

struct View {
  Cloud cloud;                                            ///< camera frame of this view
  Transform T_first_view = Transform::Identity();         ///< initial guess from the slide calibration
};

/// One organized view (the camera's cloud) and where its camera was.
struct OrganizedView {
  const OrganizedCloud* cloud = nullptr;               ///< camera frame; not owned, must outlive the call
  Transform T_fixture_camera = Transform::Identity();  ///< camera frame -> fixture frame
};

struct FuseSettings {
  double voxel_mm = 0.3;           ///< neighbourhood for averaging overlapping surfaces
  double icp_voxel_mm = 1.0;       ///< the pairwise ICP runs on the views voxelized to this
  double icp_max_distance_mm = 2.0;
  int icp_max_iterations = 30;
  double min_fitness = 0.2;        ///< a pairwise refinement below this keeps the calibration guess
  /// Organized views only (register_views on OrganizedView): the pairwise ICP leaves out pixels
  /// beside a depth jump above this (flying pixels, remove_jump_edges). They differ between
  /// viewpoints: with them, the simulator's second view at 120 mm comes out 0.04-0.08 mm off
  /// along the slide; without them 0.01-0.02 mm (test
  /// MultiView.OrganizedViewsRegisterOnTheirOverlapWithoutTheirFlyingPixels).
  double jump_edge_mm = 4.0;
};

struct FusedCloud {
  Cloud cloud;                          ///< first view's frame
  std::vector<Transform> T_first_view;  ///< refined pose of every view (first = identity)
  std::vector<double> pair_fitness;     ///< fitness of view i+1 against view i
};

/// The registration half of fuse_views() on organized views, for the multi-view inspect(),
/// which fuses the views itself: the returned views are `views` with every T_fixture_camera
/// after the first refined (chained from the first view's, which is kept).
Result<std::vector<OrganizedView>> register_views(const std::vector<OrganizedView>& views,
                                                  const FuseSettings& settings);

/// Each view starts at its calibration pose, is refined against the previous view (ICP on
/// the overlap, both views voxelized to icp_voxel_mm), the pairwise results are chained
/// (T_0_i = T_0_{i-1} * T_{i-1}_i) and the clouds are merged; overlapping surfaces become one
/// layer by neighbourhood averaging (each view is averaged to voxel_mm on its own first, then
/// the views together: overlapping views weigh alike whatever their point density).
Result<FusedCloud> fuse_views(const std::vector<View>& views, const FuseSettings& settings);

}  // namespace fettle::vision
