#pragma once
// Private helpers of fettle::vision: PCL conversions, search trees, a tiny parallel_for.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <thread>
#include <vector>

#include <pcl/kdtree/kdtree_flann.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>

#include "fettle/vision/cloud.hpp"

namespace fettle::vision::detail {

using PclCloud = pcl::PointCloud<pcl::PointXYZ>;
using Tree = pcl::KdTreeFLANN<pcl::PointXYZ>;

inline PclCloud::Ptr to_pcl(const std::vector<Eigen::Vector3f>& points) {
  auto out = std::make_shared<PclCloud>();
  out->resize(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) (*out)[i].getVector3fMap() = points[i];
  out->width = static_cast<std::uint32_t>(points.size());
  out->height = 1;
  out->is_dense = true;
  return out;
}

inline std::shared_ptr<Tree> make_tree(const std::vector<Eigen::Vector3f>& points) {
  auto tree = std::make_shared<Tree>(false);  // unsorted results: faster, we only need nearest
  if (!points.empty()) tree->setInputCloud(to_pcl(points));
  return tree;
}

/// SplitMix64 (Steele, Lea, Flood 2014): a tiny counter-based generator, cheap to seed per
/// RANSAC iteration so hypotheses do not depend on how iterations are spread over threads.
struct SplitMix64 {
  using result_type = std::uint64_t;
  std::uint64_t state;
  explicit SplitMix64(std::uint64_t seed) : state(seed) {}
  static constexpr result_type min() { return 0; }
  static constexpr result_type max() { return ~result_type{0}; }
  result_type operator()() {
    std::uint64_t z = (state += 0x9E3779B97F4A7C15ULL);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31);
  }
};

inline int thread_count(int requested) {
  if (requested > 0) return requested;
  return static_cast<int>(std::max(1U, std::thread::hardware_concurrency()));
}

/// Runs fn(thread, begin, end) over [0, n) split into contiguous chunks (one thread when n is
/// below min_n: not worth starting threads for).
template <class Fn>
void parallel_for(std::size_t n, int threads, Fn&& fn, std::size_t min_n = 2048) {
  const auto t = static_cast<std::size_t>(std::max(1, threads));
  if (t == 1 || n < min_n) {
    fn(0, std::size_t{0}, n);
    return;
  }
  std::vector<std::thread> pool;
  const std::size_t chunk = (n + t - 1) / t;
  for (std::size_t i = 1; i < t; ++i) {
    const std::size_t b = i * chunk;
    const std::size_t e = std::min(n, b + chunk);
    if (b < e) pool.emplace_back([&fn, i, b, e] { fn(i, b, e); });
  }
  fn(0, std::size_t{0}, std::min(n, chunk));
  for (auto& th : pool) th.join();
}

/// Nearest neighbour (index, squared distance) for one point; -1 when the tree is empty.
inline std::pair<int, float> nearest(const Tree& tree, const Eigen::Vector3f& p) {
  pcl::PointXYZ q;
  q.getVector3fMap() = p;
  pcl::Indices idx(1);
  std::vector<float> d2(1);
  if (tree.getInputCloud() == nullptr || tree.nearestKSearch(q, 1, idx, d2) < 1) return {-1, 0.0f};
  return {idx[0], d2[0]};
}

}  // namespace fettle::vision::detail
