#pragma once
// Private: the casting's representation (sim/src only).
//  - body: a height field of the body's top in the part frame (surface_grid_mm pitch);
//    golden = nominal, casting = nominal + form deviation (cut by grinding from the top).
//  - material: per feature (flash, riser) a dexel grid along part z at material_grid_mm,
//    one span [z0, z1] per column (empty when z1 <= z0).
//  - surface: what the scanner sees, max(body, material tops), with per-tile and per-cell
//    upper bounds for fast ray marching.
//  - the golden body's exact solid as a CSG signed distance (gouge depths).
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include "fettle/config/part.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/sim/sim.hpp"

namespace fettle::sim {

inline constexpr float kNoPart = -1.0f;  ///< height of cells without part (below the table)

struct HeightField {
  double x0 = 0, y0 = 0, pitch = 0.1;  ///< cell (i, j) centre: (x0 + (i + .5) p, y0 + (j + .5) p)
  int nx = 0, ny = 0;
  std::vector<float> h;

  [[nodiscard]] float at(int i, int j) const { return h[static_cast<std::size_t>(j) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(i)]; }
  float& at(int i, int j) { return h[static_cast<std::size_t>(j) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(i)]; }
  [[nodiscard]] double cx(int i) const { return x0 + (i + 0.5) * pitch; }
  [[nodiscard]] double cy(int j) const { return y0 + (j + 0.5) * pitch; }
  /// Bilinear height between cell centres (kNoPart outside).
  [[nodiscard]] double bilinear(double x, double y) const;
  /// Gradient (dh/dx, dh/dy) at (x, y) by central differences of the bilinear surface.
  [[nodiscard]] Eigen::Vector2d gradient(double x, double y) const;
  /// Distance from p to the 2.5D solid below the field (vertical inside).
  [[nodiscard]] double distance(const Vec3& p, double max_search_mm = 3.0) const;
};

/// Removable material of one feature.
struct Material {
  std::string region;
  int region_index = -1;  ///< index in recipe.regions, -1 = none
  bool radial = false;    ///< ring/circle flash: height measured radially
  Eigen::Vector2d axis_center{0, 0};
  double base_radius_mm = 0.0;  ///< radial: the golden cylinder's radius
  double x0 = 0, y0 = 0, pitch = 0.05;
  int nx = 0, ny = 0;
  std::vector<float> z0, z1;

  [[nodiscard]] std::size_t index(int i, int j) const { return static_cast<std::size_t>(j) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(i); }
  [[nodiscard]] double cx(int i) const { return x0 + (i + 0.5) * pitch; }
  [[nodiscard]] double cy(int j) const { return y0 + (j + 0.5) * pitch; }
};

struct Box {
  Vec3 min_mm, max_mm;  ///< base frame, axis aligned
};

class CastingModel {
 public:
  config::PartRecipe recipe;
  std::uint64_t seed = 0;
  bool golden = false;
  Transform T_base_part = Transform::Identity();
  bool on_fixture = true;  ///< false: the scanner sees the scene without the part
  HeightField nominal;  ///< golden body top
  HeightField body;     ///< this casting's body top
  HeightField surface;  ///< body + material tops (what is seen)
  std::vector<float> tile_max;  ///< per kTile x kTile cells of `surface` (with a 1-cell border)
  std::vector<float> cell_max;  ///< per cell of `surface`: max of its 3 x 3 neighbourhood, which bounds
                                ///< the bilinear surface over the cell (the ray march skips by it)
  int tiles_x = 0, tiles_y = 0;
  double zmax_cache = 0.0;  ///< highest surface point
  std::vector<Material> materials;
  std::vector<Box> scene;  ///< clamps and clutter, base frame
  std::vector<Gouge> gouges;  ///< gouges so far

  static constexpr int kTile = 16;

  /// Golden body top at (x, y) from the primitives; NaN off the body.
  [[nodiscard]] double nominal_top(double x, double y) const;
  /// This casting's own top: the nominal with its form deviation (NaN off the part). Flash and
  /// risers are cast with the body and stand on it: on the nominal, a riser over a face the form
  /// deviation lowers floated 0.5 mm above it, and a flat wheel cutting at the face took it all.
  [[nodiscard]] double own_top(double x, double y) const { return nominal_top(x, y) + form_mm(x, y); }
  [[nodiscard]] double golden_sdf(const Vec3& p) const;
  /// This casting's smooth form deviation at (x, y): how far its body's top stands over the
  /// nominal's (0 for a golden casting).
  [[nodiscard]] double form_mm(double x, double y) const;
  /// This casting's own body as a signed distance: the golden solid moved up by the form
  /// deviation at each (x, y) (exact on top faces; walls keep their place, their top edges move).
  [[nodiscard]] double body_sdf(const Vec3& p) const { return golden_sdf(p - Vec3(0.0, 0.0, form_mm(p.x(), p.y()))); }
  /// The form deviation's draw: amplitude, wave numbers and phases (amplitude 0: none).
  double form_amp_mm = 0.0, form_kx = 0.0, form_ky = 0.0;
  std::array<double, 3> form_phase{};
  /// Rebuilds `surface`, the tile and the cell maxima for cells [i0, i1) x [j0, j1) (all when empty).
  void rebuild_surface(int i0 = 0, int j0 = 0, int i1 = -1, int j1 = -1);
  [[nodiscard]] std::vector<RegionTruth> truth() const;
};

/// Deterministic counter-based random numbers (no dependence on threads).
inline std::uint64_t mix64(std::uint64_t x) {
  x += 0x9e3779b97f4a7c15ULL;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31);
}

struct Rng {
  std::uint64_t state;
  explicit Rng(std::uint64_t s) : state(mix64(s)) {}
  Rng(std::uint64_t a, std::uint64_t b, std::uint64_t c = 0) : state(mix64(mix64(mix64(a) ^ b) ^ c)) {}
  std::uint64_t next() {
    state += 0x9e3779b97f4a7c15ULL;
    return mix64(state);
  }
  double uniform() { return static_cast<double>(next() >> 11) * (1.0 / 9007199254740992.0); }
  double uniform(double a, double b) { return a + (b - a) * uniform(); }
  double gaussian() {
    const double u1 = std::max(uniform(), 1e-300);
    const double u2 = uniform();
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * 3.14159265358979323846 * u2);
  }
};

/// Uniform [0, 1) per 4 mm cell of space: which surface patches never return light.
inline double value_noise_cell(std::uint64_t seed, double x, double y, double z) {
  auto q = [](double v) { return static_cast<std::uint64_t>(static_cast<std::int64_t>(std::floor(v / 4.0))); };
  Rng r(seed ^ 0xA11CE, q(x) * 0x9E3779B1ULL ^ q(y), q(z));
  return r.uniform();
}

}  // namespace fettle::sim
