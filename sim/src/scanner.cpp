// The structured-light scanner: pinhole + distortion camera on a slide, ray casting the
// scene (table plane, clamps, clutter, the casting's height field), then the noise model.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <memory>
#include <thread>

#include "casting_model.hpp"
#include "fettle/config/calibration.hpp"

namespace fettle::sim {

// ---------------------------------------------------------------------------------------------
// Intrinsics

Eigen::Vector2d CameraIntrinsics::project(const Vec3& p) const {
  const double x = p.x() / p.z(), y = p.y() / p.z();
  const double r2 = x * x + y * y;
  const double radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2;
  const double xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x);
  const double yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y;
  return {fx * xd + cx, fy * yd + cy};
}

Vec3 CameraIntrinsics::ray(double u, double v) const {
  const double xd = (u - cx) / fx, yd = (v - cy) / fy;
  double x = xd, y = yd;
  for (int it = 0; it < 20; ++it) {
    const double r2 = x * x + y * y;
    const double radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2;
    const double dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x);
    const double dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y;
    const double nx = (xd - dx) / radial, ny = (yd - dy) / radial;
    const bool done = std::abs(nx - x) < 1e-12 && std::abs(ny - y) < 1e-12;
    x = nx, y = ny;
    if (done) break;
  }
  return {x, y, 1.0};
}

CameraIntrinsics CameraIntrinsics::scaled(int new_width, int new_height) const {
  CameraIntrinsics c = *this;
  const double sx = static_cast<double>(new_width) / width, sy = static_cast<double>(new_height) / height;
  c.width = new_width, c.height = new_height;
  c.fx *= sx, c.fy *= sy;
  c.cx = (cx + 0.5) * sx - 0.5, c.cy = (cy + 0.5) * sy - 0.5;
  return c;
}

Transform ScannerConfig::default_T_slide_camera() {
  Transform T = Transform::Identity();
  T.linear() = Eigen::Vector3d(1.0, -1.0, -1.0).asDiagonal();
  return T;
}

Transform ScannerConfig::T_base_slide(double s) const {
  Transform T = Transform::Identity();
  T.translation() = slide_origin_mm + s * slide_axis.normalized();
  return T;
}

Transform ScannerConfig::T_base_camera(double s) const { return T_base_slide(s) * T_slide_camera; }

void ScannerConfig::place_in_cell(const config::CellConfig& cell) {
  photo_positions_mm = cell.slide.photo_positions_mm;
  if (cell.calibration.file.empty()) return;
  const auto cal = config::load_calibration(cell.calibration.file);
  if (!cal.T_base_camera) return;
  // The calibration holds the camera pose with the slide at 0 mm; the slide moves along base x
  // (as fettled's T_base_camera_at does).
  slide_origin_mm = cal.T_base_camera->translation();
  slide_axis = Vec3(1.0, 0.0, 0.0);
  T_slide_camera = Transform::Identity();
  T_slide_camera.linear() = cal.T_base_camera->linear();
}

// ---------------------------------------------------------------------------------------------
// Ray casting

