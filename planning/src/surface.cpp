// Signed distance from template surface samples (a hashed voxel grid of points + normals).
#include "fettle/planning/surface.hpp"

#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <stdexcept>
#include <algorithm>

namespace fettle::planning {
namespace {

/// Samples bucketed in a dense grid of cubic cells over their bounding box (CSR layout:
/// the samples of cell c are order[first[c] .. first[c + 1])).
struct SampleIndex {
  std::vector<Vec3> points, normals;
  double cell = 4.0, search = 20.0;
  Vec3 origin = Vec3::Zero();          ///< lower corner of cell (0, 0, 0)
  std::int64_t nx = 0, ny = 0, nz = 0;
  std::vector<std::uint32_t> first, order;

  [[nodiscard]] std::int64_t idx(double v, double o) const { return static_cast<std::int64_t>(std::floor((v - o) / cell)); }
  [[nodiscard]] std::size_t flat(std::int64_t i, std::int64_t j, std::int64_t k) const {
    return static_cast<std::size_t>((k * ny + j) * nx + i);
  }

  void build() {
    Vec3 lo = Vec3::Constant(std::numeric_limits<double>::infinity()), hi = -lo;
    for (const auto& p : points) lo = lo.cwiseMin(p), hi = hi.cwiseMax(p);
    if (points.empty()) lo = hi = Vec3::Zero();
    origin = lo;
    nx = idx(hi.x(), lo.x()) + 1, ny = idx(hi.y(), lo.y()) + 1, nz = idx(hi.z(), lo.z()) + 1;
    const auto cells = static_cast<std::size_t>(nx * ny * nz);
    first.assign(cells + 1, 0);
    std::vector<std::size_t> cell_of(points.size());
    for (std::size_t s = 0; s < points.size(); ++s) {
      const auto& p = points[s];
      cell_of[s] = flat(idx(p.x(), origin.x()), idx(p.y(), origin.y()), idx(p.z(), origin.z()));
      ++first[cell_of[s] + 1];
    }
    for (std::size_t c = 0; c < cells; ++c) first[c + 1] += first[c];
    order.resize(points.size());
    std::vector<std::uint32_t> fill(first.begin(), first.end() - 1);
    for (std::size_t s = 0; s < points.size(); ++s) order[fill[cell_of[s]]++] = static_cast<std::uint32_t>(s);
  }

  [[nodiscard]] double query(const Vec3& p) const {
    if (points.empty()) return search;
    const auto ci = idx(p.x(), origin.x()), cj = idx(p.y(), origin.y()), ck = idx(p.z(), origin.z());
    const auto reach = static_cast<std::int64_t>(std::ceil(search / cell));
    // farther than `search` from every cell of the grid: no sample can be within reach
    auto gap = [&](std::int64_t c, std::int64_t n) { return c < 0 ? -c : (c >= n ? c - n + 1 : 0); };
    if (std::max({gap(ci, nx), gap(cj, ny), gap(ck, nz)}) > reach) return search;
    double best = search * search;
    std::int64_t found = -1;
    for (std::int64_t r = 0; r <= reach; ++r) {
      // shell r around the query cell (clipped to the grid); stop once a sample is found
      // closer than the shell
      for (std::int64_t k = std::max<std::int64_t>(0, ck - r); k <= std::min(nz - 1, ck + r); ++k)
        for (std::int64_t j = std::max<std::int64_t>(0, cj - r); j <= std::min(ny - 1, cj + r); ++j) {
          const bool face = std::abs(k - ck) == r || std::abs(j - cj) == r;
          const std::int64_t step = face ? 1 : 2 * r;  // inside the shell only i = ci +- r
          for (std::int64_t i = ci - r; i <= ci + r; i += std::max<std::int64_t>(1, step)) {
            if (i < 0 || i >= nx) continue;
            const auto c = flat(i, j, k);
            for (auto q = first[c]; q < first[c + 1]; ++q) {
              const auto s = order[q];
              const double d2 = (points[s] - p).squaredNorm();
              if (d2 < best) best = d2, found = s;
            }
          }
        }
      if (found >= 0 && std::sqrt(best) <= static_cast<double>(r) * cell) break;
    }
    if (found < 0) return search;
    const auto s = static_cast<std::size_t>(found);
    return (p - points[s]).dot(normals[s]);
  }
};

}  // namespace

SignedDistance sdf_from_samples(std::vector<Vec3> points, std::vector<Vec3> normals, double cell_mm, double search_mm) {
  if (points.size() != normals.size())
    throw std::invalid_argument("sdf_from_samples: " + std::to_string(points.size()) + " points but " +
                                std::to_string(normals.size()) + " normals");
  auto index = std::make_shared<SampleIndex>();
  index->cell = cell_mm > 0 ? cell_mm : 4.0;
  index->search = search_mm > 0 ? search_mm : 20.0;
  for (auto& n : normals) n.normalize();
  index->points = std::move(points);
  index->normals = std::move(normals);
  index->build();
  return [index](const Vec3& p) { return index->query(p); };
}

}  // namespace fettle::planning
