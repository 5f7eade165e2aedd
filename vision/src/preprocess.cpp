// Preprocessing: voxel grid (centroid per voxel), crop, outlier removal, normals.
#include "fettle/vision/preprocess.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <utility>

#include <Eigen/Eigenvalues>
#include <pcl/features/integral_image_normal.h>

#include "detail.hpp"
#include "spatial.hpp"

namespace fettle::vision {

namespace {

struct VoxelKeys {
  std::vector<std::pair<std::uint64_t, std::uint32_t>> keyed;  // (voxel key, point index), sorted
};

VoxelKeys voxel_keys(const std::vector<Eigen::Vector3f>& points, double voxel) {
  VoxelKeys out;
  if (points.empty()) return out;
  Eigen::Vector3f lo = points.front();
  for (const auto& p : points) lo = lo.cwiseMin(p);
  const double inv = 1.0 / voxel;
  out.keyed.resize(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) {
    const Eigen::Vector3d q = ((points[i] - lo).cast<double>() * inv).array().floor();
    // 21 bits per axis: 2 million voxels per axis is far more than any scan needs; larger
    // indices wrap, which only merges voxels 2^21 voxels apart (never adjacent ones).
    const auto ix = static_cast<std::uint64_t>(q.x()) & 0x1FFFFF;
    const auto iy = static_cast<std::uint64_t>(q.y()) & 0x1FFFFF;
    const auto iz = static_cast<std::uint64_t>(q.z()) & 0x1FFFFF;
    out.keyed[i] = {(ix << 42) | (iy << 21) | iz, static_cast<std::uint32_t>(i)};
  }
  std::sort(out.keyed.begin(), out.keyed.end());
  return out;
}

}  // namespace

Cloud voxel_downsample(const Cloud& cloud, double voxel_size) {
  if (cloud.empty() || !(voxel_size > 0.0)) return cloud;
  // A hash of cells on a grid anchored at the origin: downsampling a downsampled cloud again
  // with the same voxel changes nothing (each centroid lies in its own cell).
  detail::VoxelAccumulator acc(voxel_size, cloud.size());
  if (cloud.has_normals())
    for (std::size_t i = 0; i < cloud.size(); ++i) acc.add(cloud.points[i], cloud.normals[i]);
  else
    for (const auto& p : cloud.points) acc.add(p);
  Cloud out;
  acc.write(out.points, cloud.has_normals() ? &out.normals : nullptr);
  return out;
}

double voxel_for_count(const Cloud& cloud, std::size_t target_points) {
  if (cloud.size() <= target_points || cloud.empty()) return 0.0;
  const double diag = std::max(1e-9, static_cast<double>(bounds(cloud).diagonal()));
  double lo = diag * 1e-5;
  double hi = diag;
  auto count = [&](double v) {
    const auto keys = voxel_keys(cloud.points, v);
    std::size_t n = 0;
    for (std::size_t i = 0; i < keys.keyed.size(); ++i) n += (i == 0 || keys.keyed[i].first != keys.keyed[i - 1].first) ? 1 : 0;
    return n;
  };
  for (int it = 0; it < 30; ++it) {
    const double mid = std::sqrt(lo * hi);
    const std::size_t n = count(mid);
    if (n > target_points)
      lo = mid;
    else
      hi = mid;
    if (hi / lo < 1.03) break;
  }
  return hi;
}

Cloud crop_box(const Cloud& cloud, const Transform& T_frame_cloud, const Eigen::Vector3d& min,
               const Eigen::Vector3d& max) {
  const Eigen::Matrix3f R = T_frame_cloud.rotation().cast<float>();
  const Eigen::Vector3f t = T_frame_cloud.translation().cast<float>();
  const Eigen::Vector3f lo = min.cast<float>();
  const Eigen::Vector3f hi = max.cast<float>();
  const bool normals = cloud.has_normals();
  Cloud out;
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    const Eigen::Vector3f q = R * cloud.points[i] + t;
    if ((q.array() >= lo.array()).all() && (q.array() <= hi.array()).all()) {
      out.points.push_back(cloud.points[i]);
      if (normals) out.normals.push_back(cloud.normals[i]);
    }
  }
  return out;
}