namespace {

/// Ray hits are located to this depth (mm), far below the noise and the C16 step (0.02 mm).
constexpr double kHitTolerance_mm = 2e-4;

struct Hit {
  double t = std::numeric_limits<double>::infinity();  ///< along (x, y, 1) camera ray = depth Z
  Vec3 normal_base{0, 0, 1};
  Vec3 point_base{0, 0, 0};
};

/// A ray o + t d with the reciprocals of its direction (divisions are the ray caster's cost).
struct Ray {
  Vec3 o, d, inv;  ///< inv = 1 / d per axis (0 where |d| < 1e-15: that axis is never crossed)
  Ray(const Vec3& origin, const Vec3& direction) : o(origin), d(direction) {
    for (int a = 0; a < 3; ++a) inv[a] = std::abs(d[a]) > 1e-15 ? 1.0 / d[a] : 0.0;
  }
};

/// 2D DDA over a grid of cells of size `cell` with origin (gx, gy), visiting cells the ray
/// passes between t0 and t1. visit(i, j, ta, tb) returns true to stop.
template <class Visit>
void dda(double gx, double gy, double cell, double inv_cell, int nx, int ny, const Ray& r, double t0, double t1,
         Visit&& visit) {
  const Vec3& o = r.o;
  const Vec3& d = r.d;
  const double px = o.x() + t0 * d.x(), py = o.y() + t0 * d.y();
  int i = std::clamp(static_cast<int>(std::floor((px - gx) * inv_cell)), 0, nx - 1);
  int j = std::clamp(static_cast<int>(std::floor((py - gy) * inv_cell)), 0, ny - 1);
  const int si = d.x() > 0 ? 1 : -1, sj = d.y() > 0 ? 1 : -1;
  const double inf = std::numeric_limits<double>::infinity();
  const double dtx = r.inv.x() != 0.0 ? cell * std::abs(r.inv.x()) : inf;
  const double dty = r.inv.y() != 0.0 ? cell * std::abs(r.inv.y()) : inf;
  double tx = inf, ty = inf;
  if (r.inv.x() != 0.0) tx = (gx + (i + (si > 0 ? 1 : 0)) * cell - o.x()) * r.inv.x();
  if (r.inv.y() != 0.0) ty = (gy + (j + (sj > 0 ? 1 : 0)) * cell - o.y()) * r.inv.y();
  double t = t0;
  while (t < t1) {
    const double tn = std::min({tx, ty, t1});
    if (visit(i, j, t, tn)) return;
    t = tn;
    if (tx <= ty) {
      i += si;
      tx += dtx;
    } else {
      j += sj;
      ty += dty;
    }
    if (i < 0 || j < 0 || i >= nx || j >= ny) return;
  }
}

/// The surface seen by rays in the part frame, with the bounds the march skips by.
struct FieldView {
  const CastingModel& m;
  double x0, y0, pitch, inv_pitch;
  int nx, ny;
  const float* h;
  explicit FieldView(const CastingModel& model)
      : m(model), x0(model.surface.x0), y0(model.surface.y0), pitch(model.surface.pitch),
        inv_pitch(1.0 / model.surface.pitch), nx(model.surface.nx), ny(model.surface.ny), h(model.surface.h.data()) {}
  /// HeightField::bilinear with the division by the pitch hoisted (same surface).
  [[nodiscard]] double bilinear(double x, double y) const {
    const double u = (x - x0) * inv_pitch - 0.5, v = (y - y0) * inv_pitch - 0.5;
    if (!(u >= 0) || !(v >= 0) || u >= nx - 1 || v >= ny - 1) return kNoPart;
    const int i = static_cast<int>(u), j = static_cast<int>(v);
    const double tu = u - i, tv = v - j;
    const float* r0 = h + static_cast<std::size_t>(j) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(i);
    const float* r1 = r0 + nx;
    return (1 - tv) * ((1 - tu) * r0[0] + tu * r0[1]) + tv * ((1 - tu) * r1[0] + tu * r1[1]);
  }
};

/// Intersects a part-frame ray with the surface height field: a DDA over tiles (skipped
/// when the ray stays above their maximum), then over cells (skipped the same way with the
/// cell's bound `cell_max`), then bisection on the bilinear surface inside the first cell
/// the ray ends below, from where the ray reaches the cell's bound.
bool march(const FieldView& fv, const Ray& ray, double t_limit, double& t_hit) {
  const auto& m = fv.m;
  const Vec3& o = ray.o;
  const Vec3& d = ray.d;
  if (d.z() >= -1e-12) return false;
  const double x0 = fv.x0, x1 = fv.x0 + fv.nx * fv.pitch, y0 = fv.y0, y1 = fv.y0 + fv.ny * fv.pitch;
  double t0 = 0, t1 = t_limit;
  auto slab = [&](double oo, double dd, double inv, double lo, double hi) {
    if (std::abs(dd) < 1e-15) return oo >= lo && oo <= hi;
    double a = (lo - oo) * inv, b = (hi - oo) * inv;
    if (a > b) std::swap(a, b);
    t0 = std::max(t0, a), t1 = std::min(t1, b);
    return t0 <= t1;
  };
  if (!slab(o.x(), d.x(), ray.inv.x(), x0, x1) || !slab(o.y(), d.y(), ray.inv.y(), y0, y1) ||
      !slab(o.z(), d.z(), ray.inv.z(), 0.0, m.zmax_cache))
    return false;
  auto f = [&](double t) { return o.z() + t * d.z() - fv.bilinear(o.x() + t * d.x(), o.y() + t * d.y()); };
  bool found = false;
  const double tile = fv.pitch * CastingModel::kTile;
  const float* cell_max = m.cell_max.data();
  double t_prev = t0;
  dda(x0, y0, tile, 1.0 / tile, m.tiles_x, m.tiles_y, ray, t0, t1, [&](int ti, int tj, double ta, double tb) {
    const double zlow = o.z() + tb * d.z();
    const float tm = m.tile_max[static_cast<std::size_t>(tj) * static_cast<std::size_t>(m.tiles_x) + static_cast<std::size_t>(ti)];
    if (tm < zlow) {
      t_prev = tb;
      return false;
    }
    dda(x0, y0, fv.pitch, fv.inv_pitch, fv.nx, fv.ny, ray, ta, tb, [&](int i, int j, double, double cb) {
      const float cm = cell_max[static_cast<std::size_t>(j) * static_cast<std::size_t>(fv.nx) + static_cast<std::size_t>(i)];
      if (cm < o.z() + cb * d.z() || f(cb) > 0) {  // above everything in this cell at its exit
        t_prev = cb;
        return false;
      }
      // Nothing in this cell is above its bound: start where the ray comes down to it.
      double a = std::max(t_prev, (static_cast<double>(cm) - o.z()) * ray.inv.z()), b = cb;
      for (int it = 0; it < 40 && b - a > kHitTolerance_mm; ++it) {
        const double mid = 0.5 * (a + b);
        if (f(mid) > 0)
          a = mid;
        else
          b = mid;
      }
      t_hit = 0.5 * (a + b);
      found = true;
      return true;
    });
    return found;
  });
  return found;
}

/// Runs fn(row0, row1) over [0, rows) on `threads` threads, in small chunks taken in turn
/// (the result never depends on which thread rendered a row).
template <class Fn>
void parallel_rows(std::size_t rows, std::size_t threads, const Fn& fn) {
  constexpr std::size_t kChunk = 8;
  std::atomic<std::size_t> next{0};
  auto worker = [&] {
    for (;;) {
      const std::size_t a = next.fetch_add(kChunk);
      if (a >= rows) return;
      fn(a, std::min(rows, a + kChunk));
    }
  };
  std::vector<std::thread> pool;
  for (std::size_t t = 1; t < threads; ++t) pool.emplace_back(worker);
  worker();
  for (auto& th : pool) th.join();
}

/// Coord3D_C16 value of a depth (see to_range16).
inline std::uint16_t encode16(float z, double scale_mm, double offset_mm, std::uint16_t invalid_value) {
  if (std::isnan(z)) return invalid_value;
  const double q = std::round((z - offset_mm) / scale_mm);
  return (q < 0 || q > 65535 || static_cast<std::uint16_t>(q) == invalid_value) ? invalid_value
                                                                               : static_cast<std::uint16_t>(q);
}

}  // namespace

