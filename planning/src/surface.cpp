// Signed distance from template surface samples (a hashed voxel grid of points + normals).
#include "fettle/planning/surface.hpp"

#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <numbers>
#include <stdexcept>
#include <algorithm>

namespace fettle::planning {
namespace {

/// Samples bucketed in a dense grid of cubic cells over their bounding box (CSR layout:
/// the samples of cell c are order[first[c] .. first[c + 1])).
struct SampleIndex {
  std::vector<Vec3> points, normals;
  double cell = 4.0, search = 20.0, spacing = 0.5;
  Vec3 origin = Vec3::Zero();          ///< lower corner of cell (0, 0, 0)
  std::int64_t nx = 0, ny = 0, nz = 0;
  std::vector<std::uint32_t> first, order;
  /// Per cell, the Chebyshev distance in cells to the nearest cell holding a sample (capped at
  /// 255): a query skips the shells that are empty for certain. Most of a tool's probes are in
  /// the air; without this, searching every shell out to `search` around them takes 70 % of
  /// planning time (bench_planning_sim).
  std::vector<std::uint8_t> empty_shells;

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
    build_empty_shells();
  }

  /// Two-pass chamfer distance transform with unit weights over the 26-neighbourhood: exact
  /// for the Chebyshev distance.
  void build_empty_shells() {
    const auto cells = static_cast<std::size_t>(nx * ny * nz);
    empty_shells.assign(cells, 255);
    for (std::size_t c = 0; c < cells; ++c)
      if (first[c + 1] > first[c]) empty_shells[c] = 0;
    auto pass = [&](int dir) {
      const std::int64_t k0 = dir > 0 ? 0 : nz - 1, k1 = dir > 0 ? nz : -1;
      const std::int64_t j0 = dir > 0 ? 0 : ny - 1, j1 = dir > 0 ? ny : -1;
      const std::int64_t i0 = dir > 0 ? 0 : nx - 1, i1 = dir > 0 ? nx : -1;
      for (std::int64_t k = k0; k != k1; k += dir)
        for (std::int64_t j = j0; j != j1; j += dir)
          for (std::int64_t i = i0; i != i1; i += dir) {
            auto& here = empty_shells[flat(i, j, k)];
            if (here == 0) continue;
            // the 13 neighbours already visited in this pass's order
            for (std::int64_t dk = -1; dk <= 0; ++dk)
              for (std::int64_t dj = -1; dj <= 1; ++dj)
                for (std::int64_t di = -1; di <= 1; ++di) {
                  if (dk == 0 && (dj > 0 || (dj == 0 && di >= 0))) continue;
                  const std::int64_t a = i + dir * di, b = j + dir * dj, c = k + dir * dk;
                  if (a < 0 || a >= nx || b < 0 || b >= ny || c < 0 || c >= nz) continue;
                  here = static_cast<std::uint8_t>(std::min<int>(here, empty_shells[flat(a, b, c)] + 1));
                }
          }
    };
    pass(1);
    pass(-1);
  }

