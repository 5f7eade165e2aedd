#pragma once
// PreparedCloud's data (private to fettle::vision).
#include <algorithm>
#include <cmath>
#include <memory>

#include <pcl/point_types.h>

#include "detail.hpp"
#include "spatial.hpp"
#include "fettle/vision/registration.hpp"

namespace fettle::vision {

using Feature = pcl::FPFHSignature33;
using FeatureTree = pcl::KdTreeFLANN<Feature>;  // instantiated in registration.cpp

struct PreparedCloud::Impl {
  PrepareSettings settings;
  Cloud fine;
  Cloud coarse;
  pcl::PointCloud<Feature>::Ptr features = std::make_shared<pcl::PointCloud<Feature>>();
  std::shared_ptr<detail::Tree> fine_tree;
  std::shared_ptr<detail::Tree> coarse_tree;
  std::shared_ptr<FeatureTree> feature_tree;
  std::shared_ptr<const detail::NearestGrid> grid;  ///< set when settings.nearest_grid_cell > 0
  double fine_spacing = 0.0;

  /// Nearest fine point to q: the lookup grid when there is one (-1 beyond its band), else
  /// the search tree. (index, squared distance).
  [[nodiscard]] std::pair<int, float> nearest_fine(const Eigen::Vector3f& q) const {
    if (grid) {
      const int j = grid->lookup(q);
      if (j < 0) return {-1, 0.0f};
      return {j, (fine.points[static_cast<std::size_t>(j)] - q).squaredNorm()};
    }
    return detail::nearest(*fine_tree, q);
  }
  /// Like nearest_fine, but beyond the grid's band the search tree answers.
  [[nodiscard]] std::pair<int, float> nearest_any(const Eigen::Vector3f& q) const {
    if (grid) {
      const int j = grid->lookup(q);
      if (j >= 0) return {j, (fine.points[static_cast<std::size_t>(j)] - q).squaredNorm()};
    }
    return detail::nearest(*fine_tree, q);
  }

  void build_trees() {
    fine_tree = detail::make_tree(fine.points);
    if (settings.nearest_grid_cell > 0)
      grid = std::make_shared<const detail::NearestGrid>(fine.points, settings.nearest_grid_cell, settings.nearest_grid_band);
    coarse_tree = detail::make_tree(coarse.points);
    feature_tree = std::make_shared<FeatureTree>(false);
    if (!features->empty()) feature_tree->setInputCloud(features);
    // Median nearest-neighbour spacing of the fine cloud, from a sample.
    std::vector<float> d;
    const std::size_t step = std::max<std::size_t>(1, fine.size() / 2000);
    pcl::Indices idx(2);
    std::vector<float> d2(2);
    for (std::size_t i = 0; i < fine.size(); i += step) {
      pcl::PointXYZ q;
      q.getVector3fMap() = fine.points[i];
      if (fine_tree->nearestKSearch(q, 2, idx, d2) == 2) d.push_back(std::sqrt(d2[1]));
    }
    if (!d.empty()) {
      std::nth_element(d.begin(), d.begin() + static_cast<std::ptrdiff_t>(d.size() / 2), d.end());
      fine_spacing = d[d.size() / 2];
    }
  }
};

}  // namespace fettle::vision