struct Scanner::Impl {
  ScannerConfig config;
  std::vector<float> rays;  ///< per pixel (x, y) of the normalized ray (x, y, 1)
};

Scanner::Scanner(ScannerConfig config) : impl_(std::make_unique<Impl>()) {
  impl_->config = std::move(config);
  const auto& K = impl_->config.intrinsics;
  const auto W = static_cast<std::size_t>(K.width);
  impl_->rays.resize(W * static_cast<std::size_t>(K.height) * 2);
  parallel_rows(static_cast<std::size_t>(K.height), static_cast<std::size_t>(std::max(1, impl_->config.threads)),
                [&](std::size_t r0, std::size_t r1) {
                  for (std::size_t v = r0; v < r1; ++v)
                    for (std::size_t u = 0; u < W; ++u) {
                      const Vec3 r = K.ray(static_cast<double>(u), static_cast<double>(v));
                      const auto k = (v * W + u) * 2;
                      impl_->rays[k] = static_cast<float>(r.x());
                      impl_->rays[k + 1] = static_cast<float>(r.y());
                    }
                });
}
Scanner::~Scanner() = default;
Scanner::Scanner(Scanner&&) noexcept = default;
Scanner& Scanner::operator=(Scanner&&) noexcept = default;
const ScannerConfig& Scanner::config() const { return impl_->config; }

std::vector<Capture> Scanner::capture_all(const Casting& casting) const {
  std::vector<Capture> out;
  for (std::size_t k = 0; k < impl_->config.photo_positions_mm.size(); ++k)
    out.push_back(capture(casting, impl_->config.photo_positions_mm[k], k));
  return out;
}