  /// Nearest sample to p within `search` (other than `exclude`), or -1; squared distance in d2.
  [[nodiscard]] std::int64_t nearest(const Vec3& p, double& d2, std::int64_t exclude = -1) const {
    d2 = search * search;
    if (points.empty()) return -1;
    const auto ci = idx(p.x(), origin.x()), cj = idx(p.y(), origin.y()), ck = idx(p.z(), origin.z());
    const auto reach = static_cast<std::int64_t>(std::ceil(search / cell));
    // farther than `search` from every cell of the grid: no sample can be within reach
    auto gap = [&](std::int64_t c, std::int64_t n) { return c < 0 ? -c : (c >= n ? c - n + 1 : 0); };
    const std::int64_t outside = std::max({gap(ci, nx), gap(cj, ny), gap(ck, nz)});
    if (outside > reach) return -1;
    std::int64_t found = -1;
    // shells nearer than the nearest occupied cell are empty (a query outside the grid starts
    // at its distance to the grid)
    const std::int64_t r0 = outside > 0 ? outside : std::int64_t{empty_shells[flat(ci, cj, ck)]};
    for (std::int64_t r = r0; r <= reach; ++r) {
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
              if (static_cast<std::int64_t>(s) == exclude) continue;
              const double dd = (points[s] - p).squaredNorm();
              if (dd < d2) d2 = dd, found = s;
            }
          }
        }
      if (found >= 0 && std::sqrt(d2) <= static_cast<double>(r) * cell) break;
    }
    return found;
  }

  /// Calls fn(sample) for every sample within `radius` of p.
  template <class Fn>
  void within(const Vec3& p, double radius, Fn&& fn) const {
    const auto r = static_cast<std::int64_t>(std::ceil(radius / cell));
    const auto ci = idx(p.x(), origin.x()), cj = idx(p.y(), origin.y()), ck = idx(p.z(), origin.z());
    for (std::int64_t k = std::max<std::int64_t>(0, ck - r); k <= std::min(nz - 1, ck + r); ++k)
      for (std::int64_t j = std::max<std::int64_t>(0, cj - r); j <= std::min(ny - 1, cj + r); ++j)
        for (std::int64_t i = std::max<std::int64_t>(0, ci - r); i <= std::min(nx - 1, ci + r); ++i) {
          const auto c = flat(i, j, k);
          for (auto q = first[c]; q < first[c + 1]; ++q)
            if ((points[order[q]] - p).squaredNorm() <= radius * radius) fn(order[q]);
        }
  }

  /// Median distance between neighbouring samples, from up to 2000 of them.
  void estimate_spacing() {
    std::vector<double> d;
    const std::size_t stride = std::max<std::size_t>(1, points.size() / 2000);
    for (std::size_t s = 0; s < points.size(); s += stride) {
      double d2 = 0;
      if (nearest(points[s], d2, static_cast<std::int64_t>(s)) >= 0) d.push_back(std::sqrt(d2));
    }
    if (d.empty()) return;
    std::nth_element(d.begin(), d.begin() + static_cast<std::ptrdiff_t>(d.size() / 2), d.end());
    spacing = std::max(1e-3, d[d.size() / 2]);
  }

  /// For each sample, the sample within two spacings whose normal turns most (more than 45°)
  /// from its own: the other face of an edge through it, or -1 on a smooth patch.
  std::vector<std::int32_t> partner;

  void find_partners() {
    partner.assign(points.size(), -1);
    const double radius = 2.0 * spacing;
    for (std::size_t s = 0; s < points.size(); ++s) {
      double lowest = std::cos(std::numbers::pi / 4);
      within(points[s], radius, [&](std::uint32_t q) {
        const double c = normals[s].dot(normals[q]);
        if (c < lowest) lowest = c, partner[s] = static_cast<std::int32_t>(q);
      });
    }
  }

  [[nodiscard]] double query(const Vec3& p) const {
    double d2 = 0;
    const auto found = nearest(p, d2);
    if (found < 0) return search;
    const auto s = static_cast<std::size_t>(found);
    const Vec3 d = p - points[s];
    const double along = d.dot(normals[s]);
    // At an edge the nearest sample may belong to the other face (a wall's top sample for a
    // point just above the top): both tangent planes count. Locally the solid is the
    // intersection of the two half-spaces at a convex edge (the larger distance holds) and
    // their union at a concave one (the smaller).
    double planes = along;
    if (const std::int32_t o = partner[s]; o >= 0) {
      const auto so = static_cast<std::size_t>(o);
      const double along_o = (p - points[so]).dot(normals[so]);
      // convex when the normals open away from each other (the local convexity criterion of
      // Stein et al., LCCP, CVPR 2014); symmetric in the two samples, so a partner a few
      // hundredths of a millimetre beside the other's plane (a sampled or stepped wall) cannot
      // turn a convex edge concave
      const bool convex = (normals[s] - normals[so]).dot(points[s] - points[so]) > 0.0;
      planes = convex ? std::max(along, along_o) : std::min(along, along_o);
    }
    // Where p projects onto the sampled patch around s (lateral offset within one sample
    // spacing) that is accurate to well below the spacing. Off the patch (beside an edge) the
    // tangent planes say nothing about the size (above a vertical wall's top edge the wall's
    // says 0): the distance to s, short by at most a spacing, with the planes' sign.
    // Just outside a convex edge the solid lies in both tangent half-spaces, so the larger plane
    // distance is a bound too: diagonally off a wall's top edge the wall's top sample alone said
    // 0.03 mm for a point 0.25 mm above the top and 0.03 mm past the wall, and no lift cleared it
    // (test SampledSdf.DiagonallyOffAConvexEdgeTheDistanceIsNotTheWallsAlone). Only within two
    // spacings of the sample: farther, the distance to it is as good, and does not depend on
    // which of two equally near samples was found (test SampledSdf.TheAnswerDoesNotDependOnTheCellSize).
    const double lateral = std::sqrt(std::max(0.0, d2 - along * along));
    const double beyond = lateral - spacing;
    if (beyond <= 0.0) return planes;
    const double off_patch = std::sqrt(along * along + beyond * beyond);
    if (planes >= 0.0) return d2 <= 4.0 * spacing * spacing ? std::max(planes, off_patch) : off_patch;
    return -off_patch;
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
  index->estimate_spacing();
  index->find_partners();
  return [index](const Vec3& p) { return index->query(p); };
}

}  // namespace fettle::planning
