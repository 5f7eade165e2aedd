#pragma once
// Private spatial structures of fettle::vision: a voxel hash (open addressing), a radius-search
// grid built on it, and a dense nearest-template-point lookup grid for ICP.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include <Eigen/Core>

namespace fettle::vision::detail {

/// Integer cell of a point for cell size 1/inv (floor).
inline Eigen::Vector3i cell_of(const Eigen::Vector3f& p, float inv) {
  return {static_cast<int>(std::floor(p.x() * inv)), static_cast<int>(std::floor(p.y() * inv)),
          static_cast<int>(std::floor(p.z() * inv))};
}

/// 21 bits per axis (cells within +-2^20 of the origin: +-1 km at 1 mm cells); farther cells
/// wrap, which merges cells 2^21 apart and never neighbours.
inline std::uint64_t cell_key(const Eigen::Vector3i& c) {
  constexpr std::uint64_t kMask = 0x1FFFFF;
  const auto x = static_cast<std::uint64_t>(static_cast<std::int64_t>(c.x()) + (1 << 20)) & kMask;
  const auto y = static_cast<std::uint64_t>(static_cast<std::int64_t>(c.y()) + (1 << 20)) & kMask;
  const auto z = static_cast<std::uint64_t>(static_cast<std::int64_t>(c.z()) + (1 << 20)) & kMask;
  return (x << 42) | (y << 21) | z;
}

/// Cell key -> dense id (0, 1, 2, ... in order of first insertion). Linear probing.
class CellIndex {
 public:
  explicit CellIndex(std::size_t expected_cells) {
    std::size_t cap = 16;
    while (cap < 2 * expected_cells + 16) cap *= 2;
    keys_.assign(cap, kEmpty);
    ids_.resize(cap);
    mask_ = cap - 1;
  }
  /// The id of `key`, inserting it with id size() when absent.
  std::uint32_t insert(std::uint64_t key) {
    if (2 * (size_ + 1) > keys_.size()) grow();
    std::size_t i = slot(key);
    while (keys_[i] != kEmpty) {
      if (keys_[i] == key) return ids_[i];
      i = (i + 1) & mask_;
    }
    keys_[i] = key;
    ids_[i] = static_cast<std::uint32_t>(size_);
    return static_cast<std::uint32_t>(size_++);
  }
  /// The id of `key`, or -1.
  [[nodiscard]] std::int64_t find(std::uint64_t key) const {
    std::size_t i = slot(key);
    while (keys_[i] != kEmpty) {
      if (keys_[i] == key) return ids_[i];
      i = (i + 1) & mask_;
    }
    return -1;
  }
  [[nodiscard]] std::size_t size() const { return size_; }