Cloud remove_statistical_outliers(const Cloud& cloud, int k, double std_ratio) {
  if (k <= 0 || cloud.size() <= static_cast<std::size_t>(k) + 1) return cloud;
  const auto tree = detail::make_tree(cloud.points);
  std::vector<double> mean_dist(cloud.size(), 0.0);
  detail::parallel_for(cloud.size(), detail::thread_count(0), [&](std::size_t, std::size_t b, std::size_t e) {
    pcl::Indices idx(static_cast<std::size_t>(k) + 1);
    std::vector<float> d2(static_cast<std::size_t>(k) + 1);
    pcl::PointXYZ q;
    for (std::size_t i = b; i < e; ++i) {
      q.getVector3fMap() = cloud.points[i];
      const int found = tree->nearestKSearch(q, k + 1, idx, d2);
      double s = 0.0;
      for (int j = 0; j < found; ++j) s += std::sqrt(static_cast<double>(d2[static_cast<std::size_t>(j)]));
      mean_dist[i] = found > 1 ? s / (found - 1) : 0.0;  // the point itself is at distance 0
    }
  });
  const double n = static_cast<double>(mean_dist.size());
  const double mean = std::accumulate(mean_dist.begin(), mean_dist.end(), 0.0) / n;
  double var = 0.0;
  for (double d : mean_dist) var += (d - mean) * (d - mean);
  const double limit = mean + std_ratio * std::sqrt(var / std::max(1.0, n - 1.0));
  Cloud out;
  const bool normals = cloud.has_normals();
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    if (mean_dist[i] > limit) continue;
    out.points.push_back(cloud.points[i]);
    if (normals) out.normals.push_back(cloud.normals[i]);
  }
  return out;
}

namespace {
/// Each pixel's range (distance from the camera), NaN where the pixel is invalid.
std::vector<float> ranges(const OrganizedCloud& cloud) {
  std::vector<float> range(cloud.size());
  detail::parallel_for(cloud.size(), detail::thread_count(0), [&](std::size_t, std::size_t b, std::size_t e) {
    for (std::size_t k = b; k < e; ++k)
      range[k] = cloud.points[k].allFinite() ? cloud.points[k].norm() : std::numeric_limits<float>::quiet_NaN();
  });
  return range;
}

/// mixed_pixels on the cloud's ranges (ranges()).
std::vector<std::uint8_t> mixed_pixels(const OrganizedCloud& cloud, const std::vector<float>& range, double min_jump_mm,
                                       double tolerance_mm);
/// occluding_edges on the cloud's ranges (ranges()).
Cloud occluding_edges(const OrganizedCloud& cloud, const std::vector<float>& range, const std::vector<std::uint8_t>& mixed,
                      double min_jump_mm);
}  // namespace

OrganizedCloud remove_jump_edges(const OrganizedCloud& cloud, double max_jump_mm) {
  OrganizedCloud out = cloud;
  const std::size_t w = cloud.width, h = cloud.height;
  if (max_jump_mm <= 0.0 || w * h != cloud.size()) return out;
  const std::vector<float> range = ranges(cloud);
  const auto jump = static_cast<float>(max_jump_mm);
  for (std::size_t v = 0; v < h; ++v)
    for (std::size_t u = 0; u < w; ++u) {
      const std::size_t k = v * w + u;
      const float r = range[k];
      if (std::isnan(r)) continue;
      auto far = [&](std::size_t n) { return !std::isnan(range[n]) && std::abs(range[n] - r) > jump; };
      if ((u > 0 && far(k - 1)) || (u + 1 < w && far(k + 1)) || (v > 0 && far(k - w)) || (v + 1 < h && far(k + w)))
        out.points[k] = OrganizedCloud::invalid();
    }
  return out;
}

std::vector<std::uint8_t> mixed_pixels(const OrganizedCloud& cloud, double min_jump_mm, double tolerance_mm) {
  return mixed_pixels(cloud, ranges(cloud), min_jump_mm, tolerance_mm);
}

Cloud occluding_edges(const OrganizedCloud& cloud, const std::vector<std::uint8_t>& mixed, double min_jump_mm) {
  return occluding_edges(cloud, ranges(cloud), mixed, min_jump_mm);
}

Cloud occluding_edges(const OrganizedCloud& cloud, double min_jump_mm, double mixed_tolerance_mm) {
  const std::vector<float> range = ranges(cloud);
  return occluding_edges(cloud, range, mixed_pixels(cloud, range, min_jump_mm, mixed_tolerance_mm), min_jump_mm);
}

