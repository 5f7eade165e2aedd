// The simulated casting: golden body, form deviation, flash and risers, placement, scene.
#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <numbers>

#include "casting_model.hpp"
#include "fettle/core/error.hpp"

namespace fettle::sim {
namespace {

using config::ValueRange;

double draw(Rng& rng, const ValueRange& r, bool vary) { return vary ? rng.uniform(r.min, r.max) : 0.5 * (r.min + r.max); }

/// A smooth periodic function of an angle in [-1, 1] (three random harmonics).
struct Wobble {
  std::array<double, 3> phase{0, 0, 0};
  std::array<double, 3> weight{0, 0, 0};
  Wobble(Rng& rng, bool vary) {
    double sum = 0;
    for (std::size_t k = 0; k < 3; ++k) {
      phase[k] = rng.uniform(0.0, 2 * std::numbers::pi);
      weight[k] = vary ? rng.uniform(0.3, 1.0) : 0.0;
      sum += weight[k];
    }
    if (sum > 0)
      for (auto& w : weight) w /= sum;
  }
  [[nodiscard]] double operator()(double a, double base_freq) const {
    double v = 0;
    for (std::size_t k = 0; k < 3; ++k)
      v += weight[k] * std::sin(base_freq * static_cast<double>(k * 2 + 3) * a + phase[k]);
    return v;
  }
};

/// Value noise in [-1, 1] on a lattice of `cell` mm (bilinear), seeded.
double value_noise(std::uint64_t seed, double x, double y, double cell) {
  const double u = x / cell, v = y / cell;
  const double fu = std::floor(u), fv = std::floor(v);
  const auto i = static_cast<std::int64_t>(fu), j = static_cast<std::int64_t>(fv);
  auto node = [&](std::int64_t a, std::int64_t b) {
    Rng r(seed, static_cast<std::uint64_t>(a) * 0x9E3779B1ULL, static_cast<std::uint64_t>(b));
    return r.uniform(-1.0, 1.0);
  };
  const double tu = u - fu, tv = v - fv;
  return (1 - tu) * (1 - tv) * node(i, j) + tu * (1 - tv) * node(i + 1, j) + (1 - tu) * tv * node(i, j + 1) +
         tu * tv * node(i + 1, j + 1);
}

HeightField make_field(const Vec3& lo, const Vec3& hi, double pitch) {
  HeightField f;
  f.pitch = pitch;
  f.x0 = lo.x() - 2 * pitch;
  f.y0 = lo.y() - 2 * pitch;
  f.nx = static_cast<int>(std::ceil((hi.x() - lo.x()) / pitch)) + 4;
  f.ny = static_cast<int>(std::ceil((hi.y() - lo.y()) / pitch)) + 4;
  f.h.assign(static_cast<std::size_t>(f.nx) * static_cast<std::size_t>(f.ny), kNoPart);
  return f;
}

Material make_material(const std::string& region, const config::PartRecipe& recipe, double x0, double y0, double x1,
                       double y1, double pitch) {
  Material m;
  m.region = region;
  for (std::size_t i = 0; i < recipe.regions.size(); ++i)
    if (recipe.regions[i].name == region) m.region_index = static_cast<int>(i);
  m.pitch = pitch;
  m.x0 = x0;
  m.y0 = y0;
  m.nx = std::max(1, static_cast<int>(std::ceil((x1 - x0) / pitch)));
  m.ny = std::max(1, static_cast<int>(std::ceil((y1 - y0) / pitch)));
  const auto n = static_cast<std::size_t>(m.nx) * static_cast<std::size_t>(m.ny);
  m.z0.assign(n, 0.0f);
  m.z1.assign(n, 0.0f);
  return m;
}

double box_sdf_inside(const Vec3& p, const config::BodyBlock& b) {
  const double cx = 0.5 * (b.min_mm[0] + b.max_mm[0]);
  const double cy = 0.5 * (b.min_mm[1] + b.max_mm[1]);
  const double sx = std::tan(deg_to_rad(b.top_slope_deg[0]));
  const double sy = std::tan(deg_to_rad(b.top_slope_deg[1]));
  // top plane: z - (max_z + sx (x - cx) + sy (y - cy)) <= 0, normalized
  const double top = (p.z() - (b.max_mm[2] + sx * (p.x() - cx) + sy * (p.y() - cy))) / std::sqrt(1 + sx * sx + sy * sy);
  double d = top;
  d = std::max(d, b.min_mm[0] - p.x());
  d = std::max(d, p.x() - b.max_mm[0]);
  d = std::max(d, b.min_mm[1] - p.y());
  d = std::max(d, p.y() - b.max_mm[1]);
  d = std::max(d, b.min_mm[2] - p.z());
  return d;
}

/// The closest point of triangle abc to p (Ericson, Real-Time Collision Detection, 5.1.5).
Vec3 closest_on_triangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c) {
  const Vec3 ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const Vec3 bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return a + d1 / (d1 - d3) * ab;
  const Vec3 cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return a + d2 / (d2 - d6) * ac;
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) return b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b);
  const double denom = 1.0 / (va + vb + vc);
  return a + ab * (vb * denom) + ac * (vc * denom);
}