 private:
  static constexpr std::uint64_t kEmpty = ~std::uint64_t{0};
  [[nodiscard]] std::size_t slot(std::uint64_t key) const {
    key ^= key >> 33;
    key *= 0xff51afd7ed558ccdULL;
    key ^= key >> 33;
    return static_cast<std::size_t>(key) & mask_;
  }
  void grow() {
    std::vector<std::uint64_t> keys(keys_.size() * 2, kEmpty);
    std::vector<std::uint32_t> ids(keys.size());
    keys.swap(keys_);
    ids.swap(ids_);
    mask_ = keys_.size() - 1;
    for (std::size_t j = 0; j < keys.size(); ++j) {
      if (keys[j] == kEmpty) continue;
      std::size_t i = slot(keys[j]);
      while (keys_[i] != kEmpty) i = (i + 1) & mask_;
      keys_[i] = keys[j];
      ids_[i] = ids[j];
    }
  }
  std::vector<std::uint64_t> keys_;
  std::vector<std::uint32_t> ids_;
  std::size_t mask_ = 0;
  std::size_t size_ = 0;
};

/// Centroid per voxel, accumulated point by point (a hash, no sort): the voxel grid of the
/// preprocessing. Output order is the order in which voxels were first seen.
class VoxelAccumulator {
 public:
  VoxelAccumulator(double voxel, std::size_t expected_points)
      : inv_(static_cast<float>(1.0 / voxel)), index_(expected_points / 2 + 16) {}
  void add(const Eigen::Vector3f& p) {
    const std::uint64_t key = cell_key(cell_of(p, inv_));
    const std::uint32_t id = index_.insert(key);
    if (id == sums_.size()) {
      sums_.emplace_back(Eigen::Vector3d::Zero());
      counts_.push_back(0);
      keys_.push_back(key);
    }
    sums_[id] += p.cast<double>();
    ++counts_[id];
  }
  /// Adds the voxels of another accumulator (same voxel size, no normals).
  void merge(const VoxelAccumulator& other) {
    for (std::size_t k = 0; k < other.sums_.size(); ++k) {
      const std::uint32_t id = index_.insert(other.keys_[k]);
      if (id == sums_.size()) {
        sums_.emplace_back(Eigen::Vector3d::Zero());
        counts_.push_back(0);
        keys_.push_back(other.keys_[k]);
      }
      sums_[id] += other.sums_[k];
      counts_[id] += other.counts_[k];
    }
  }
  void add(const Eigen::Vector3f& p, const Eigen::Vector3f& n) {
    const std::uint32_t id = index_.insert(cell_key(cell_of(p, inv_)));
    if (id == sums_.size()) {
      sums_.emplace_back(Eigen::Vector3d::Zero());
      counts_.push_back(0);
      nsums_.emplace_back(n.cast<double>());
    } else {
      // Normals of one voxel may be flipped against each other: align with the sum so far.
      Eigen::Vector3d nd = n.cast<double>();
      if (nd.dot(nsums_[id]) < 0) nd = -nd;
      nsums_[id] += nd;
    }
    sums_[id] += p.cast<double>();
    ++counts_[id];
  }
  [[nodiscard]] std::size_t size() const { return sums_.size(); }
  /// Centroids (and averaged, renormalised normals when normals were added).
  void write(std::vector<Eigen::Vector3f>& points, std::vector<Eigen::Vector3f>* normals = nullptr) const {
    points.resize(sums_.size());
    for (std::size_t i = 0; i < sums_.size(); ++i) points[i] = (sums_[i] / counts_[i]).cast<float>();
    if (normals != nullptr && !nsums_.empty()) {
      normals->resize(nsums_.size());
      for (std::size_t i = 0; i < nsums_.size(); ++i) {
        const double len = nsums_[i].norm();
        (*normals)[i] = len > 1e-12 ? Eigen::Vector3f((nsums_[i] / len).cast<float>()) : Eigen::Vector3f::Zero();
      }
    }
  }

 private:
  float inv_;
  CellIndex index_;
  std::vector<Eigen::Vector3d> sums_;
  std::vector<std::uint32_t> counts_;
  std::vector<Eigen::Vector3d> nsums_;
  std::vector<std::uint64_t> keys_;  // of voxels added without normals (for merge)
};

/// Points bucketed by cell (cell size = the largest search radius): radius queries visit the
/// 27 cells around the query. Built in O(n).
class PointGrid {
 public:
  PointGrid(const std::vector<Eigen::Vector3f>& points, double cell)
      : points_(&points), inv_(static_cast<float>(1.0 / cell)), index_(points.size() / 4 + 16) {
    std::vector<std::uint32_t> cell_of_point(points.size());
    for (std::size_t i = 0; i < points.size(); ++i) cell_of_point[i] = index_.insert(cell_key(cell_of(points[i], inv_)));
    start_.assign(index_.size() + 1, 0);
    for (auto c : cell_of_point) ++start_[c + 1];
    for (std::size_t c = 0; c < index_.size(); ++c) start_[c + 1] += start_[c];
    order_.resize(points.size());
    std::vector<std::uint32_t> fill(start_.begin(), start_.end() - 1);
    for (std::size_t i = 0; i < points.size(); ++i) order_[fill[cell_of_point[i]]++] = static_cast<std::uint32_t>(i);
  }
  /// Calls fn(index, squared distance) for every point within sqrt(max_d2) (<= the cell size).
  template <class Fn>
  void for_each_within(const Eigen::Vector3f& q, float max_d2, Fn&& fn) const {
    const Eigen::Vector3i c = cell_of(q, inv_);
    for (int dz = -1; dz <= 1; ++dz)
      for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
          const auto id = index_.find(cell_key(c + Eigen::Vector3i(dx, dy, dz)));
          if (id < 0) continue;
          for (auto k = start_[static_cast<std::size_t>(id)]; k < start_[static_cast<std::size_t>(id) + 1]; ++k) {
            const float d2 = ((*points_)[order_[k]] - q).squaredNorm();
            if (d2 <= max_d2) fn(order_[k], d2);
          }
        }
  }
  /// Nearest point within sqrt(max_d2) (<= the cell size): (index, squared distance), or -1.
  [[nodiscard]] std::pair<int, float> nearest(const Eigen::Vector3f& q, float max_d2) const {
    const Eigen::Vector3i c = cell_of(q, inv_);
    int best = -1;
    float best_d2 = max_d2;
    for (int dz = -1; dz <= 1; ++dz)
      for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
          const auto id = index_.find(cell_key(c + Eigen::Vector3i(dx, dy, dz)));
          if (id < 0) continue;
          for (auto k = start_[static_cast<std::size_t>(id)]; k < start_[static_cast<std::size_t>(id) + 1]; ++k) {
            const float d2 = ((*points_)[order_[k]] - q).squaredNorm();
            if (d2 <= best_d2) {
              best_d2 = d2;
              best = static_cast<int>(order_[k]);
            }
          }
        }
    return {best, best_d2};
  }

 private:
  const std::vector<Eigen::Vector3f>* points_;
  float inv_;
  CellIndex index_;
  std::vector<std::uint32_t> start_;
  std::vector<std::uint32_t> order_;
};

