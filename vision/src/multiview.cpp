// Multi-view fusion (Zhu et al. Eq. 11: chained pairwise registrations into the first view).
#include "fettle/vision/multiview.hpp"

#include <string>

#include "fettle/vision/preprocess.hpp"
#include "fettle/vision/registration.hpp"

namespace fettle::vision {

namespace {

struct ViewPoses {
  std::vector<Transform> T_first_view;  // refined pose of every view (first = identity)
  std::vector<double> pair_fitness;     // fitness of view i+1 against view i
};

Cloud downsampled(const Cloud& c, double voxel) {
  Cloud d = voxel_downsample(c, voxel);
  d.normals.clear();
  return d;
}

/// The pairwise registration chain of fuse_views(); the views placed in the first view's frame
/// (voxelized to voxel_mm) are appended to `merged` when it is given.
Result<ViewPoses> chain_views(const std::vector<View>& views, const FuseSettings& settings, Cloud* merged) {
  if (views.empty()) return Error{"vision.no_views", "multi-view fusion needs at least one view"};
  if (!(settings.voxel_mm > 0) || !(settings.icp_voxel_mm > 0))
    return Error{"vision.settings", "multi-view fusion needs voxel sizes above 0 (voxel " + std::to_string(settings.voxel_mm) +
                                        " mm, ICP voxel " + std::to_string(settings.icp_voxel_mm) + " mm)"};
  // Every view is voxelized before anything else: the output is voxel_mm anyway, and the
  // pairwise ICP needs no more than icp_voxel_mm (preparing a whole 3.2 MP view for ICP,
  // normals of 3 M points, takes 55 s for two views).
  ViewPoses out;
  out.T_first_view.push_back(Transform::Identity());
  Cloud first = downsampled(views.front().cloud, settings.voxel_mm);
  Cloud previous = downsampled(first, settings.icp_voxel_mm);  // view i-1 in the first view's frame
  if (merged != nullptr) *merged = std::move(first);
  for (std::size_t i = 1; i < views.size(); ++i) {
    const auto& v = views[i];
    if (v.cloud.size() < 6) return Error{"vision.too_few_points", "view " + std::to_string(i) + " has too few points"};
    // Calibration guess, relative to the previous view, chained onto its refined pose.
    const Transform T_prev_i_calib = views[i - 1].T_first_view.inverse() * v.T_first_view;
    const Transform T_0_i_guess = out.T_first_view.back() * T_prev_i_calib;
    const Cloud fine = downsampled(v.cloud, settings.voxel_mm);
    const Cloud coarse = downsampled(fine, settings.icp_voxel_mm);
    PrepareSettings ps;
    ps.features = false;
    ps.coarse_voxel = settings.icp_max_distance_mm / 2.0;
    const auto prev = PreparedCloud::prepare(previous, ps);
    FineSettings fs;
    fs.max_distance = settings.icp_max_distance_mm;
    fs.max_iterations = settings.icp_max_iterations;
    auto r = refine(prev, coarse, T_0_i_guess.inverse(), fs);
    Transform T_0_i = T_0_i_guess;
    if (r && r->fitness >= settings.min_fitness) T_0_i = r->T_scene_template.inverse();
    out.pair_fitness.push_back(r ? r->fitness : 0.0);
    out.T_first_view.push_back(T_0_i);
    if (merged != nullptr) {
      const Cloud placed = transformed(fine, T_0_i);
      merged->points.insert(merged->points.end(), placed.points.begin(), placed.points.end());
    }
    previous = transformed(coarse, T_0_i);
  }
  return out;
}

}  // namespace

Result<std::vector<OrganizedView>> register_views(const std::vector<OrganizedView>& views,
                                                  const FuseSettings& settings) {
  if (views.empty()) return Error{"vision.no_views", "multi-view registration needs at least one view"};
  std::vector<View> clouds;
  clouds.reserve(views.size());
  for (std::size_t i = 0; i < views.size(); ++i) {
    if (views[i].cloud == nullptr) return Error{"vision.no_views", "view " + std::to_string(i) + " has no cloud"};
    const OrganizedCloud& c = *views[i].cloud;
    clouds.push_back({settings.jump_edge_mm > 0 ? to_cloud(remove_jump_edges(c, settings.jump_edge_mm)) : to_cloud(c),
                      views.front().T_fixture_camera.inverse() * views[i].T_fixture_camera});
  }
  auto poses = chain_views(clouds, settings, nullptr);
  if (!poses) return poses.error();
  std::vector<OrganizedView> out = views;
  for (std::size_t i = 1; i < out.size(); ++i)
    out[i].T_fixture_camera = views.front().T_fixture_camera * poses->T_first_view[i];
  return out;
}

Result<FusedCloud> fuse_views(const std::vector<View>& views, const FuseSettings& settings) {
  Cloud merged;
  auto poses = chain_views(views, settings, &merged);
  if (!poses) return poses.error();
  FusedCloud out;
  out.T_first_view = std::move(poses->T_first_view);
  out.pair_fitness = std::move(poses->pair_fitness);
  // Overlaps become one surface: every neighbourhood (voxel) is replaced by its centroid.
  out.cloud = voxel_downsample(merged, settings.voxel_mm);
  return out;
}

}  // namespace fettle::vision