namespace {
std::vector<std::uint8_t> mixed_pixels(const OrganizedCloud& cloud, const std::vector<float>& range, double min_jump_mm,
                                       double tolerance_mm) {
  const std::size_t w = cloud.width, h = cloud.height;
  std::vector<std::uint8_t> mixed(cloud.size(), 0);
  if (min_jump_mm <= 0.0 || w * h != cloud.size() || w < 3 || h < 3) return mixed;
  const auto jump = static_cast<float>(min_jump_mm);
  const auto tol = static_cast<float>(tolerance_mm);
  constexpr int du[8] = {1, -1, 0, 0, 1, 1, -1, -1};
  constexpr int dv[8] = {0, 0, 1, -1, 1, -1, 1, -1};
  const int iw = static_cast<int>(w), ih = static_cast<int>(h);
  detail::parallel_for(h, detail::thread_count(0), [&](std::size_t, std::size_t b, std::size_t e) {
    for (int v = static_cast<int>(b); v < static_cast<int>(e); ++v)
      for (int u = 0; u < iw; ++u) {
        const auto k = static_cast<std::size_t>(v * iw + u);
        const float r = range[k];
        if (std::isnan(r)) continue;
        float largest = 0.0f;
        for (int d = 0; d < 4; ++d) {
          const int uu = u + du[d], vv = v + dv[d];
          if (uu < 0 || uu >= iw || vv < 0 || vv >= ih) continue;
          const float rn = range[static_cast<std::size_t>(vv * iw + uu)];
          if (!std::isnan(rn)) largest = std::max(largest, std::abs(rn - r));
        }
        if (largest <= jump) continue;
        const float limit = std::max(tol, 0.1f * largest);
        bool on_surface = false;
        for (int d = 0; d < 8 && !on_surface; ++d) {
          const int u1 = u + du[d], v1 = v + dv[d], u2 = u + 2 * du[d], v2 = v + 2 * dv[d];
          if (u2 < 0 || u2 >= iw || v2 < 0 || v2 >= ih) continue;
          const float r1 = range[static_cast<std::size_t>(v1 * iw + u1)];
          const float r2 = range[static_cast<std::size_t>(v2 * iw + u2)];
          if (std::isnan(r1) || std::isnan(r2) || std::abs(r1 - r2) > jump) continue;
          on_surface = std::abs(2.0f * r1 - r2 - r) <= limit;
        }
        if (!on_surface) mixed[k] = 1;
      }
  }, 16);
  return mixed;
}

Cloud occluding_edges(const OrganizedCloud& cloud, const std::vector<float>& range, const std::vector<std::uint8_t>& mixed,
                      double min_jump_mm) {
  Cloud out;
  const std::size_t w = cloud.width, h = cloud.height;
  if (w * h != cloud.size() || w < 3 || h < 3) return out;
  const bool has_mixed = mixed.size() == cloud.size();
  auto usable = [&](std::size_t k) { return !std::isnan(range[k]) && !(has_mixed && mixed[k] != 0); };
  const auto jump = static_cast<float>(std::max(0.0, min_jump_mm));
  constexpr int du[4] = {1, -1, 0, 0};
  constexpr int dv[4] = {0, 0, 1, -1};
  const int iw = static_cast<int>(w), ih = static_cast<int>(h);
  const int threads = detail::thread_count(0);
  std::vector<std::vector<Eigen::Vector3f>> found(static_cast<std::size_t>(threads));
  detail::parallel_for(h, threads, [&](std::size_t th, std::size_t b, std::size_t e) {
    auto& f = found[th];
    for (int v = static_cast<int>(b); v < static_cast<int>(e); ++v)
      for (int u = 0; u < iw; ++u) {
        const auto k = static_cast<std::size_t>(v * iw + u);
        if (!usable(k)) continue;
        const Eigen::Vector3f& a = cloud.points[k];
        const float ra = range[k];
        for (int d = 0; d < 4; ++d) {
          int uu = u + du[d], vv = v + dv[d];
          if (uu < 0 || uu >= iw || vv < 0 || vv >= ih) continue;
          auto n = static_cast<std::size_t>(vv * iw + uu);
          if (std::isnan(range[n])) continue;  // a dropout: where the face ends is unknown
          if (has_mixed && mixed[n] != 0) {    // past one mixed pixel
            uu += du[d], vv += dv[d];
            if (uu < 0 || uu >= iw || vv < 0 || vv >= ih) continue;
            n = static_cast<std::size_t>(vv * iw + uu);
            if (!usable(n)) continue;
          }
          const float rb = range[n];
          if (!(rb - ra > jump)) continue;
          const Eigen::Vector3f& p = cloud.points[n];
          f.push_back((a / ra + p / rb).normalized() * ra);
        }
      }
  }, 16);
  for (auto& f : found) out.points.insert(out.points.end(), f.begin(), f.end());
  return out;
}
}  // namespace

