// Excess material: points above the template surface, cleaned, measured.
#include "fettle/vision/excess.hpp"

#include <algorithm>
#include <cmath>

#include <Eigen/Cholesky>

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

namespace {

/// The robust plane of offsets (see FormOffset): least squares on (1, x, y), then twice again
/// on the points within 3 robust sigmas (at least 0.05 mm) of it. Points on one line or fewer
/// than 30 give the median offset alone; fewer than 10, nothing.
FormOffset fit_form_offset(const PreparedCloud::Impl& T, const Cloud& scene, const std::vector<int>& owner,
                           const std::vector<float>& height, double form_deviation_mm) {
  FormOffset f;
  struct Sample { double x, y, h; };
  std::vector<Sample> face;
  for (std::size_t i = 0; i < owner.size(); ++i) {
    if (owner[i] < 0 || std::abs(height[i]) > form_deviation_mm) continue;
    if (T.fine.normals[static_cast<std::size_t>(owner[i])].z() < 0.8f) continue;  // upward faces only
    face.push_back({scene.points[i].x(), scene.points[i].y(), height[i]});
  }
  if (face.size() < 10) return f;
  const auto median_of = [](std::vector<double> v) {
    const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
    std::nth_element(v.begin(), mid, v.end());
    return *mid;
  };
  std::vector<char> keep(face.size(), 1);
  std::vector<double> res(face.size(), 0.0);  // |offset - plane| of every face point, last fit
  for (int round = 0; round < 3; ++round) {
    Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
    Eigen::Vector3d b = Eigen::Vector3d::Zero();
    Eigen::Vector2d mean = Eigen::Vector2d::Zero();
    std::vector<double> hs;
    for (std::size_t k = 0; k < face.size(); ++k)
      if (keep[k]) mean += Eigen::Vector2d(face[k].x, face[k].y), hs.push_back(face[k].h);
    if (hs.size() < 10) break;
    mean /= static_cast<double>(hs.size());
    for (std::size_t k = 0; k < face.size(); ++k) {
      if (!keep[k]) continue;
      const Eigen::Vector3d a(1.0, face[k].x - mean.x(), face[k].y - mean.y());
      A += a * a.transpose();
      b += a * face[k].h;
    }
    // a plane needs the points spread in x and y (centred moments of a few mm at least)
    const double n = static_cast<double>(hs.size());
    const bool planar = hs.size() >= 30 && A(1, 1) / n > 4.0 && A(2, 2) / n > 4.0 &&
                        A.bottomRightCorner<2, 2>().determinant() / (n * n) > 16.0;
    if (planar) {
      const Eigen::Vector3d c = A.ldlt().solve(b);
      f.per_mm_x = c(1), f.per_mm_y = c(2);
      f.at_origin_mm = c(0) - c(1) * mean.x() - c(2) * mean.y();
    } else {
      f.per_mm_x = f.per_mm_y = 0.0;
      f.at_origin_mm = median_of(hs);
    }
    f.fitted = true;
    std::vector<double> kept_res;
    for (std::size_t k = 0; k < face.size(); ++k) {
      res[k] = std::abs(face[k].h - f.at(face[k].x, face[k].y));
      if (keep[k]) kept_res.push_back(res[k]);
    }
    const double gate = std::max(0.05, 3.0 * 1.4826 * median_of(kept_res));
    for (std::size_t k = 0; k < face.size(); ++k) keep[k] = res[k] <= gate ? 1 : 0;
  }
  double ss = 0.0;
  f.points = 0;
  for (std::size_t k = 0; k < face.size(); ++k)
    if (keep[k]) ss += res[k] * res[k], ++f.points;
  f.rms_mm = f.points > 0 ? std::sqrt(ss / static_cast<double>(f.points)) : 0.0;
  return f;
}

}  // namespace

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
  // 1b. The casting's own surface: with a form deviation of up to +-F the body itself stands up
  //     to F over the nominal, and measured against the nominal it would be "material" (0.5 mm
  //     of it over a whole face beside a riser). The offsets of the points on the template's
  //     upward faces within F of it give a plane of offsets; material stands out of that.
  if (settings.form_deviation_mm > 0.0) out.form = fit_form_offset(T, scene_in_template, owner, height, settings.form_deviation_mm);
  const auto candidate = [&](std::size_t i) {
    const auto& p = scene_in_template.points[i];
    return owner[i] >= 0 && height[i] - out.form.at(p.x(), p.y()) > settings.threshold_mm &&
           height[i] <= settings.max_height_mm;
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