Capture Scanner::capture(const Casting& casting, double slide_position_mm, std::size_t view) const {
  const auto& cfg = impl_->config;
  const auto& K = cfg.intrinsics;
  const auto& m = casting.model();
  const std::size_t W = static_cast<std::size_t>(K.width), H = static_cast<std::size_t>(K.height), N = W * H;
  const Transform T_base_camera = cfg.T_base_camera(slide_position_mm);
  const Transform T_part_base = m.T_base_part.inverse();
  const Eigen::Matrix3d R_bc = T_base_camera.linear();
  const Vec3 o_base = T_base_camera.translation();
  const Vec3 o_part = T_part_base * o_base;
  const Eigen::Matrix3d R_pb = T_part_base.linear();
  const Eigen::Matrix3d R_bp = m.T_base_part.linear();
  const float* rays = impl_->rays.data();
  const FieldView fv(m);
  const float nanf = std::numeric_limits<float>::quiet_NaN();

  // Pass 1: ideal depth (Z along the camera axis) and the cosine of the incidence angle.
  const auto depth = std::make_unique_for_overwrite<float[]>(N);
  const auto cos_inc = std::make_unique_for_overwrite<float[]>(N);
  auto render_rows = [&](std::size_t r0, std::size_t r1) {
    for (std::size_t v = r0; v < r1; ++v)
      for (std::size_t u = 0; u < W; ++u) {
        const std::size_t k = v * W + u;
        depth[k] = nanf;
        cos_inc[k] = 1.0f;
        const Vec3 d = R_bc * Vec3(rays[2 * k], rays[2 * k + 1], 1.0);
        const Ray ray_base(o_base, d);
        Hit best;
        if (d.z() < 0) {  // table plane z = 0
          best.t = -o_base.z() * ray_base.inv.z();
          best.normal_base = Vec3::UnitZ();
        }
        for (const auto& b : m.scene) {
          double t0 = 0, t1 = best.t;
          int axis = -1;
          bool ok = true;
          for (int a = 0; a < 3 && ok; ++a) {
            if (std::abs(d[a]) < 1e-15) {
              ok = o_base[a] >= b.min_mm[a] && o_base[a] <= b.max_mm[a];
              continue;
            }
            double ta = (b.min_mm[a] - o_base[a]) * ray_base.inv[a], tb = (b.max_mm[a] - o_base[a]) * ray_base.inv[a];
            if (ta > tb) std::swap(ta, tb);
            if (ta > t0) t0 = ta, axis = a;
            t1 = std::min(t1, tb);
            ok = t0 <= t1;
          }
          if (ok && axis >= 0 && t0 < best.t) {
            best.t = t0;
            best.normal_base = Vec3::Zero();
            best.normal_base[axis] = d[axis] > 0 ? -1.0 : 1.0;
          }
        }
        const Vec3 dp = R_pb * d;
        double th = 0;
        if (m.on_fixture && march(fv, Ray(o_part, dp), best.t, th) && th < best.t) {
          best.t = th;
          const Vec3 pp = o_part + th * dp;
          const Eigen::Vector2d g = m.surface.gradient(pp.x(), pp.y());
          best.normal_base = R_bp * Vec3(-g.x(), -g.y(), 1.0).normalized();
        }
        if (!std::isfinite(best.t)) continue;
        if (best.t < cfg.min_range_mm || best.t > cfg.max_range_mm) continue;
        depth[k] = static_cast<float>(best.t);
        cos_inc[k] = static_cast<float>(std::abs(best.normal_base.dot(d.normalized())));
      }
  };
  const std::size_t threads = static_cast<std::size_t>(std::max(1, cfg.threads));
  parallel_rows(H, threads, render_rows);

  // Pass 2: the noise model, then the range images and the cloud. Every pixel draws from its
  // own stream (seed, view, pixel): thread independent.
  Capture cap;
  cap.range.width = cap.range16.width = cap.cloud.width = static_cast<std::uint32_t>(W);
  cap.range.height = cap.range16.height = cap.cloud.height = static_cast<std::uint32_t>(H);
  cap.range.data.resize(N);
  cap.range16.data.resize(N);
  cap.cloud.points.resize(N);
  const RangeImage16 enc;  // default Coord3D_C16 scale, offset and invalid value
  cap.range16.scale_mm = enc.scale_mm, cap.range16.offset_mm = enc.offset_mm, cap.range16.invalid_value = enc.invalid_value;
  const auto& nm = cfg.noise;
  const std::uint64_t seed = casting.seed();
  const double start = deg_to_rad(nm.dropout_start_deg), full = deg_to_rad(nm.dropout_full_deg);
  const double cos_start = std::cos(start), cos_full = std::cos(full);
  // The measured depth of pixel k (ideal depth z > 0), or NaN where it drops out.
  auto add_noise = [&](std::size_t k, std::size_t u, std::size_t v, float z) -> float {
    Rng rng(seed * 0x100000001b3ULL + view, k, 0xD15C);
    const double c = std::max(1e-3, static_cast<double>(cos_inc[k]));
    if (c <= cos_full) return nanf;  // incidence beyond dropout_full_deg
    if (c < cos_start) {            // between dropout_start_deg and dropout_full_deg
      const double inc = std::acos(std::min(1.0, c));
      if (rng.uniform() < (inc - start) / (full - start)) return nanf;
    }
    if (nm.surface_dropout_fraction > 0) {
      const Vec3 d = R_bc * Vec3(rays[2 * k], rays[2 * k + 1], 1.0);
      const Eigen::Vector3f p = (o_base + static_cast<double>(z) * d).cast<float>();
      if (value_noise_cell(seed, p.x(), p.y(), p.z()) < nm.surface_dropout_fraction) return nanf;
    }
    double zz = z;
    // flying pixels at depth discontinuities
    float other = z;
    double jump = 0;
    auto look = [&](std::size_t kk) {
      const float zn = depth[kk];
      if (std::isnan(zn)) return;
      if (std::abs(zn - z) > jump) jump = std::abs(zn - z), other = zn;
    };
    if (u > 0) look(k - 1);
    if (u + 1 < W) look(k + 1);
    if (v > 0) look(k - W);
    if (v + 1 < H) look(k + W);
    if (jump > nm.discontinuity_mm && rng.uniform() < nm.flying_pixel_fraction)
      zz += rng.uniform(0.15, 0.85) * (other - z);
    const double rel = z / nm.reference_distance_mm;
    const double grow = nm.distance_exponent == 2.0 ? rel * rel : std::pow(rel, nm.distance_exponent);
    const double sigma = nm.sigma_z_mm * grow * (1.0 + nm.grazing_gain * (std::min(1.0 / c, 5.0) - 1.0));
    zz += sigma * rng.gaussian();
    if (rng.uniform() < nm.outlier_fraction) zz += rng.uniform(-nm.outlier_range_mm, nm.outlier_range_mm);
    return (zz < cfg.min_range_mm || zz > cfg.max_range_mm) ? nanf : static_cast<float>(zz);
  };
  auto noise_rows = [&](std::size_t r0, std::size_t r1) {
    for (std::size_t v = r0; v < r1; ++v)
      for (std::size_t u = 0; u < W; ++u) {
        const std::size_t k = v * W + u;
        const float z = depth[k];
        float zout = z;
        if (nm.enabled && !std::isnan(z)) zout = add_noise(k, u, v, z);
        cap.range.data[k] = zout;
        cap.range16.data[k] = encode16(zout, enc.scale_mm, enc.offset_mm, enc.invalid_value);
        cap.cloud.points[k] = std::isnan(zout) ? OrganizedCloud::invalid()
                                               : Eigen::Vector3f(rays[2 * k] * zout, rays[2 * k + 1] * zout, zout);
      }
  };
  parallel_rows(H, threads, noise_rows);

  auto& t = cap.truth;
  t.part_id = casting.part_id();
  t.seed = seed;
  t.view = view;
  t.slide_position_mm = slide_position_mm;
  t.T_base_camera = T_base_camera;
  t.T_base_part = m.T_base_part;
  t.intrinsics = K;
  t.regions = m.truth();
  t.gouges = m.gouges;
  return cap;
}

