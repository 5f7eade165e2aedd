// Excess material: points above the template surface, cleaned, measured.
#include "fettle/vision/excess.hpp"

#include <algorithm>
#include <cmath>

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
  // 1. Every scene point's signed distance along the normal of its nearest template point;
  //    the candidates are those above the threshold.
  std::vector<int> owner(scene_in_template.size(), -1);
  std::vector<float> height(scene_in_template.size(), 0.0f);
  detail::parallel_for(scene_in_template.size(), detail::thread_count(0), [&](std::size_t, std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      const auto& p = scene_in_template.points[i];
      const auto [j, d2] = T.nearest_any(p);
      if (j < 0) continue;
      const auto k = static_cast<std::size_t>(j);
      owner[i] = j;
      height[i] = T.fine.normals[k].dot(p - T.fine.points[k]);
    }
  });
  const auto candidate = [&](std::size_t i) {
    return owner[i] >= 0 && height[i] > settings.threshold_mm && height[i] <= settings.max_height_mm;
  };
  std::vector<std::size_t> cand;
  for (std::size_t i = 0; i < owner.size(); ++i)
    if (candidate(i)) cand.push_back(i);
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

  // 3. Measure. Each template point stands for a patch of surface (area from its local
  //    spacing). A patch carries material when the scene point nearest to its centre, dropped
  //    along the normal onto the template (its foot), is material, and then the patch's height
  //    is that point's: nearest-neighbour resampling of the scan onto the template's patches.
  //    Counting only the patches that have a material point of their own (and filling holes
  //    inside) loses the rim: a scan voxelized in the fixture frame, at the template's pitch but
  //    not on its grid, leaves patches without a point of their own, and along the rim they
  //    cannot be told from outside; a riser's footprint comes out 2-10 % small (test
  //    Excess.ADiscSampledOnAnotherGridHasItsWholeFootprint).
  std::vector<char> material(scene_in_template.size(), 0);
  for (const auto& c : clusters)
    for (const auto idx : c.indices) {
      const auto i = cand[static_cast<std::size_t>(idx)];
      material[i] = 1;
      out.points.push_back(scene_in_template.points[i]);
      out.heights_mm.push_back(height[i]);
      out.max_height_mm = std::max(out.max_height_mm, static_cast<double>(height[i]));
    }
  if (out.points.empty()) return out;
  std::vector<Eigen::Vector3f> feet;
  std::vector<std::size_t> foot_of;  // scene point of each foot
  feet.reserve(scene_in_template.size());
  foot_of.reserve(scene_in_template.size());
  for (std::size_t i = 0; i < scene_in_template.size(); ++i) {
    if (owner[i] < 0) continue;
    feet.push_back(scene_in_template.points[i] - height[i] * T.fine.normals[static_cast<std::size_t>(owner[i])]);
    foot_of.push_back(i);
  }
  const auto feet_tree = detail::make_tree(feet);
  // The patches to decide: those within reach of a material point's foot. Farther than reach
  // from every foot is a patch the scan did not see (a shadow): no material is claimed there.
  const double spacing = std::max(1e-6, templ.fine_spacing());
  const auto reach = static_cast<float>(1.5 * spacing);
  std::vector<char> near_material(T.fine.size(), 0);
  pcl::Indices nn;
  std::vector<float> d2;
  for (std::size_t f = 0; f < feet.size(); ++f) {
    if (!material[foot_of[f]]) continue;
    pcl::PointXYZ q;
    q.getVector3fMap() = feet[f];
    T.fine_tree->radiusSearch(q, reach, nn, d2);
    for (const auto m : nn) near_material[static_cast<std::size_t>(m)] = 1;
  }
  // Patch area: the square of the mean distance to the 4 nearest template points (exact
  // on the voxel grid the template is resampled to).
  constexpr int k = 4;
  pcl::Indices knn(k + 1);
  std::vector<float> kd2(k + 1);
  for (std::size_t j = 0; j < T.fine.size(); ++j) {
    if (!near_material[j]) continue;
    const auto [f, fd2] = detail::nearest(*feet_tree, T.fine.points[j]);
    if (f < 0 || fd2 > reach * reach) continue;
    const auto i = foot_of[static_cast<std::size_t>(f)];
    if (!material[i]) continue;
    pcl::PointXYZ q;
    q.getVector3fMap() = T.fine.points[j];
    const int found = T.fine_tree->nearestKSearch(q, k + 1, knn, kd2);
    double sum = 0.0;
    for (int m = 1; m < found; ++m) sum += std::sqrt(static_cast<double>(kd2[static_cast<std::size_t>(m)]));
    const double side = found > 1 ? sum / (found - 1) : 0.0;
    out.footprint_mm2 += side * side;
    out.volume_mm3 += side * side * height[i];
  }
  return out;
}

}  // namespace fettle::vision
