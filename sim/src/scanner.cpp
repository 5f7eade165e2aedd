// The structured-light scanner: pinhole + distortion camera on a slide, ray casting the
// scene (table plane, clamps, clutter, the casting's height field), then the noise model.
#include <algorithm>
#include <cmath>
#include <thread>

#include "casting_model.hpp"

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

// ---------------------------------------------------------------------------------------------
// Ray casting

namespace {

struct Hit {
  double t = std::numeric_limits<double>::infinity();  ///< along (x, y, 1) camera ray = depth Z
  Vec3 normal_base{0, 0, 1};
  Vec3 point_base{0, 0, 0};
};

/// 2D DDA over a grid of cells of size `cell` with origin (gx, gy), visiting cells the ray
/// o + t d passes between t0 and t1. visit(i, j, ta, tb) returns true to stop.
template <class Visit>
void dda(double gx, double gy, double cell, int nx, int ny, const Vec3& o, const Vec3& d, double t0, double t1,
         Visit&& visit) {
  const double px = o.x() + t0 * d.x(), py = o.y() + t0 * d.y();
  int i = std::clamp(static_cast<int>(std::floor((px - gx) / cell)), 0, nx - 1);
  int j = std::clamp(static_cast<int>(std::floor((py - gy) / cell)), 0, ny - 1);
  const int si = d.x() > 0 ? 1 : -1, sj = d.y() > 0 ? 1 : -1;
  const double inf = std::numeric_limits<double>::infinity();
  const double dtx = std::abs(d.x()) > 1e-15 ? cell / std::abs(d.x()) : inf;
  const double dty = std::abs(d.y()) > 1e-15 ? cell / std::abs(d.y()) : inf;
  double tx = inf, ty = inf;
  if (std::abs(d.x()) > 1e-15) tx = (gx + (i + (si > 0 ? 1 : 0)) * cell - o.x()) / d.x();
  if (std::abs(d.y()) > 1e-15) ty = (gy + (j + (sj > 0 ? 1 : 0)) * cell - o.y()) / d.y();
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

/// Intersects a part-frame ray with the surface height field.
bool march(const CastingModel& m, const Vec3& o, const Vec3& d, double t_limit, double& t_hit) {
  const auto& s = m.surface;
  if (d.z() >= -1e-12) return false;
  const double x0 = s.x0, x1 = s.x0 + s.nx * s.pitch, y0 = s.y0, y1 = s.y0 + s.ny * s.pitch;
  double t0 = 0, t1 = t_limit;
  auto slab = [&](double oo, double dd, double lo, double hi) {
    if (std::abs(dd) < 1e-15) return oo >= lo && oo <= hi;
    double a = (lo - oo) / dd, b = (hi - oo) / dd;
    if (a > b) std::swap(a, b);
    t0 = std::max(t0, a), t1 = std::min(t1, b);
    return t0 <= t1;
  };
  if (!slab(o.x(), d.x(), x0, x1) || !slab(o.y(), d.y(), y0, y1) || !slab(o.z(), d.z(), 0.0, m.zmax_cache))
    return false;
  auto f = [&](double t) { return o.z() + t * d.z() - s.bilinear(o.x() + t * d.x(), o.y() + t * d.y()); };
  bool found = false;
  const double tile = s.pitch * CastingModel::kTile;
  double t_prev = t0;
  dda(x0, y0, tile, m.tiles_x, m.tiles_y, o, d, t0, t1, [&](int ti, int tj, double ta, double tb) {
    const double zlow = o.z() + tb * d.z();
    const float tm = m.tile_max[static_cast<std::size_t>(tj) * static_cast<std::size_t>(m.tiles_x) + static_cast<std::size_t>(ti)];
    if (tm < zlow) {
      t_prev = tb;
      return false;
    }
    dda(x0, y0, s.pitch, s.nx, s.ny, o, d, ta, tb, [&](int, int, double, double cb) {
      if (f(cb) > 0) {
        t_prev = cb;
        return false;
      }
      double a = t_prev, b = cb;
      for (int it = 0; it < 14; ++it) {
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

}  // namespace

struct Scanner::Impl {
  ScannerConfig config;
  std::vector<float> rays;  ///< per pixel (x, y) of the normalized ray (x, y, 1)
};

Scanner::Scanner(ScannerConfig config) : impl_(std::make_unique<Impl>()) {
  impl_->config = std::move(config);
  const auto& K = impl_->config.intrinsics;
  impl_->rays.resize(static_cast<std::size_t>(K.width) * static_cast<std::size_t>(K.height) * 2);
  for (int v = 0; v < K.height; ++v)
    for (int u = 0; u < K.width; ++u) {
      const Vec3 r = K.ray(u, v);
      const auto k = (static_cast<std::size_t>(v) * static_cast<std::size_t>(K.width) + static_cast<std::size_t>(u)) * 2;
      impl_->rays[k] = static_cast<float>(r.x());
      impl_->rays[k + 1] = static_cast<float>(r.y());
    }
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

  std::vector<float> depth(N, std::numeric_limits<float>::quiet_NaN());
  std::vector<float> cos_inc(N, 1.0f);
  std::vector<Eigen::Vector3f> hit_base(N);

  auto render_rows = [&](std::size_t r0, std::size_t r1) {
    for (std::size_t v = r0; v < r1; ++v)
      for (std::size_t u = 0; u < W; ++u) {
        const std::size_t k = v * W + u;
        const Vec3 rc(impl_->rays[2 * k], impl_->rays[2 * k + 1], 1.0);
        const Vec3 d = R_bc * rc;
        Hit best;
        if (d.z() < 0) {  // table plane z = 0
          best.t = -o_base.z() / d.z();
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
            double ta = (b.min_mm[a] - o_base[a]) / d[a], tb = (b.max_mm[a] - o_base[a]) / d[a];
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
        if (march(m, o_part, dp, best.t, th) && th < best.t) {
          best.t = th;
          const Vec3 pp = o_part + th * dp;
          const Eigen::Vector2d g = m.surface.gradient(pp.x(), pp.y());
          best.normal_base = m.T_base_part.linear() * Vec3(-g.x(), -g.y(), 1.0).normalized();
        }
        if (!std::isfinite(best.t)) continue;
        if (best.t < cfg.min_range_mm || best.t > cfg.max_range_mm) continue;
        depth[k] = static_cast<float>(best.t);
        cos_inc[k] = static_cast<float>(std::abs(best.normal_base.dot(d.normalized())));
        hit_base[k] = (o_base + best.t * d).cast<float>();
      }
  };
  const std::size_t threads = static_cast<std::size_t>(std::max(1, cfg.threads));
  auto parallel = [&](const auto& fn) {
    std::vector<std::thread> pool;
    const std::size_t chunk = (H + threads - 1) / threads;
    for (std::size_t t = 0; t < threads; ++t) {
      const std::size_t a = t * chunk, b = std::min(H, a + chunk);
      if (a < b) pool.emplace_back([&fn, a, b] { fn(a, b); });
    }
    for (auto& th : pool) th.join();
  };
  parallel(render_rows);

  // Noise: every pixel draws from its own stream (seed, view, pixel): thread independent.
  const auto& nm = cfg.noise;
  std::vector<float> out(depth);
  const std::uint64_t seed = casting.seed();
  auto noise_rows = [&](std::size_t r0, std::size_t r1) {
    for (std::size_t v = r0; v < r1; ++v)
      for (std::size_t u = 0; u < W; ++u) {
        const std::size_t k = v * W + u;
        const float z = depth[k];
        if (!nm.enabled || std::isnan(z)) continue;
        Rng rng(seed * 0x100000001b3ULL + view, k, 0xD15C);
        const double c = std::max(1e-3, static_cast<double>(cos_inc[k]));
        const double inc = std::acos(std::min(1.0, c));
        if (inc >= deg_to_rad(nm.dropout_full_deg)) {
          out[k] = std::numeric_limits<float>::quiet_NaN();
          continue;
        }
        const double start = deg_to_rad(nm.dropout_start_deg);
        if (inc > start && rng.uniform() < (inc - start) / (deg_to_rad(nm.dropout_full_deg) - start)) {
          out[k] = std::numeric_limits<float>::quiet_NaN();
          continue;
        }
        if (nm.surface_dropout_fraction > 0) {
          const auto& p = hit_base[k];
          const double n = value_noise_cell(seed, p.x(), p.y(), p.z());
          if (n < nm.surface_dropout_fraction) {
            out[k] = std::numeric_limits<float>::quiet_NaN();
            continue;
          }
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
        const double sigma = nm.sigma_z_mm * std::pow(z / nm.reference_distance_mm, nm.distance_exponent) *
                             (1.0 + nm.grazing_gain * (std::min(1.0 / c, 5.0) - 1.0));
        zz += sigma * rng.gaussian();
        if (rng.uniform() < nm.outlier_fraction) zz += rng.uniform(-nm.outlier_range_mm, nm.outlier_range_mm);
        out[k] = (zz < cfg.min_range_mm || zz > cfg.max_range_mm) ? std::numeric_limits<float>::quiet_NaN()
                                                                    : static_cast<float>(zz);
      }
  };
  parallel(noise_rows);

  Capture cap;
  cap.range.width = static_cast<std::uint32_t>(W);
  cap.range.height = static_cast<std::uint32_t>(H);
  cap.range.data = std::move(out);
  cap.range16 = to_range16(cap.range);
  cap.cloud.width = cap.range.width;
  cap.cloud.height = cap.range.height;
  cap.cloud.points.resize(N);
  for (std::size_t k = 0; k < N; ++k) {
    const float z = cap.range.data[k];
    cap.cloud.points[k] = std::isnan(z) ? OrganizedCloud::invalid()
                                        : Eigen::Vector3f(impl_->rays[2 * k] * z, impl_->rays[2 * k + 1] * z, z);
  }
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
  for (std::size_t k = 0; k < range.data.size(); ++k) {
    const float z = range.data[k];
    if (std::isnan(z)) {
      r.data[k] = invalid_value;
      continue;
    }
    const double q = std::round((z - offset_mm) / scale_mm);
    r.data[k] = (q < 0 || q > 65535 || static_cast<std::uint16_t>(q) == invalid_value)
                    ? invalid_value
                    : static_cast<std::uint16_t>(q);
  }
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