OrganizedCloud remove_statistical_outliers(const OrganizedCloud& cloud, int window_radius, double std_ratio) {
  if (window_radius <= 0 || cloud.width == 0 || cloud.height == 0) return cloud;
  const int w = static_cast<int>(cloud.width);
  const int h = static_cast<int>(cloud.height);
  std::vector<float> mean_dist(cloud.size(), -1.0f);
  detail::parallel_for(static_cast<std::size_t>(h), detail::thread_count(0), [&](std::size_t, std::size_t b, std::size_t e) {
    for (int v = static_cast<int>(b); v < static_cast<int>(e); ++v) {
      for (int u = 0; u < w; ++u) {
        const auto i = static_cast<std::size_t>(v * w + u);
        const Eigen::Vector3f& p = cloud.points[i];
        if (!p.allFinite()) continue;
        float s = 0.0f;
        int n = 0;
        for (int dv = -window_radius; dv <= window_radius; ++dv) {
          const int vv = v + dv;
          if (vv < 0 || vv >= h) continue;
          for (int du = -window_radius; du <= window_radius; ++du) {
            const int uu = u + du;
            if (uu < 0 || uu >= w || (du == 0 && dv == 0)) continue;
            const Eigen::Vector3f& q = cloud.points[static_cast<std::size_t>(vv * w + uu)];
            if (!q.allFinite()) continue;
            s += (q - p).norm();
            ++n;
          }
        }
        mean_dist[i] = n > 0 ? s / static_cast<float>(n) : std::numeric_limits<float>::infinity();
      }
    }
  });
  double sum = 0.0;
  double sum2 = 0.0;
  std::size_t n = 0;
  for (float d : mean_dist) {
    if (d < 0.0f || !std::isfinite(d)) continue;
    sum += d;
    sum2 += static_cast<double>(d) * d;
    ++n;
  }
  OrganizedCloud out = cloud;
  if (n < 2) return out;
  const double mean = sum / static_cast<double>(n);
  const double sd = std::sqrt(std::max(0.0, sum2 / static_cast<double>(n) - mean * mean));
  const double limit = mean + std_ratio * sd;
  for (std::size_t i = 0; i < out.size(); ++i)
    if (mean_dist[i] >= 0.0f && !(mean_dist[i] <= limit)) out.points[i] = OrganizedCloud::invalid();
  return out;
}

void estimate_normals(Cloud& cloud, int k, const Eigen::Vector3f& viewpoint) {
  cloud.normals.assign(cloud.size(), Eigen::Vector3f::UnitZ());
  if (cloud.size() < 3) return;
  const auto tree = detail::make_tree(cloud.points);
  const int kk = std::min<int>(k, static_cast<int>(cloud.size()));
  detail::parallel_for(cloud.size(), detail::thread_count(0), [&](std::size_t, std::size_t b, std::size_t e) {
    pcl::Indices idx(static_cast<std::size_t>(kk));
    std::vector<float> d2(static_cast<std::size_t>(kk));
    pcl::PointXYZ q;
    for (std::size_t i = b; i < e; ++i) {
      q.getVector3fMap() = cloud.points[i];
      const int found = tree->nearestKSearch(q, kk, idx, d2);
      if (found < 3) continue;
      Eigen::Vector3d mean = Eigen::Vector3d::Zero();
      for (int j = 0; j < found; ++j) mean += cloud.points[static_cast<std::size_t>(idx[static_cast<std::size_t>(j)])].cast<double>();
      mean /= found;
      Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
      for (int j = 0; j < found; ++j) {
        const Eigen::Vector3d d = cloud.points[static_cast<std::size_t>(idx[static_cast<std::size_t>(j)])].cast<double>() - mean;
        cov += d * d.transpose();
      }
      Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
      es.computeDirect(cov);
      Eigen::Vector3f n = es.eigenvectors().col(0).cast<float>().normalized();
      if (n.dot(viewpoint - cloud.points[i]) < 0.0f) n = -n;
      cloud.normals[i] = n;
    }
  });
}

Cloud organized_normals(const OrganizedCloud& cloud, float depth_change_factor, float smoothing_size) {
  Cloud out;
  if (cloud.width < 3 || cloud.height < 3) return out;
  auto pc = std::make_shared<pcl::PointCloud<pcl::PointXYZ>>();
  pc->width = cloud.width;
  pc->height = cloud.height;
  pc->is_dense = false;
  pc->resize(cloud.size());
  for (std::size_t i = 0; i < cloud.size(); ++i) (*pc)[i].getVector3fMap() = cloud.points[i];
  pcl::IntegralImageNormalEstimation<pcl::PointXYZ, pcl::Normal> ne;
  ne.setNormalEstimationMethod(ne.AVERAGE_3D_GRADIENT);
  ne.setMaxDepthChangeFactor(depth_change_factor);
  ne.setNormalSmoothingSize(smoothing_size);
  ne.setInputCloud(pc);
  pcl::PointCloud<pcl::Normal> normals;
  ne.compute(normals);
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    const Eigen::Vector3f n = normals[i].getNormalVector3fMap();
    if (!cloud.points[i].allFinite() || !n.allFinite()) continue;
    out.points.push_back(cloud.points[i]);
    Eigen::Vector3f nn = n.normalized();
    if (nn.dot(-cloud.points[i]) < 0.0f) nn = -nn;
    out.normals.push_back(nn);
  }
  return out;
}

}  // namespace fettle::vision
