// Multi-view fusion (Zhu et al. Eq. 11: chained pairwise registrations into the first view).
#include "fettle/vision/multiview.hpp"

#include <string>

#include "fettle/vision/preprocess.hpp"
#include "fettle/vision/registration.hpp"

namespace fettle::vision {

Result<FusedCloud> fuse_views(const std::vector<View>& views, const FuseSettings& settings) {
  if (views.empty()) return Error{"vision.no_views", "multi-view fusion needs at least one view"};
  FusedCloud out;
  out.T_first_view.push_back(Transform::Identity());
  Cloud merged = views.front().cloud;
  merged.normals.clear();
  Cloud previous = merged;  // view i-1 in the first view's frame
  for (std::size_t i = 1; i < views.size(); ++i) {
    const auto& v = views[i];
    if (v.cloud.size() < 6) return Error{"vision.too_few_points", "view " + std::to_string(i) + " has too few points"};
    // Calibration guess, relative to the previous view, chained onto its refined pose.
    const Transform T_prev_i_calib = views[i - 1].T_first_view.inverse() * v.T_first_view;
    const Transform T_0_i_guess = out.T_first_view.back() * T_prev_i_calib;
    PrepareSettings ps;
    ps.features = false;
    ps.coarse_voxel = settings.icp_max_distance_mm / 2.0;
    const auto prev = PreparedCloud::prepare(previous, ps);
    FineSettings fs;
    fs.max_distance = settings.icp_max_distance_mm;
    fs.max_iterations = settings.icp_max_iterations;
    auto r = refine(prev, v.cloud, T_0_i_guess.inverse(), fs);
    Transform T_0_i = T_0_i_guess;
    if (r && r->fitness >= settings.min_fitness) T_0_i = r->T_scene_template.inverse();
    out.pair_fitness.push_back(r ? r->fitness : 0.0);
    out.T_first_view.push_back(T_0_i);
    Cloud placed = transformed(v.cloud, T_0_i);
    placed.normals.clear();
    merged.points.insert(merged.points.end(), placed.points.begin(), placed.points.end());
    previous = std::move(placed);
  }
  // Overlaps become one surface: every neighbourhood (voxel) is replaced by its centroid.
  out.cloud = voxel_downsample(merged, settings.voxel_mm);
  return out;
}

}  // namespace fettle::vision
