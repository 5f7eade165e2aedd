// Excess material: points above the template surface, cleaned, measured.
#include "fettle/vision/excess.hpp"

#include <algorithm>
#include <cmath>
#include <unordered_map>

#include <pcl/search/kdtree.h>
#include <pcl/segmentation/extract_clusters.h>

#include "detail.hpp"
#include "prepared_impl.hpp"

namespace fettle::vision {

std::vector<float> signed_distances(const PreparedCloud& templ, const std::vector<Eigen::Vector3f>& points) {
  const auto& T = templ.impl();
  std::vector<float> out(points.size(), 0.0f);
  detail::parallel_for(points.size(), detail::thread_count(0), [&](std::size_t, std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      const auto [j, d2] = T.nearest_any(points[i]);
      if (j < 0) {
        out[i] = std::numeric_limits<float>::quiet_NaN();
        continue;
      }
      const auto k = static_cast<std::size_t>(j);
      out[i] = T.fine.normals[k].dot(points[i] - T.fine.points[k]);
    }
  });
  return out;
}

ExcessMaterial measure_excess(const PreparedCloud& templ, const Cloud& scene_in_template, const ExcessSettings& settings) {
  ExcessMaterial out;
  const auto& T = templ.impl();
  if (T.fine.empty() || scene_in_template.empty()) return out;
  // 1. Candidates: signed distance along the normal of the nearest template point.
  std::vector<int> owner(scene_in_template.size(), -1);
  std::vector<float> height(scene_in_template.size(), 0.0f);
  detail::parallel_for(scene_in_template.size(), detail::thread_count(0), [&](std::size_t, std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      const auto& p = scene_in_template.points[i];
      const auto [j, d2] = T.nearest_any(p);
      if (j < 0) continue;
      const auto k = static_cast<std::size_t>(j);
      const float h = T.fine.normals[k].dot(p - T.fine.points[k]);
      if (h > settings.threshold_mm && h <= settings.max_height_mm) {
        owner[i] = j;
        height[i] = h;
      }
    }
  });
  std::vector<std::size_t> cand;
  for (std::size_t i = 0; i < owner.size(); ++i)
    if (owner[i] >= 0) cand.push_back(i);
  if (cand.empty()) return out;

  // 2. Cleaning: Euclidean clusters; small ones are noise (speckle, flying pixels).
  std::vector<Eigen::Vector3f> cpts;
  cpts.reserve(cand.size());
  for (auto i : cand) cpts.push_back(scene_in_template.points[i]);
  const auto pc = detail::to_pcl(cpts);
  auto tree = std::make_shared<pcl::search::KdTree<pcl::PointXYZ>>(false);
  tree->setInputCloud(pc);
  const double tol = settings.cluster_tolerance_mm > 0 ? settings.cluster_tolerance_mm : 3.0 * std::max(0.2, templ.fine_spacing());
  pcl::EuclideanClusterExtraction<pcl::PointXYZ> ec;
  ec.setClusterTolerance(tol);
  ec.setMinClusterSize(std::max(1, settings.min_cluster_points));
  ec.setMaxClusterSize(std::numeric_limits<int>::max());
  ec.setSearchMethod(tree);
  ec.setInputCloud(pc);
  std::vector<pcl::PointIndices> clusters;
  ec.extract(clusters);

  // 3. Measure: each template point stands for a patch of surface (area from its local
  //    spacing); the excess above a patch is the tallest point that maps to it.
  std::unordered_map<int, float> top;  // template point -> largest height
  for (const auto& c : clusters) {
    for (const auto idx : c.indices) {
      const auto i = cand[static_cast<std::size_t>(idx)];
      out.points.push_back(scene_in_template.points[i]);
      out.heights_mm.push_back(height[i]);
      auto& t = top[owner[i]];
      t = std::max(t, height[i]);
      out.max_height_mm = std::max(out.max_height_mm, static_cast<double>(height[i]));
    }
  }
  // Holes: a scene sampled at the template's own pitch leaves some patches without a point
  // of their own (aliasing of two grids). A patch whose 4-neighbourhood carries excess on at
  // least 3 sides is inside the footprint: it gets their mean height.
  {
    const double reach = 1.05 * std::max(1e-6, templ.fine_spacing());
    std::unordered_map<int, std::pair<float, int>> fill;  // template point -> (height sum, sides)
    pcl::Indices nn4;
    std::vector<float> d4;
    for (const auto& [j, h] : top) {
      pcl::PointXYZ q;
      q.getVector3fMap() = T.fine.points[static_cast<std::size_t>(j)];
      T.fine_tree->radiusSearch(q, reach, nn4, d4);
      for (const auto m : nn4) {
        if (m == j || top.count(m) > 0) continue;
        if (T.fine.normals[static_cast<std::size_t>(m)].dot(T.fine.normals[static_cast<std::size_t>(j)]) < 0.9f) continue;
        auto& f = fill[m];
        f.first += h;
        ++f.second;
      }
    }
    for (const auto& [m, f] : fill)
      if (f.second >= 3) top[m] = f.first / static_cast<float>(f.second);
  }
  // Patch area: the square of the mean distance to the 4 nearest template points (exact
  // on the voxel grid the template is resampled to).
  constexpr int k = 4;
  pcl::Indices nn(k + 1);
  std::vector<float> d2(k + 1);
  for (const auto& [j, h] : top) {
    pcl::PointXYZ q;
    q.getVector3fMap() = T.fine.points[static_cast<std::size_t>(j)];
    const int found = T.fine_tree->nearestKSearch(q, k + 1, nn, d2);
    double s = 0.0;
    for (int m = 1; m < found; ++m) s += std::sqrt(static_cast<double>(d2[static_cast<std::size_t>(m)]));
    const double spacing = found > 1 ? s / (found - 1) : 0.0;
    const double area = spacing * spacing;
    out.footprint_mm2 += area;
    out.volume_mm3 += area * h;
  }
  return out;
}

}  // namespace fettle::vision
