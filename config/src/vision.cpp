// [vision] in a part recipe.
#include "fettle/config/vision.hpp"
#include "sections.hpp"

namespace fettle::config::detail {

void read_vision(TableReader& root, VisionSettings& v) {
  if (auto t = root.table("vision")) {
    t->choice("crop_frame", v.crop_frame, {"fixture", "camera"});
    t->vec3("crop_min_mm", v.crop_min_mm, kCoordMm);
    t->vec3("crop_max_mm", v.crop_max_mm, kCoordMm);
    for (int i = 0; i < 3; ++i) {
      if (v.crop_min_mm[static_cast<std::size_t>(i)] >= v.crop_max_mm[static_cast<std::size_t>(i)]) {
        t->error("crop_max_mm", "must be larger than crop_min_mm on every axis");
        break;
      }
    }
    t->integer("outlier_neighbours", v.outlier_neighbours, {0, 100});
    t->number("outlier_std_ratio", v.outlier_std_ratio, {0.1, 100.0});
    t->number("jump_edge_mm", v.jump_edge_mm, {0.0, 1000.0});
    t->boolean("remove_plane", v.remove_plane);
    t->number("plane_distance_mm", v.plane_distance_mm, {0.001, 100.0});
    t->number("plane_probability", v.plane_probability, {0.5, 0.999999});
    t->number("coarse_voxel_mm", v.coarse_voxel_mm, {0.05, 100.0});
    t->number("feature_radius_mm", v.feature_radius_mm, {0.1, 1000.0});
    t->integer("ransac_max_iterations", v.ransac_max_iterations, {10, 10'000'000});
    t->choice("icp_method", v.icp_method, {"point_to_plane"});
    t->integer("icp_max_iterations", v.icp_max_iterations, {1, 1000});
    t->number("min_fitness", v.min_fitness, {0.0, 1.0});
    t->number("min_part_fitness", v.min_part_fitness, {0.0, 1.0});
    t->integer("min_region_points", v.min_region_points, {3, 100'000'000});
    t->integer("excess_min_cluster_points", v.excess_min_cluster_points, {1, 1'000'000});
    t->number("form_deviation_mm", v.form_deviation_mm, {0.0, 5.0});
    t->boolean("cache", v.cache);
  }
}

}  // namespace fettle::config::detail
