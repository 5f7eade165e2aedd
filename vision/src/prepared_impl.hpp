#pragma once
// PreparedCloud's data (private to fettle::vision).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <mutex>
#include <vector>

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
  /// Per fine point at an edge of the sampled surface: the nearest fine point within two
  /// spacings whose normal turns more than 45 degrees from its own (-1: none), and whether
  /// the edge between them is convex. ICP measures a scene point against both tangent planes
  /// there (edge_residual). Found by find_edges(), once, when first needed: most prepared
  /// clouds (the scene's coarse cloud, fused views, `fettle locate`) never are (bench_vision:
  /// 0.479 s when every prepared cloud searches its edges, 0.446 s so).
  mutable std::vector<int> edge_partner;
  mutable std::vector<std::uint8_t> edge_convex;
  mutable std::once_flag edges_found;

  /// Point-to-plane residual of q against fine point j, edge-aware: at a convex edge the
  /// larger of the two tangent-plane distances, at a concave one the smaller (the distance to
  /// the surface made of the two planes). A point just inside a top face whose nearest sample
  /// is the wall's top row otherwise reads as deep inside the wall and pulls the pose sideways.
  /// Returns the residual and sets `j` to the point whose plane it is measured against.
  [[nodiscard]] float edge_residual(const Eigen::Vector3f& q, int& j) const {
    const auto k = static_cast<std::size_t>(j);
    const float r = fine.normals[k].dot(q - fine.points[k]);
    if (edge_partner.empty() || edge_partner[k] < 0) return r;
    const auto e = static_cast<std::size_t>(edge_partner[k]);
    const float re = fine.normals[e].dot(q - fine.points[e]);
    if (edge_convex[k] != 0 ? re > r : re < r) {
      j = edge_partner[k];
      return re;
    }
    return r;
  }

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

  /// Fills edge_partner and edge_convex (thread-safe; the work is done once).
  void find_edges() const {
    std::call_once(edges_found, [this] { find_edges_now(); });
  }

 private:
  void find_edges_now() const {
    edge_partner.assign(fine.size(), -1);
    edge_convex.assign(fine.size(), 0);
    if (!fine.has_normals() || !(fine_spacing > 0)) return;
    const auto radius = static_cast<float>(2.0 * fine_spacing);
    const float cos45 = std::sqrt(0.5f);
    detail::parallel_for(fine.size(), detail::thread_count(settings.threads), [&](std::size_t, std::size_t b, std::size_t e) {
      pcl::Indices idx;
      std::vector<float> d2;
      for (std::size_t i = b; i < e; ++i) {
        pcl::PointXYZ q;
        q.getVector3fMap() = fine.points[i];
        if (fine_tree->radiusSearch(q, radius, idx, d2) <= 1) continue;
        int best = -1;
        float best_d2 = 0.0f;
        for (std::size_t n = 0; n < idx.size(); ++n) {
          const auto k = static_cast<std::size_t>(idx[n]);
          if (fine.normals[k].dot(fine.normals[i]) >= cos45) continue;
          if (best < 0 || d2[n] < best_d2) best = idx[n], best_d2 = d2[n];
        }
        if (best < 0) continue;
        const auto k = static_cast<std::size_t>(best);
        const Eigen::Vector3f ik = fine.points[k] - fine.points[i];
        edge_partner[i] = best;
        // convex: each lies below the other's tangent plane
        edge_convex[i] = ik.dot(fine.normals[i]) - ik.dot(fine.normals[k]) < 0.0f ? 1 : 0;
      }
    });
  }
};

}  // namespace fettle::vision