/// The exact distance from a point outside a block with a tilted top (a convex polyhedron) to
/// it: the nearest of its six faces, each two triangles.
double tilted_box_outside_distance(const Vec3& p, const config::BodyBlock& b) {
  const double cx = 0.5 * (b.min_mm[0] + b.max_mm[0]);
  const double cy = 0.5 * (b.min_mm[1] + b.max_mm[1]);
  const double sx = std::tan(deg_to_rad(b.top_slope_deg[0]));
  const double sy = std::tan(deg_to_rad(b.top_slope_deg[1]));
  std::array<Vec3, 8> v;  // bottom 0-3, top 4-7, counter-clockwise from (min x, min y)
  const std::array<std::array<double, 2>, 4> xy{{{b.min_mm[0], b.min_mm[1]},
                                                 {b.max_mm[0], b.min_mm[1]},
                                                 {b.max_mm[0], b.max_mm[1]},
                                                 {b.min_mm[0], b.max_mm[1]}}};
  for (std::size_t k = 0; k < 4; ++k) {
    const double x = xy[k][0], y = xy[k][1];
    v[k] = Vec3(x, y, b.min_mm[2]);
    v[k + 4] = Vec3(x, y, b.max_mm[2] + sx * (x - cx) + sy * (y - cy));
  }
  static constexpr std::array<std::array<int, 4>, 6> kFaces{
      {{0, 1, 2, 3}, {4, 5, 6, 7}, {0, 1, 5, 4}, {1, 2, 6, 5}, {2, 3, 7, 6}, {3, 0, 4, 7}}};
  double d2 = std::numeric_limits<double>::infinity();
  for (const auto& f : kFaces)
    for (const auto& [i, j, k] : {std::array<int, 3>{f[0], f[1], f[2]}, std::array<int, 3>{f[0], f[2], f[3]}}) {
      const Vec3 q = closest_on_triangle(p, v[static_cast<std::size_t>(i)], v[static_cast<std::size_t>(j)],
                                         v[static_cast<std::size_t>(k)]);
      d2 = std::min(d2, (p - q).squaredNorm());
    }
  return std::sqrt(d2);
}