/// Dense lookup grid over a template's bounding box (+ band): each cell holds the template
/// point nearest to the cell centre, for cells within `band` of the template; -1 elsewhere.
/// ICP asks it instead of a search tree: one memory read per correspondence. The answer is
/// the nearest point to the cell centre, i.e. within half a cell diagonal of the exact one;
/// point-to-plane residuals use that point's tangent plane, which is the same surface.
class NearestGrid {
 public:
  NearestGrid() = default;
  NearestGrid(const std::vector<Eigen::Vector3f>& points, double cell, double band) : cell_(static_cast<float>(cell)) {
    if (points.empty() || !(cell > 0)) return;
    Eigen::Vector3f lo = points.front();
    Eigen::Vector3f hi = points.front();
    for (const auto& p : points) {
      lo = lo.cwiseMin(p);
      hi = hi.cwiseMax(p);
    }
    const auto b = static_cast<float>(band);
    origin_ = lo - Eigen::Vector3f::Constant(b + cell_);
    const Eigen::Vector3f extent = hi - lo + Eigen::Vector3f::Constant(2 * (b + cell_));
    for (int a = 0; a < 3; ++a) dims_[a] = static_cast<int>(std::ceil(extent[a] / cell_)) + 1;
    const std::size_t n = static_cast<std::size_t>(dims_[0]) * dims_[1] * dims_[2];
    if (n > (std::size_t{1} << 28)) return;  // > 1 GB: leave it to the search tree
    nearest_.assign(n, -1);
    std::vector<float> best(n, b * b);
    const int r = static_cast<int>(std::ceil(b / cell_));
    const float inv = 1.0f / cell_;
    for (std::size_t i = 0; i < points.size(); ++i) {
      const Eigen::Vector3f g = (points[i] - origin_) * inv;
      const int cx = static_cast<int>(g.x()), cy = static_cast<int>(g.y()), cz = static_cast<int>(g.z());
      for (int z = std::max(0, cz - r); z <= std::min(dims_[2] - 1, cz + r); ++z)
        for (int y = std::max(0, cy - r); y <= std::min(dims_[1] - 1, cy + r); ++y) {
          const std::size_t row = (static_cast<std::size_t>(z) * dims_[1] + y) * dims_[0];
          for (int x = std::max(0, cx - r); x <= std::min(dims_[0] - 1, cx + r); ++x) {
            const Eigen::Vector3f centre = origin_ + (Eigen::Vector3f(x, y, z) + Eigen::Vector3f::Constant(0.5f)) * cell_;
            const float d2 = (centre - points[i]).squaredNorm();
            if (d2 < best[row + x]) {
              best[row + x] = d2;
              nearest_[row + x] = static_cast<std::int32_t>(i);
            }
          }
        }
    }
  }
  [[nodiscard]] bool empty() const { return nearest_.empty(); }
  /// The template point for q, or -1 (farther than the band from the template).
  [[nodiscard]] int lookup(const Eigen::Vector3f& q) const {
    const Eigen::Vector3f g = (q - origin_) / cell_;
    if (!(g.x() >= 0 && g.y() >= 0 && g.z() >= 0)) return -1;
    const int x = static_cast<int>(g.x()), y = static_cast<int>(g.y()), z = static_cast<int>(g.z());
    if (x >= dims_[0] || y >= dims_[1] || z >= dims_[2]) return -1;
    return nearest_[(static_cast<std::size_t>(z) * dims_[1] + y) * dims_[0] + x];
  }

 private:
  float cell_ = 0.0f;
  Eigen::Vector3f origin_ = Eigen::Vector3f::Zero();
  int dims_[3] = {0, 0, 0};
  std::vector<std::int32_t> nearest_;
};

}  // namespace fettle::vision::detail
