// Signed distance from template surface samples (a hashed voxel grid of points + normals).
#include "fettle/planning/surface.hpp"

#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <stdexcept>
#include <unordered_map>

namespace fettle::planning {
namespace {

struct SampleIndex {
  std::vector<Vec3> points, normals;
  double cell = 4.0, search = 20.0;
  std::unordered_map<std::uint64_t, std::vector<std::uint32_t>> cells;

  static std::uint64_t key(std::int64_t i, std::int64_t j, std::int64_t k) {
    constexpr std::int64_t off = 1 << 20;
    return (static_cast<std::uint64_t>(i + off) << 42) | (static_cast<std::uint64_t>(j + off) << 21) |
           static_cast<std::uint64_t>(k + off);
  }
  [[nodiscard]] std::int64_t idx(double v) const { return static_cast<std::int64_t>(std::floor(v / cell)); }

  [[nodiscard]] double query(const Vec3& p) const {
    const auto ci = idx(p.x()), cj = idx(p.y()), ck = idx(p.z());
    const auto reach = static_cast<std::int64_t>(std::ceil(search / cell));
    double best = search * search;
    std::int64_t found = -1;
    for (std::int64_t r = 0; r <= reach; ++r) {
      // shell r around the query cell; stop once a sample is found closer than the shell
      for (std::int64_t i = ci - r; i <= ci + r; ++i)
        for (std::int64_t j = cj - r; j <= cj + r; ++j)
          for (std::int64_t k = ck - r; k <= ck + r; ++k) {
            if (std::max({std::abs(i - ci), std::abs(j - cj), std::abs(k - ck)}) != r) continue;
            const auto it = cells.find(key(i, j, k));
            if (it == cells.end()) continue;
            for (auto s : it->second) {
              const double d2 = (points[s] - p).squaredNorm();
              if (d2 < best) best = d2, found = s;
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
  for (std::size_t i = 0; i < points.size(); ++i) {
    const Vec3& p = points[i];
    index->cells[SampleIndex::key(index->idx(p.x()), index->idx(p.y()), index->idx(p.z()))].push_back(
        static_cast<std::uint32_t>(i));
    normals[i].normalize();
  }
  index->points = std::move(points);
  index->normals = std::move(normals);
  return [index](const Vec3& p) { return index->query(p); };
}

}  // namespace fettle::planning