double cylinder_sdf(const Vec3& p, const config::BodyCylinder& c) {
  const double r = std::hypot(p.x() - c.center_mm[0], p.y() - c.center_mm[1]) - c.radius_mm;
  const double z = std::max(c.base_z_mm - p.z(), p.z() - c.top_z_mm);
  if (r <= 0 || z <= 0) return std::max(r, z);
  return std::hypot(r, z);
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// HeightField

double HeightField::bilinear(double x, double y) const {
  const double u = (x - x0) / pitch - 0.5, v = (y - y0) / pitch - 0.5;
  if (!(u >= 0) || !(v >= 0) || u >= nx - 1 || v >= ny - 1) return kNoPart;
  const int i = static_cast<int>(u), j = static_cast<int>(v);
  const double tu = u - i, tv = v - j;
  return (1 - tu) * (1 - tv) * at(i, j) + tu * (1 - tv) * at(i + 1, j) + (1 - tu) * tv * at(i, j + 1) +
         tu * tv * at(i + 1, j + 1);
}

Eigen::Vector2d HeightField::gradient(double x, double y) const {
  const double e = 0.5 * pitch;
  return {(bilinear(x + e, y) - bilinear(x - e, y)) / (2 * e), (bilinear(x, y + e) - bilinear(x, y - e)) / (2 * e)};
}

double HeightField::distance(const Vec3& p, double max_search_mm) const {
  const double h0 = bilinear(p.x(), p.y());
  const bool inside = p.z() < h0;
  const double d0 = std::abs(p.z() - h0);
  double best = d0;
  const double radius = std::min(d0, max_search_mm);
  const int ci = static_cast<int>(std::floor((p.x() - x0) / pitch));
  const int cj = static_cast<int>(std::floor((p.y() - y0) / pitch));
  const int r = static_cast<int>(std::ceil(radius / pitch)) + 1;
  for (int j = std::max(0, cj - r); j <= std::min(ny - 1, cj + r); ++j) {
    const double dy = std::max(0.0, std::abs(cy(j) - p.y()) - 0.5 * pitch);
    if (dy >= best) continue;
    for (int i = std::max(0, ci - r); i <= std::min(nx - 1, ci + r); ++i) {
      const double top = at(i, j);
      const double dx = std::max(0.0, std::abs(cx(i) - p.x()) - 0.5 * pitch);
      if (inside) {
        // below the surface: the way out is up through its own column's top, up through a
        // neighbour's lower top (a point just inside a step's foot: the floor beside the wall
        // is 0.1 mm away, its own column's top 10 mm), or sideways past a column lower than p
        const double up = std::max(0.0, top - p.z());
        best = std::min(best, std::sqrt(dx * dx + dy * dy + up * up));
        continue;
      }
      if (top <= kNoPart) continue;
      const double dz = std::max(0.0, p.z() - top);
      const double d = std::sqrt(dx * dx + dy * dy + dz * dz);
      best = std::min(best, d);
    }
  }
  return best;
}

// ---------------------------------------------------------------------------------------------
// CastingModel

double CastingModel::nominal_top(double x, double y) const { return config::nominal_top_z_mm(recipe.geometry, x, y); }

double CastingModel::golden_sdf(const Vec3& p) const {
  const auto& g = recipe.geometry;
  double d = std::numeric_limits<double>::infinity();
  for (const auto& b : g.blocks) {
    const double inside = box_sdf_inside(p, b);
    if (inside <= 0) {
      d = std::min(d, inside);
    } else if (b.top_slope_deg[0] != 0.0 || b.top_slope_deg[1] != 0.0) {
      // outside a tilted top: the exact distance to the polyhedron (the untilted box's distance
      // reads the tilted block's low edge 3.9 mm higher than it is: a ball passing beside it
      // reads gouged up to 0.55 mm; test Casting.GoldenDistanceBesideATiltedBlockIsExact)
      d = std::min(d, tilted_box_outside_distance(p, b));
    } else {
      // outside an axis-aligned box: the distance to the box, exact
      const Vec3 lo(b.min_mm[0], b.min_mm[1], b.min_mm[2]);
      const Vec3 hi(b.max_mm[0], b.max_mm[1], b.max_mm[2]);
      const Vec3 q = (p - p.cwiseMax(lo).cwiseMin(hi));
      d = std::min(d, std::max(inside, q.norm()));
    }
  }
  for (const auto& c : g.cylinders) d = std::min(d, cylinder_sdf(p, c));
  for (const auto& r : g.ring_flashes) d = std::min(d, cylinder_sdf(p, r.cylinder));
  return d;
}

double CastingModel::form_mm(double x, double y) const {
  if (form_amp_mm == 0.0) return 0.0;
  return form_amp_mm * (0.5 * std::sin(form_kx * x + form_phase[0]) * std::cos(form_ky * y + form_phase[1]) +
                        0.5 * std::sin(form_kx * 0.7 * x + form_ky * 0.6 * y + form_phase[2]));
}

void CastingModel::rebuild_surface(int i0, int j0, int i1, int j1) {
  if (i1 < 0) {
    i0 = 0, j0 = 0, i1 = body.nx, j1 = body.ny;
    surface = body;
  }
  i0 = std::max(0, i0), j0 = std::max(0, j0), i1 = std::min(body.nx, i1), j1 = std::min(body.ny, j1);
  for (int j = j0; j < j1; ++j)
    for (int i = i0; i < i1; ++i) surface.at(i, j) = body.at(i, j);
  // Material tops: each material column raises the surface cell it falls in.
  for (const auto& m : materials) {
    const double sx0 = body.x0 + i0 * body.pitch, sx1 = body.x0 + i1 * body.pitch;
    const double sy0 = body.y0 + j0 * body.pitch, sy1 = body.y0 + j1 * body.pitch;
    const int mi0 = std::max(0, static_cast<int>(std::floor((sx0 - m.x0) / m.pitch)));
    const int mi1 = std::min(m.nx, static_cast<int>(std::ceil((sx1 - m.x0) / m.pitch)));
    const int mj0 = std::max(0, static_cast<int>(std::floor((sy0 - m.y0) / m.pitch)));
    const int mj1 = std::min(m.ny, static_cast<int>(std::ceil((sy1 - m.y0) / m.pitch)));
    for (int j = mj0; j < mj1; ++j) {
      const int sj = static_cast<int>(std::floor((m.cy(j) - body.y0) / body.pitch));
      if (sj < j0 || sj >= j1) continue;
      for (int i = mi0; i < mi1; ++i) {
        const auto k = m.index(i, j);
        if (m.z1[k] <= m.z0[k]) continue;
        const int si = static_cast<int>(std::floor((m.cx(i) - body.x0) / body.pitch));
        if (si < i0 || si >= i1) continue;
        float& s = surface.at(si, sj);
        s = std::max(s, m.z1[k]);
      }
    }
  }
  // Cell bounds (separable 3 x 3 max) for the changed cells and their neighbours.
  if (cell_max.size() != surface.h.size()) {
    cell_max.assign(surface.h.size(), kNoPart);
    i0 = std::min(i0, 0), j0 = std::min(j0, 0), i1 = std::max(i1, surface.nx), j1 = std::max(j1, surface.ny);
  }
  {
    const int ci0 = std::max(0, i0 - 1), ci1 = std::min(surface.nx, i1 + 1);
    const int cj0 = std::max(0, j0 - 1), cj1 = std::min(surface.ny, j1 + 1);
    const int rj0 = std::max(0, cj0 - 1), rj1 = std::min(surface.ny, cj1 + 1);
    const auto w = static_cast<std::size_t>(ci1 - ci0);
    std::vector<float> row_max(w * static_cast<std::size_t>(rj1 - rj0));
    for (int j = rj0; j < rj1; ++j)
      for (int i = ci0; i < ci1; ++i) {
        float mx = surface.at(i, j);
        if (i > 0) mx = std::max(mx, surface.at(i - 1, j));
        if (i + 1 < surface.nx) mx = std::max(mx, surface.at(i + 1, j));
        row_max[static_cast<std::size_t>(j - rj0) * w + static_cast<std::size_t>(i - ci0)] = mx;
      }
    for (int j = cj0; j < cj1; ++j)
      for (int i = ci0; i < ci1; ++i) {
        float mx = kNoPart;
        for (int jj = std::max(rj0, j - 1); jj < std::min(rj1, j + 2); ++jj)
          mx = std::max(mx, row_max[static_cast<std::size_t>(jj - rj0) * w + static_cast<std::size_t>(i - ci0)]);
        cell_max[static_cast<std::size_t>(j) * static_cast<std::size_t>(surface.nx) + static_cast<std::size_t>(i)] = mx;
      }
  }
  zmax_cache = 0.0;
  for (float v : surface.h) zmax_cache = std::max(zmax_cache, static_cast<double>(v));
  zmax_cache += 0.01;
  tiles_x = (surface.nx + kTile - 1) / kTile;
  tiles_y = (surface.ny + kTile - 1) / kTile;
  if (tile_max.size() != static_cast<std::size_t>(tiles_x) * static_cast<std::size_t>(tiles_y))
    tile_max.assign(static_cast<std::size_t>(tiles_x) * static_cast<std::size_t>(tiles_y), kNoPart);
  const int tx0 = std::max(0, (i0 - 1) / kTile), tx1 = std::min(tiles_x, (i1 + 1) / kTile + 1);
  const int ty0 = std::max(0, (j0 - 1) / kTile), ty1 = std::min(tiles_y, (j1 + 1) / kTile + 1);
  for (int ty = ty0; ty < ty1; ++ty)
    for (int tx = tx0; tx < tx1; ++tx) {
      float mx = kNoPart;
      for (int j = std::max(0, ty * kTile - 1); j < std::min(surface.ny, ty * kTile + kTile + 1); ++j)
        for (int i = std::max(0, tx * kTile - 1); i < std::min(surface.nx, tx * kTile + kTile + 1); ++i)
          mx = std::max(mx, surface.at(i, j));
      tile_max[static_cast<std::size_t>(ty) * static_cast<std::size_t>(tiles_x) + static_cast<std::size_t>(tx)] = mx;
    }
}

std::vector<RegionTruth> CastingModel::truth() const {
  std::vector<RegionTruth> out;
  for (const auto& r : recipe.regions) {
    RegionTruth t;
    t.name = r.name;
    t.type = r.type;
    out.push_back(t);
  }
  for (const auto& m : materials) {
    if (m.region_index < 0) continue;
    auto& t = out[static_cast<std::size_t>(m.region_index)];
    t.radial = m.radial;
    if (m.radial) t.axis_center_mm = Vec3(m.axis_center.x(), m.axis_center.y(), 0.0);
    const double area = m.pitch * m.pitch;
    double volume = 0, height = 0;
    for (int j = 0; j < m.ny; ++j)
      for (int i = 0; i < m.nx; ++i) {
        const auto k = m.index(i, j);
        if (m.z1[k] <= m.z0[k]) continue;
        volume += static_cast<double>(m.z1[k] - m.z0[k]) * area;
        if (m.radial) {
          height = std::max(height, std::hypot(m.cx(i) - m.axis_center.x(), m.cy(j) - m.axis_center.y()) +
                                        0.5 * m.pitch - m.base_radius_mm);
        } else {
          const double top = own_top(m.cx(i), m.cy(j));
          height = std::max(height, static_cast<double>(m.z1[k]) - (std::isnan(top) ? 0.0 : top));
        }
      }
    t.volume_mm3 += volume;
    t.max_height_mm = std::max(t.max_height_mm, height);
  }
  return out;
}

// ---------------------------------------------------------------------------------------------
// Casting

Casting::Casting(std::unique_ptr<CastingModel> model) : model_(std::move(model)) {}
Casting::Casting(const Casting& other) : model_(std::make_unique<CastingModel>(*other.model_)) {}
Casting& Casting::operator=(const Casting& other) {
  if (this != &other) model_ = std::make_unique<CastingModel>(*other.model_);
  return *this;
}
Casting::Casting(Casting&&) noexcept = default;
Casting& Casting::operator=(Casting&&) noexcept = default;
Casting::~Casting() = default;

std::uint64_t Casting::seed() const { return model_->seed; }
const std::string& Casting::part_id() const { return model_->recipe.id; }
const Transform& Casting::T_base_part() const { return model_->T_base_part; }
void Casting::set_T_base_part(const Transform& T_base_part) { model_->T_base_part = T_base_part; }
std::vector<RegionTruth> Casting::material() const { return model_->truth(); }
double Casting::surface_z_mm(double x_mm, double y_mm) const {
  const double z = model_->surface.bilinear(x_mm, y_mm);
  return z <= kNoPart ? std::nan("") : z;
}
std::pair<Vec3, Vec3> Casting::bounds_part_mm() const {
  const auto& s = model_->surface;
  float top = 0;
  for (float v : s.h) top = std::max(top, v);
  return {Vec3(s.x0, s.y0, 0.0), Vec3(s.x0 + s.nx * s.pitch, s.y0 + s.ny * s.pitch, top)};
}
double Casting::distance_to_surface_mm(const Vec3& p_part) const { return model_->surface.distance(p_part); }
double Casting::rms_distance_to_surface_mm(const std::vector<Eigen::Vector3f>& points, const Transform& T_part_points,
                                           std::size_t stride) const {
  double sum = 0.0;
  std::size_t n = 0;
  for (std::size_t k = 0; k < points.size(); k += std::max<std::size_t>(1, stride), ++n) {
    const double d = distance_to_surface_mm(T_part_points * points[k].cast<double>());
    sum += d * d;
  }
  return n > 0 ? std::sqrt(sum / static_cast<double>(n)) : 0.0;
}
double Casting::distance_to_golden_mm(const Vec3& p_part) const { return model_->nominal.distance(p_part); }
double Casting::distance_to_body_mm(const Vec3& p_part) const { return model_->body.distance(p_part); }
double Casting::golden_top_z_mm(double x_mm, double y_mm) const { return model_->nominal_top(x_mm, y_mm); }
void Casting::take_off_fixture() { model_->on_fixture = false; }
bool Casting::on_fixture() const { return model_->on_fixture; }

void Casting::remove_all_material() {
  for (auto& m : model_->materials) m.z1 = m.z0;
  model_->rebuild_surface();
}
double Casting::golden_sdf_mm(const Vec3& p_part) const { return model_->golden_sdf(p_part); }
double Casting::form_deviation_mm(double x_mm, double y_mm) const { return model_->form_mm(x_mm, y_mm); }

std::vector<SurfacePoint> Casting::sample_golden_surface(double spacing_mm) const {
  const auto& f = model_->nominal;
  std::vector<SurfacePoint> out;
  const int step = std::max(1, static_cast<int>(std::lround(spacing_mm / f.pitch)));
  for (int j = 1; j + 1 < f.ny; j += step)
    for (int i = 1; i + 1 < f.nx; i += step) {
      const float h = f.at(i, j);
      if (h <= kNoPart) continue;
      // top
      const double x = f.cx(i), y = f.cy(j);
      const double gx = (f.at(i + 1, j) - f.at(i - 1, j)) / (2 * f.pitch);
      const double gy = (f.at(i, j + 1) - f.at(i, j - 1)) / (2 * f.pitch);
      if (std::abs(gx) < 2.0 && std::abs(gy) < 2.0) {
        Eigen::Vector3f n(static_cast<float>(-gx), static_cast<float>(-gy), 1.0f);
        out.push_back({Eigen::Vector3f(static_cast<float>(x), static_cast<float>(y), h), n.normalized()});
      }
    }
  // walls: where the height drops by more than a cell between neighbours (x and y). The height
  // field draws a curved or slanted wall as a staircase; the wall's normal is not the step's
  // (±x or ±y) but the direction away from the high side over a disc of about 1 mm around
  // the crossing (the centroid of a half-disc lies along the true normal).
  const int reach = std::max(2, static_cast<int>(std::lround(1.0 / f.pitch)));
  auto wall_normal = [&](double x, double y, float lo, float hi) {
    Eigen::Vector2d sum = Eigen::Vector2d::Zero();
    const int ic = static_cast<int>(std::floor((x - f.x0) / f.pitch)), jc = static_cast<int>(std::floor((y - f.y0) / f.pitch));
    for (int dj = -reach; dj <= reach; ++dj)
      for (int di = -reach; di <= reach; ++di) {
        const int i = ic + di, j = jc + dj;
        if (i < 0 || j < 0 || i >= f.nx || j >= f.ny) continue;
        const Eigen::Vector2d d(f.cx(i) - x, f.cy(j) - y);
        if (d.norm() > reach * f.pitch) continue;
        const double w = std::clamp((static_cast<double>(f.at(i, j)) - lo) / std::max(1e-6, static_cast<double>(hi - lo)), 0.0, 1.0);
        sum -= w * d;
      }
    return sum;
  };
  auto add_wall = [&](double x, double y, float lo, float hi, const Eigen::Vector2d& step_normal) {
    Eigen::Vector2d n2 = wall_normal(x, y, lo, hi);
    if (n2.norm() < 1e-9 || n2.dot(step_normal) <= 0.0) n2 = step_normal;
    n2.normalize();
    const Eigen::Vector3f n(static_cast<float>(n2.x()), static_cast<float>(n2.y()), 0.0f);
    for (float z = lo + static_cast<float>(spacing_mm) * 0.5f; z < hi; z += static_cast<float>(spacing_mm))
      out.push_back({Eigen::Vector3f(static_cast<float>(x), static_cast<float>(y), z), n});
  };
  for (int j = 0; j < f.ny; j += step)
    for (int i = 0; i + 1 < f.nx; ++i) {
      const float a = f.at(i, j), b = f.at(i + 1, j);
      const float lo = std::max(std::min(a, b), 0.0f), hi = std::max(a, b);
      if (hi - lo < 4 * f.pitch) continue;
      add_wall(f.x0 + (i + 1) * f.pitch, f.cy(j), lo, hi, Eigen::Vector2d(a > b ? 1.0 : -1.0, 0.0));
    }
  for (int i = 0; i < f.nx; i += step)
    for (int j = 0; j + 1 < f.ny; ++j) {
      const float a = f.at(i, j), b = f.at(i, j + 1);
      const float lo = std::max(std::min(a, b), 0.0f), hi = std::max(a, b);
      if (hi - lo < 4 * f.pitch) continue;
      add_wall(f.cx(i), f.y0 + (j + 1) * f.pitch, lo, hi, Eigen::Vector2d(0.0, a > b ? 1.0 : -1.0));
    }
  return out;
}

namespace {

std::unique_ptr<CastingModel> build(const config::PartRecipe& recipe, std::uint64_t seed, bool vary, bool golden) {
  const auto& g = recipe.geometry;
  if (!g.present || g.blocks.empty())
    throw UserError(recipe.source.string() +
                    ": the part recipe has no [geometry] table with [[geometry.blocks]]; the simulator needs it to "
                    "build the casting (see docs/simulator.md)");
  auto m = std::make_unique<CastingModel>();
  m->recipe = recipe;
  m->seed = seed;
  m->golden = golden;
  Rng rng(seed, 0x5eed);
  // Placement on the fixture.
  const auto& fx = recipe.fixture;
  const double tol = vary ? g.variation.placement_tolerance_mm : 0.0;
  const double tol_rad = vary ? deg_to_rad(g.variation.placement_tolerance_deg) : 0.0;
  const double dx = rng.uniform(-1, 1) * tol, dy = rng.uniform(-1, 1) * tol, dyaw = rng.uniform(-1, 1) * tol_rad;
  Transform T = Transform::Identity();
  T.linear() = (Eigen::AngleAxisd(deg_to_rad(fx.rotation_deg[2]) + dyaw, Vec3::UnitZ()) *
                Eigen::AngleAxisd(deg_to_rad(fx.rotation_deg[1]), Vec3::UnitY()) *
                Eigen::AngleAxisd(deg_to_rad(fx.rotation_deg[0]), Vec3::UnitX()))
                   .toRotationMatrix();
  T.translation() = Vec3(fx.position_mm[0] + dx, fx.position_mm[1] + dy, fx.position_mm[2]);
  // Optional small tilts about the part's x and y (a chip or burr under a locator), from a
  // stream of their own so that every other draw (and so every casting without tilt) stays
  // the same. Applied below, once the part's footprint is known.
  double droll = 0.0, dpitch = 0.0;
  if (vary && g.variation.placement_tilt_deg > 0.0) {
    Rng tr(seed, 0x7117);
    droll = tr.uniform(-1, 1) * deg_to_rad(g.variation.placement_tilt_deg);
    dpitch = tr.uniform(-1, 1) * deg_to_rad(g.variation.placement_tilt_deg);
  }

  // Bounds of the body and its features.
  Vec3 lo(1e9, 1e9, 0), hi(-1e9, -1e9, 0);
  auto grow = [&](double x0, double y0, double x1, double y1) {
    lo.x() = std::min(lo.x(), x0), lo.y() = std::min(lo.y(), y0), hi.x() = std::max(hi.x(), x1),
    hi.y() = std::max(hi.y(), y1);
  };
  for (const auto& b : g.blocks) grow(b.min_mm[0], b.min_mm[1], b.max_mm[0], b.max_mm[1]);
  for (const auto& c : g.cylinders)
    grow(c.center_mm[0] - c.radius_mm, c.center_mm[1] - c.radius_mm, c.center_mm[0] + c.radius_mm,
         c.center_mm[1] + c.radius_mm);
  for (const auto& r : g.ring_flashes) {
    const double R = r.cylinder.radius_mm + r.extent_mm.max + r.edge_irregularity_mm + 1.0;
    grow(r.cylinder.center_mm[0] - R, r.cylinder.center_mm[1] - R, r.cylinder.center_mm[0] + R,
         r.cylinder.center_mm[1] + R);
  }
  if (droll != 0.0 || dpitch != 0.0) {
    // Tilted about the part's bottom centre, then lifted so that the lowest bottom corner of
    // the body's blocks rests where the flat part's bottom was: the rest is above it.
    const Vec3 pivot(0.5 * (lo.x() + hi.x()), 0.5 * (lo.y() + hi.y()), 0.0);
    const Eigen::Matrix3d R0 = T.linear();
    const Eigen::Matrix3d R = R0 * (Eigen::AngleAxisd(dpitch, Vec3::UnitY()) * Eigen::AngleAxisd(droll, Vec3::UnitX()))
                                       .toRotationMatrix();
    double low = std::numeric_limits<double>::infinity(), low0 = low;
    for (const auto& b : g.blocks)
      for (double x : {b.min_mm[0], b.max_mm[0]})
        for (double y : {b.min_mm[1], b.max_mm[1]}) {
          const Vec3 p = Vec3(x, y, b.min_mm[2]) - pivot;
          low = std::min(low, (R * p).z());
          low0 = std::min(low0, (R0 * p).z());
        }
    T.translation() += R0 * pivot - R * pivot + Vec3(0.0, 0.0, low0 - low);
    T.linear() = R;
  }
  m->T_base_part = T;
  m->nominal = make_field(lo, hi, g.surface_grid_mm);
  auto& nom = m->nominal;
  for (int j = 0; j < nom.ny; ++j)
    for (int i = 0; i < nom.nx; ++i) {
      const double z = m->nominal_top(nom.cx(i), nom.cy(j));
      if (!std::isnan(z)) nom.at(i, j) = static_cast<float>(z);
    }
  // This casting's body: nominal + a smooth form deviation.
  m->body = nom;
  const double amp = (vary && !golden) ? g.variation.form_deviation_mm : 0.0;
  if (amp > 0) {
    std::array<double, 4> ph{};
    for (auto& p : ph) p = rng.uniform(0, 2 * std::numbers::pi);
    m->form_amp_mm = amp;
    m->form_phase = {ph[0], ph[1], ph[2]};
    m->form_kx = 2 * std::numbers::pi / rng.uniform(90.0, 200.0);
    m->form_ky = 2 * std::numbers::pi / rng.uniform(90.0, 200.0);
    for (int j = 0; j < nom.ny; ++j)
      for (int i = 0; i < nom.nx; ++i) {
        float& h = m->body.at(i, j);
        if (h <= kNoPart) continue;
        h = static_cast<float>(h + m->form_mm(nom.cx(i), nom.cy(j)));
      }
  } else {
    for (int k = 0; k < 4; ++k) (void)rng.uniform();
  }

  // Removable material (skipped for the golden template, but the draws still happen so
  // that the scene of a golden template matches the casting of the same seed).
  const double mp = g.material_grid_mm;
  for (std::size_t fi = 0; fi < g.ring_flashes.size(); ++fi) {
    const auto& f = g.ring_flashes[fi];
    Rng fr(seed, 0x1000 + fi);
    const double t = draw(fr, f.thickness_mm, vary), e = draw(fr, f.extent_mm, vary);
    const Wobble wob(fr, vary);
    const double irr = vary ? f.edge_irregularity_mm : 0.0;
    // gaps: 1..3 arcs summing to gap_fraction of the circumference
    const int ngaps = vary && f.gap_fraction > 0 ? 1 + static_cast<int>(fr.uniform() * 3) : 0;
    std::vector<std::pair<double, double>> gaps;
    for (int k = 0; k < ngaps; ++k) {
      const double start = fr.uniform(0, 2 * std::numbers::pi);
      gaps.emplace_back(start, f.gap_fraction * 2 * std::numbers::pi / ngaps);
    }
    if (golden) continue;
    const double R = f.cylinder.radius_mm, cx = f.cylinder.center_mm[0], cy = f.cylinder.center_mm[1];
    const double Rmax = R + e + irr + mp;
    auto mat = make_material(f.region, recipe, cx - Rmax, cy - Rmax, cx + Rmax, cy + Rmax, mp);
    mat.radial = true;
    mat.axis_center = {cx, cy};
    mat.base_radius_mm = R;
    for (int j = 0; j < mat.ny; ++j)
      for (int i = 0; i < mat.nx; ++i) {
        const double x = mat.cx(i) - cx, y = mat.cy(j) - cy;
        const double r = std::hypot(x, y);
        if (r <= R) continue;
        const double a = std::atan2(y, x);
        if (r > R + e + irr * wob(a, 1.0)) continue;
        bool in_gap = false;
        for (const auto& [s, w] : gaps) {
          double d = std::remainder(a - s, 2 * std::numbers::pi);
          if (d >= 0 && d < w) in_gap = true;
        }
        if (in_gap) continue;
        const double z0 = f.parting_z_mm - 0.5 * t, z1 = f.parting_z_mm + 0.5 * t;
        const double floor_z = m->own_top(mat.cx(i), mat.cy(j));
        const auto k = mat.index(i, j);
        mat.z0[k] = static_cast<float>(std::isnan(floor_z) ? z0 : std::max(z0, floor_z));
        mat.z1[k] = static_cast<float>(z1);
      }
    m->materials.push_back(std::move(mat));
  }
  for (std::size_t fi = 0; fi < g.risers.size(); ++fi) {
    const auto& f = g.risers[fi];
    Rng fr(seed, 0x2000 + fi);
    const double d = draw(fr, f.diameter_mm, vary), h = draw(fr, f.height_mm, vary);
    const double tilt = deg_to_rad(draw(fr, f.top_tilt_deg, vary));
    const double tilt_dir = fr.uniform(0, 2 * std::numbers::pi);
    const double rough = vary ? f.roughness_mm : 0.0;
    const std::uint64_t noise_seed = fr.next();
    if (golden) continue;
    const double cx = f.center_mm[0], cy = f.center_mm[1], r = 0.5 * d;
    const double base = m->own_top(cx, cy);
    auto mat = make_material(f.region, recipe, cx - r - mp, cy - r - mp, cx + r + mp, cy + r + mp, mp);
    for (int j = 0; j < mat.ny; ++j)
      for (int i = 0; i < mat.nx; ++i) {
        const double x = mat.cx(i), y = mat.cy(j);
        if (std::hypot(x - cx, y - cy) > r) continue;
        const double floor_z = m->own_top(x, y);
        if (std::isnan(floor_z)) continue;
        double top = base + h + std::tan(tilt) * ((x - cx) * std::cos(tilt_dir) + (y - cy) * std::sin(tilt_dir));
        if (rough > 0)
          top += rough * (0.6 * value_noise(noise_seed, x, y, 2.0) + 0.4 * value_noise(noise_seed + 1, x, y, 0.7));
        const auto k = mat.index(i, j);
        mat.z0[k] = static_cast<float>(floor_z);
        mat.z1[k] = static_cast<float>(std::max(top, floor_z));
      }
    m->materials.push_back(std::move(mat));
  }
  for (std::size_t fi = 0; fi < g.straight_flashes.size(); ++fi) {
    const auto& f = g.straight_flashes[fi];
    Rng fr(seed, 0x3000 + fi);
    const double L = draw(fr, f.length_mm, vary), h = draw(fr, f.height_mm, vary), t = draw(fr, f.thickness_mm, vary);
    const Wobble wob(fr, vary);
    const double irr = vary ? std::min(f.edge_irregularity_mm, 0.8 * h) : 0.0;
    if (golden) continue;
    const double a = deg_to_rad(f.direction_deg);
    const Eigen::Vector2d u(std::cos(a), std::sin(a)), n(-u.y(), u.x()), s(f.start_mm[0], f.start_mm[1]);
    const Eigen::Vector2d e = s + L * u;
    const double pad = t + mp;
    auto mat = make_material(f.region, recipe, std::min(s.x(), e.x()) - pad, std::min(s.y(), e.y()) - pad,
                             std::max(s.x(), e.x()) + pad, std::max(s.y(), e.y()) + pad, mp);
    for (int j = 0; j < mat.ny; ++j)
      for (int i = 0; i < mat.nx; ++i) {
        const Eigen::Vector2d p(mat.cx(i), mat.cy(j));
        const double along = (p - s).dot(u), across = (p - s).dot(n);
        if (along < 0 || along > L || std::abs(across) > 0.5 * t) continue;
        const double floor_z = m->own_top(p.x(), p.y());
        if (std::isnan(floor_z)) continue;
        const double top = floor_z + h + irr * wob(along / 40.0, 1.0);
        const auto k = mat.index(i, j);
        mat.z0[k] = static_cast<float>(floor_z);
        mat.z1[k] = static_cast<float>(top);
      }
    m->materials.push_back(std::move(mat));
  }
  m->rebuild_surface();

  // Scene: clamps at the ends of the nominal part, clutter on the table (base frame).
  const Vec3 c_nom(fx.position_mm[0] + 0.5 * (lo.x() + hi.x()), fx.position_mm[1] + 0.5 * (lo.y() + hi.y()), 0.0);
  const double hx = 0.5 * (hi.x() - lo.x()), hy = 0.5 * (hi.y() - lo.y());
  for (int k = 0; k < g.clamps; ++k) {
    const double side = (k % 2 == 0) ? -1.0 : 1.0;
    const double off = (k / 2 % 2 == 0) ? 0.0 : (k / 2 == 1 ? 0.5 : -0.5) * hy;
    Box b;
    const Vec3 c = c_nom + Vec3(side * (hx + 22.0), off, 0.0);
    b.min_mm = c + Vec3(-12.0, -18.0, 0.0);
    b.max_mm = c + Vec3(12.0, 18.0, 28.0);
    m->scene.push_back(b);
  }
  Rng cr(seed, 0xC1A77E5);
  for (int k = 0; k < g.clutter_items; ++k) {
    for (int attempt = 0; attempt < 50; ++attempt) {
      // Drawn one per statement, last coordinate first: the order gcc evaluates
      // Vec3(cr.uniform(..), cr.uniform(..), cr.uniform(..)) in, so seeds keep their scenes and
      // every compiler builds the same one (argument order is unspecified in C++).
      const double sz = cr.uniform(2, 18), sy = cr.uniform(8, 40), sx = cr.uniform(8, 40);
      const Vec3 size(sx, sy, sz);
      const double cy = cr.uniform(-190, 190), cx = cr.uniform(-250, 250);
      const Vec3 c(c_nom.x() + cx, c_nom.y() + cy, 0.0);
      if (std::abs(c.x() - c_nom.x()) < hx + 45 + size.x() && std::abs(c.y() - c_nom.y()) < hy + 25 + size.y()) continue;
      m->scene.push_back(Box{c - Vec3(size.x() / 2, size.y() / 2, 0), c + Vec3(size.x() / 2, size.y() / 2, size.z())});
      break;
    }
  }
  return m;
}

}  // namespace

Casting Casting::make(const config::PartRecipe& recipe, std::uint64_t seed, const CastingOptions& options) {
  return Casting(build(recipe, seed, options.vary, false));
}

Casting Casting::golden(const config::PartRecipe& recipe, std::uint64_t seed) {
  return Casting(build(recipe, seed, true, true));
}

config::PartRecipe mirrored_in_x(const config::PartRecipe& recipe) {
  config::PartRecipe mirrored = recipe;
  auto& g = mirrored.geometry;
  auto flip = [](std::array<double, 2>& c) { c[0] = -c[0]; };
  for (auto& b : g.blocks) {
    const double lo = b.min_mm[0];
    b.min_mm[0] = -b.max_mm[0];
    b.max_mm[0] = -lo;
    b.top_slope_deg[0] = -b.top_slope_deg[0];
  }
  for (auto& c : g.cylinders) flip(c.center_mm);
  for (auto& r : g.ring_flashes) flip(r.cylinder.center_mm);
  for (auto& r : g.risers) flip(r.center_mm);
  for (auto& f : g.straight_flashes) {
    flip(f.start_mm);
    f.direction_deg = 180.0 - f.direction_deg;
  }
  return mirrored;
}

}  // namespace fettle::sim