RangeImage16 to_range16(const RangeImageF32& range, double scale_mm, double offset_mm, std::uint16_t invalid_value) {
  RangeImage16 r;
  r.width = range.width, r.height = range.height;
  r.scale_mm = scale_mm, r.offset_mm = offset_mm, r.invalid_value = invalid_value;
  r.data.resize(range.data.size());
  for (std::size_t k = 0; k < range.data.size(); ++k) r.data[k] = encode16(range.data[k], scale_mm, offset_mm, invalid_value);
  return r;
}

RangeImageF32 to_range_f32(const RangeImage16& range) {
  RangeImageF32 r;
  r.width = range.width, r.height = range.height;
  r.data.resize(range.data.size());
  for (std::size_t k = 0; k < range.data.size(); ++k)
    r.data[k] = range.data[k] == range.invalid_value
                    ? std::numeric_limits<float>::quiet_NaN()
                    : static_cast<float>(range.data[k] * range.scale_mm + range.offset_mm);
  return r;
}

OrganizedCloud to_cloud(const RangeImageF32& range, const CameraIntrinsics& K) {
  OrganizedCloud c;
  c.width = range.width, c.height = range.height;
  c.points.resize(range.data.size());
  for (std::uint32_t v = 0; v < range.height; ++v)
    for (std::uint32_t u = 0; u < range.width; ++u) {
      const std::size_t k = static_cast<std::size_t>(v) * range.width + u;
      const float z = range.data[k];
      if (std::isnan(z)) {
        c.points[k] = OrganizedCloud::invalid();
        continue;
      }
      const Vec3 r = K.ray(u, v) * z;
      c.points[k] = r.cast<float>();
    }
  return c;
}

}  // namespace fettle::sim
