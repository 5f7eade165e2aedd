// Excess material: points above the template surface, cleaned, measured.
#include "fettle/vision/excess.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Cholesky>

#include <pcl/search/kdtree.h>
#include <pcl/segmentation/extract_clusters.h>

#include "fettle/config/vision.hpp"

#include "detail.hpp"
#include "prepared_impl.hpp"

namespace fettle::vision {

std::vector<float> signed_distances(const PreparedCloud& templ, const std::vector<Eigen::Vector3f>& points) {
  const auto& T = templ.impl();
  std::vector<float> out(points.size(), 0.0f);
  detail::parallel_for(points.size(), detail::thread_count(0), [&](std::size_t, std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      const auto [j, d2] = T.nearest_any(points[i]);
      if (j < 0) {
        out[i] = std::numeric_limits<float>::quiet_NaN();
        continue;
      }
      const auto k = static_cast<std::size_t>(j);
      out[i] = T.fine.normals[k].dot(points[i] - T.fine.points[k]);
    }
  });
  return out;
}

namespace {

struct FaceSample {
  double x, y, h;
};

/// A robust surface of the offsets around (x, y), as polynomial coefficients in (dx, dy) / scale:
/// a plane (N = 3: 1, u, v) or a quadratic (N = 6: and u^2, uv, v^2). Least squares, then again on
/// the samples no more than 2.5 robust sigmas (at least 0.03 mm) above it and 4 (at least 0.05 mm)
/// below, three times. What stands on a face lies above it (a fin's or a riser's foot), so the
/// upper side is trimmed hard; below, only what no face has (a mixed pixel at a wall's foot),
/// since the passes follow the face down. A surface rather than a quantile keeps a sloped face's
/// offset at its centre (a quantile of a slope reads low). The kept samples' centroid (dx, dy)
/// in `centroid`. Nothing with fewer than 4 N samples or badly conditioned.
template <int N>
std::optional<Eigen::Matrix<double, N, 1>> robust_surface(const std::vector<FaceSample>& s, double x, double y,
                                                          double scale, Eigen::Vector2d& centroid) {
  using Vec = Eigen::Matrix<double, N, 1>;
  const auto basis = [&](const FaceSample& p) {
    const double u = (p.x - x) / scale, v = (p.y - y) / scale;
    Vec a;
    a[0] = 1.0, a[1] = u, a[2] = v;
    if constexpr (N == 6) a[3] = u * u, a[4] = u * v, a[5] = v * v;
    return a;
  };
  constexpr std::size_t kMin = 4 * N;
  if (s.size() < kMin) return std::nullopt;
  std::vector<char> keep(s.size(), 1);
  Vec c = Vec::Zero();
  for (int round = 0; round < 4; ++round) {
    Eigen::Matrix<double, N, N> A = Eigen::Matrix<double, N, N>::Zero();
    Vec b = Vec::Zero();
    std::size_t n = 0;
    for (std::size_t k = 0; k < s.size(); ++k) {
      if (!keep[k]) continue;
      const Vec a = basis(s[k]);
      A += a * a.transpose(), b += a * s[k].h, ++n;
    }
    if (n < kMin) return std::nullopt;
    const Eigen::LDLT<Eigen::Matrix<double, N, N>> ldlt(A);
    if (ldlt.info() != Eigen::Success || ldlt.rcond() < 1e-6) return std::nullopt;
    c = ldlt.solve(b);
    if (round == 3) {
      centroid = scale * Eigen::Vector2d(A(0, 1) / A(0, 0), A(0, 2) / A(0, 0));
      break;
    }
    std::vector<double> res(s.size()), abs_kept;
    for (std::size_t k = 0; k < s.size(); ++k) {
      res[k] = s[k].h - basis(s[k]).dot(c);
      if (keep[k]) abs_kept.push_back(std::abs(res[k]));
    }
    const auto mid = abs_kept.begin() + static_cast<std::ptrdiff_t>(abs_kept.size() / 2);
    std::nth_element(abs_kept.begin(), mid, abs_kept.end());
    const double sigma = 1.4826 * *mid;
    const double above = std::max(0.03, 2.5 * sigma), below = std::max(0.05, 4.0 * sigma);
    for (std::size_t k = 0; k < s.size(); ++k) keep[k] = res[k] <= above && res[k] >= -below;
  }
  return c;
}

/// The offset at (x, y) of a robust plane through the samples around it (robust_surface), and
/// whether they lie on one side of it: their kept centroid more than kOneSidedMm from (x, y) (a
/// half disc's is 4.2 mm off its centre; beside a riser, past its foot, 5-9 mm). On one side,
/// the samples' slope carried to the node reads the face 0.2-0.4 mm off beside a riser: there a
/// hole's quadratic replaces it (fill_holes). NaN where fewer than 12 samples or they lie on one
/// line.
std::pair<double, bool> local_plane_at(const std::vector<FaceSample>& s, double x, double y) {
  constexpr double kOneSidedMm = 5.0;
  Eigen::Vector2d centroid;
  const auto c = robust_surface<3>(s, x, y, 1.0, centroid);
  if (!c) return {std::numeric_limits<double>::quiet_NaN(), false};
  return {(*c)[0], centroid.norm() > kOneSidedMm};
}

/// The nodes without an offset of their own, or with one from samples on one side of them
/// (`one_sided`). A hole the samples surround (under a riser and along its rim): one
/// robust quadratic through the samples within kLocalRadiusMm of its nodes, where the mean of
/// their unit directions from the hole's centre is shorter than 0.4 (a half ring's is 0.64). A
/// quadratic carries the face's curvature across it: a riser 40 mm wide on the crest of a 90 mm
/// form wave stands on a face 0.3 mm over the region's plane (test
/// Excess.TheFaceUnderARiserIsInterpolatedNotExtrapolated). The others (a hole at the edge of
/// what the scan saw) and any the quadratic fails: the one-sided nodes keep their own offset,
/// the empty ones the harmonic interpolation of the nodes around them (each the mean of its
/// neighbours, Gauss-Seidel from the region's plane), never beyond the values around them.
void fill_holes(const std::vector<FaceSample>& samples, const std::vector<char>& one_sided, FormOffset& f) {
  const int nx = f.local_nx, ny = f.local_ny;
  const auto index = [&](int i, int j) { return static_cast<std::size_t>(j) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(i); };
  const auto node = [&](std::size_t k) {
    return Eigen::Vector2d(f.local_x0 + static_cast<double>(k % static_cast<std::size_t>(nx)) * f.local_pitch_mm,
                           f.local_y0 + static_cast<double>(k / static_cast<std::size_t>(nx)) * f.local_pitch_mm);
  };
  std::vector<int> component(f.local.size(), -1);
  std::vector<std::size_t> harmonic;
  int next = 0;
  const auto in_hole = [&](std::size_t k) { return std::isnan(f.local[k]) || one_sided[k]; };
  for (std::size_t seed = 0; seed < f.local.size(); ++seed) {
    if (!in_hole(seed) || component[seed] >= 0) continue;
    // the hole's nodes (4-connected); one on the grid's border is not surrounded
    std::vector<std::size_t> hole{seed};
    component[seed] = next;
    bool border = false;
    for (std::size_t h = 0; h < hole.size(); ++h) {
      const int i = static_cast<int>(hole[h] % static_cast<std::size_t>(nx)), j = static_cast<int>(hole[h] / static_cast<std::size_t>(nx));
      border = border || i == 0 || j == 0 || i == nx - 1 || j == ny - 1;
      for (const auto& [a, b] : {std::pair{i - 1, j}, std::pair{i + 1, j}, std::pair{i, j - 1}, std::pair{i, j + 1}}) {
        if (a < 0 || b < 0 || a >= nx || b >= ny) continue;
        const auto k = index(a, b);
        if (in_hole(k) && component[k] < 0) component[k] = next, hole.push_back(k);
      }
    }
    ++next;
    std::optional<Eigen::Matrix<double, 6, 1>> quadratic;
    Eigen::Vector2d centre = Eigen::Vector2d::Zero(), lo = node(hole.front()), hi = lo;
    for (const auto k : hole) centre += node(k), lo = lo.cwiseMin(node(k)), hi = hi.cwiseMax(node(k));
    centre /= static_cast<double>(hole.size());
    const double scale = 0.5 * (hi - lo).norm() + FormOffset::kLocalRadiusMm;
    if (!border) {
      std::vector<FaceSample> ring;
      Eigen::Vector2d direction = Eigen::Vector2d::Zero();
      const double r = FormOffset::kLocalRadiusMm + f.local_pitch_mm;
      for (const auto& p : samples) {
        const Eigen::Vector2d q(p.x, p.y);
        if ((q.array() < lo.array() - r).any() || (q.array() > hi.array() + r).any()) continue;
        bool near = false;
        for (const auto k : hole)
          if ((q - node(k)).squaredNorm() <= r * r) {
            near = true;
            break;
          }
        if (!near) continue;
        ring.push_back(p);
        if ((q - centre).norm() > 1e-9) direction += (q - centre).normalized();
      }
      Eigen::Vector2d centroid;
      if (!ring.empty() && direction.norm() / static_cast<double>(ring.size()) < 0.4)
        quadratic = robust_surface<6>(ring, centre.x(), centre.y(), scale, centroid);
    }
    for (const auto k : hole) {
      if (!quadratic) {
        if (std::isnan(f.local[k])) harmonic.push_back(k);
        continue;
      }
      const Eigen::Vector2d uv = (node(k) - centre) / scale;
      const auto& c = *quadratic;
      f.local[k] = static_cast<float>(c[0] + c[1] * uv.x() + c[2] * uv.y() + c[3] * uv.x() * uv.x() +
                                      c[4] * uv.x() * uv.y() + c[5] * uv.y() * uv.y());
    }
  }
  if (harmonic.empty() || harmonic.size() == f.local.size()) return;
  for (const auto k : harmonic) f.local[k] = static_cast<float>(f.plane_at(node(k).x(), node(k).y()));
  for (int sweep = 0; sweep < 500; ++sweep) {
    double change = 0.0;
    for (const auto k : harmonic) {
      const int i = static_cast<int>(k % static_cast<std::size_t>(nx)), j = static_cast<int>(k / static_cast<std::size_t>(nx));
      double sum = 0.0;
      int n = 0;
      for (const auto& [a, b] : {std::pair{i - 1, j}, std::pair{i + 1, j}, std::pair{i, j - 1}, std::pair{i, j + 1}})
        if (a >= 0 && b >= 0 && a < nx && b < ny) sum += f.local[index(a, b)], ++n;
      const double v = sum / n;
      change = std::max(change, std::abs(v - f.local[k]));
      f.local[k] = static_cast<float>(v);
    }
    if (change < 1e-4) break;
  }
}

/// The local offsets of a FormOffset (see there): at nodes `pitch` apart over the samples'
/// extent, local_plane_at() the samples within FormOffset::kLocalRadiusMm.
void fit_local_offsets(const std::vector<FaceSample>& samples, FormOffset& f) {
  if (samples.empty()) return;
  const double p = f.local_pitch_mm, r = FormOffset::kLocalRadiusMm;
  double x0 = samples.front().x, y0 = samples.front().y, x1 = x0, y1 = y0;
  for (const auto& s : samples) x0 = std::min(x0, s.x), y0 = std::min(y0, s.y), x1 = std::max(x1, s.x), y1 = std::max(y1, s.y);
  f.local_x0 = std::floor(x0 / p) * p, f.local_y0 = std::floor(y0 / p) * p;
  f.local_nx = static_cast<int>(std::ceil((x1 - f.local_x0) / p)) + 1;
  f.local_ny = static_cast<int>(std::ceil((y1 - f.local_y0) / p)) + 1;
  // the samples by node cell (each sample in the cell of the node at or below it)
  const auto cells = static_cast<std::size_t>(f.local_nx) * static_cast<std::size_t>(f.local_ny);
  std::vector<std::vector<std::size_t>> in_cell(cells);
  const auto cell_of = [&](int i, int j) { return static_cast<std::size_t>(j) * static_cast<std::size_t>(f.local_nx) + static_cast<std::size_t>(i); };
  for (std::size_t k = 0; k < samples.size(); ++k) {
    const int i = std::clamp(static_cast<int>((samples[k].x - f.local_x0) / p), 0, f.local_nx - 1);
    const int j = std::clamp(static_cast<int>((samples[k].y - f.local_y0) / p), 0, f.local_ny - 1);
    in_cell[cell_of(i, j)].push_back(k);
  }
  const int reach = static_cast<int>(std::ceil(r / p));
  f.local.assign(cells, std::numeric_limits<float>::quiet_NaN());
  std::vector<char> one_sided(cells, 0);
  std::vector<FaceSample> near;
  for (int j = 0; j < f.local_ny; ++j)
    for (int i = 0; i < f.local_nx; ++i) {
      const double x = f.local_x0 + i * p, y = f.local_y0 + j * p;
      near.clear();
      for (int jj = std::max(0, j - reach); jj <= std::min(f.local_ny - 1, j + reach); ++jj)
        for (int ii = std::max(0, i - reach); ii <= std::min(f.local_nx - 1, i + reach); ++ii)
          for (const auto k : in_cell[cell_of(ii, jj)])
            if ((samples[k].x - x) * (samples[k].x - x) + (samples[k].y - y) * (samples[k].y - y) <= r * r)
              near.push_back(samples[k]);
      const auto [offset, on_one_side] = local_plane_at(near, x, y);
      f.local[cell_of(i, j)] = static_cast<float>(offset);
      one_sided[cell_of(i, j)] = on_one_side ? 1 : 0;
    }
  fill_holes(samples, one_sided, f);
}

/// The samples that lie clear of what stands on the face: those farther than
/// FormOffset::kFootMm (x-y) from every 1 mm cell that holds at least 3 scene points on an
/// upward face more than `threshold_mm` (and at most `max_height_mm`) above the face `f`.
std::vector<FaceSample> clear_of_material(const std::vector<FaceSample>& samples, const PreparedCloud::Impl& T,
                                          const Cloud& scene, const std::vector<int>& owner,
                                          const std::vector<float>& height, const FormOffset& f,
                                          double threshold_mm, double max_height_mm) {
  if (samples.empty()) return samples;
  constexpr double cell = 1.0;
  double x0 = samples.front().x, y0 = samples.front().y, x1 = x0, y1 = y0;
  for (const auto& s : samples) x0 = std::min(x0, s.x), y0 = std::min(y0, s.y), x1 = std::max(x1, s.x), y1 = std::max(y1, s.y);
  const int reach = static_cast<int>(std::ceil(FormOffset::kFootMm / cell));
  x0 -= reach * cell, y0 -= reach * cell, x1 += reach * cell, y1 += reach * cell;
  const int nx = static_cast<int>((x1 - x0) / cell) + 1, ny = static_cast<int>((y1 - y0) / cell) + 1;
  const auto index = [&](int i, int j) { return static_cast<std::size_t>(j) * static_cast<std::size_t>(nx) + static_cast<std::size_t>(i); };
  std::vector<int> count(static_cast<std::size_t>(nx) * static_cast<std::size_t>(ny), 0);
  for (std::size_t k = 0; k < owner.size(); ++k) {
    if (owner[k] < 0 || height[k] > max_height_mm) continue;
    if (T.fine.normals[static_cast<std::size_t>(owner[k])].z() < 0.8f) continue;
    const auto& p = scene.points[k];
    if (p.x() < x0 || p.y() < y0 || p.x() >= x1 || p.y() >= y1) continue;
    if (height[k] - f.at(p.x(), p.y()) <= threshold_mm) continue;
    ++count[index(static_cast<int>((p.x() - x0) / cell), static_cast<int>((p.y() - y0) / cell))];
  }
  std::vector<char> foot(count.size(), 0);
  bool any = false;
  for (int j = 0; j < ny; ++j)
    for (int i = 0; i < nx; ++i) {
      if (count[index(i, j)] < 3) continue;
      any = true;
      for (int b = std::max(0, j - reach); b <= std::min(ny - 1, j + reach); ++b)
        for (int a = std::max(0, i - reach); a <= std::min(nx - 1, i + reach); ++a)
          if ((a - i) * (a - i) + (b - j) * (b - j) <= reach * reach) foot[index(a, b)] = 1;
    }
  if (!any) return samples;
  std::vector<FaceSample> out;
  out.reserve(samples.size());
  for (const auto& s : samples)
    if (!foot[index(static_cast<int>((s.x - x0) / cell), static_cast<int>((s.y - y0) / cell))]) out.push_back(s);
  return out;
}

/// The robust plane of offsets (see FormOffset): least squares on (1, x, y), then twice again
/// on the points within 3 robust sigmas (at least 0.05 mm) of it. Points on one line or fewer
/// than 30 give the median offset alone; fewer than 10, nothing. Then the local offsets, fitted
/// again (up to three times) without the samples at the foot of what stands out of the last
/// fit's face: a riser whose tilted top meets the face is a ramp of material within the form
/// deviation, which a plane through a node's neighbourhood takes for face and reads up to
/// 0.5 mm high there; each round's lower face shows more of the ramp as material (test
/// Excess.ARiserMeetingTheFaceOnARampLeavesTheFaceWhereItIs).
FormOffset fit_form_offset(const PreparedCloud::Impl& T, const Cloud& scene, const std::vector<int>& owner,
                           const std::vector<float>& height, double form_deviation_mm, double threshold_mm,
                           double max_height_mm) {
  FormOffset f;
  const double band = config::face_band_mm(form_deviation_mm);
  std::vector<FaceSample> face;  // within the band of the template
  for (std::size_t i = 0; i < owner.size(); ++i) {
    if (owner[i] < 0 || std::abs(height[i]) > band) continue;
    if (T.fine.normals[static_cast<std::size_t>(owner[i])].z() < 0.8f) continue;  // upward faces only
    face.push_back({scene.points[i].x(), scene.points[i].y(), height[i]});
  }
  if (face.size() < 10) return f;
  const auto median_of = [](std::vector<double> v) {
    const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
    std::nth_element(v.begin(), mid, v.end());
    return *mid;
  };
  std::vector<char> keep(face.size(), 1);
  std::vector<double> res(face.size(), 0.0);  // |offset - plane| of every face point, last fit
  for (int round = 0; round < 3; ++round) {
    Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
    Eigen::Vector3d b = Eigen::Vector3d::Zero();
    Eigen::Vector2d mean = Eigen::Vector2d::Zero();
    std::vector<double> hs;
    for (std::size_t k = 0; k < face.size(); ++k)
      if (keep[k]) mean += Eigen::Vector2d(face[k].x, face[k].y), hs.push_back(face[k].h);
    if (hs.size() < 10) break;
    mean /= static_cast<double>(hs.size());
    for (std::size_t k = 0; k < face.size(); ++k) {
      if (!keep[k]) continue;
      const Eigen::Vector3d a(1.0, face[k].x - mean.x(), face[k].y - mean.y());
      A += a * a.transpose();
      b += a * face[k].h;
    }
    // a plane needs the points spread in x and y (centred moments of a few mm at least)
    const double n = static_cast<double>(hs.size());
    const bool planar = hs.size() >= 30 && A(1, 1) / n > 4.0 && A(2, 2) / n > 4.0 &&
                        A.bottomRightCorner<2, 2>().determinant() / (n * n) > 16.0;
    if (planar) {
      const Eigen::Vector3d c = A.ldlt().solve(b);
      f.per_mm_x = c(1), f.per_mm_y = c(2);
      f.at_origin_mm = c(0) - c(1) * mean.x() - c(2) * mean.y();
    } else {
      f.per_mm_x = f.per_mm_y = 0.0;
      f.at_origin_mm = median_of(hs);
    }
    f.fitted = true;
    std::vector<double> kept_res;
    for (std::size_t k = 0; k < face.size(); ++k) {
      res[k] = std::abs(face[k].h - f.plane_at(face[k].x, face[k].y));
      if (keep[k]) kept_res.push_back(res[k]);
    }
    const double gate = std::max(0.05, 3.0 * 1.4826 * median_of(kept_res));
    for (std::size_t k = 0; k < face.size(); ++k) keep[k] = res[k] <= gate ? 1 : 0;
  }
  double ss = 0.0;
  f.points = 0;
  for (std::size_t k = 0; k < face.size(); ++k)
    if (keep[k]) ss += res[k] * res[k], ++f.points;
  f.rms_mm = f.points > 0 ? std::sqrt(ss / static_cast<double>(f.points)) : 0.0;
  // the local fit's samples: within the band of the plane (which carries the tilt a best fit to
  // a deformed body takes), not of the template
  auto wide = face;
  std::erase_if(wide, [&](const FaceSample& w) { return std::abs(w.h - f.plane_at(w.x, w.y)) > band; });
  fit_local_offsets(wide, f);
  for (int round = 0; round < 3; ++round) {
    const auto clear = clear_of_material(wide, T, scene, owner, height, f, threshold_mm, max_height_mm);
    if (clear.size() == wide.size()) break;
    wide = clear;
    fit_local_offsets(wide, f);
  }
  return f;
}

}  // namespace

std::optional<double> FormOffset::local_at(double x_mm, double y_mm) const {
  if (!fitted || local_nx < 2 || local_ny < 2) return std::nullopt;
  double u = (x_mm - local_x0) / local_pitch_mm, v = (y_mm - local_y0) / local_pitch_mm;
  const double beyond = kLocalRadiusMm / local_pitch_mm;
  if (u < -beyond || v < -beyond || u > local_nx - 1 + beyond || v > local_ny - 1 + beyond) return std::nullopt;
  u = std::clamp(u, 0.0, local_nx - 1.0), v = std::clamp(v, 0.0, local_ny - 1.0);
  // the cell's lower-left node, the last row and column belonging to the cell below them
  const int i = std::min(static_cast<int>(u), local_nx - 2), j = std::min(static_cast<int>(v), local_ny - 2);
  const double fu = u - i, fv = v - j;
  // bilinear over the nodes that hold an offset, their weights renormalised (the edge of the
  // seen face keeps the offset it has there); none where none does
  double sum = 0.0, weight = 0.0;
  for (int b = 0; b < 2; ++b)
    for (int a = 0; a < 2; ++a) {
      const double node = local[static_cast<std::size_t>(j + b) * static_cast<std::size_t>(local_nx) + static_cast<std::size_t>(i + a)];
      const double w = (a ? fu : 1.0 - fu) * (b ? fv : 1.0 - fv);
      if (std::isnan(node) || w <= 0.0) continue;
      sum += w * node, weight += w;
    }
  if (!(weight > 1e-9)) return std::nullopt;
  return sum / weight;
}

ExcessMaterial measure_excess(const PreparedCloud& templ, const Cloud& scene_in_template, const ExcessSettings& settings) {
  ExcessMaterial out;
  const auto& T = templ.impl();
  if (T.fine.empty() || scene_in_template.empty()) return out;
  // 1. Every scene point's signed distance along the normal of its nearest template point;
  //    the candidates are those above the threshold.
  std::vector<int> owner(scene_in_template.size(), -1);
  std::vector<float> height(scene_in_template.size(), 0.0f);
  detail::parallel_for(scene_in_template.size(), detail::thread_count(0), [&](std::size_t, std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      const auto& p = scene_in_template.points[i];
      const auto [j, d2] = T.nearest_any(p);
      if (j < 0) continue;
      const auto k = static_cast<std::size_t>(j);
      owner[i] = j;
      height[i] = T.fine.normals[k].dot(p - T.fine.points[k]);
    }
  });
  // 1b. The casting's own surface: with a form deviation of up to +-F the body itself stands up
  //     to F over the nominal, and measured against the nominal it would be "material" (0.5 mm
  //     of it over a whole face beside a riser). The offsets of the points on the template's
  //     upward faces within F of it give a plane of offsets; material stands out of that.
  if (settings.form_deviation_mm > 0.0)
    out.form = settings.face != nullptr ? *settings.face
                                        : fit_form_offset(T, scene_in_template, owner, height, settings.form_deviation_mm,
                                                          settings.threshold_mm, settings.max_height_mm);
  const auto candidate = [&](std::size_t i) {
    const auto& p = scene_in_template.points[i];
    return owner[i] >= 0 && height[i] - out.form.at(p.x(), p.y()) > settings.threshold_mm &&
           height[i] <= settings.max_height_mm && (p.array() >= settings.material_min_mm.array()).all() &&
           (p.array() <= settings.material_max_mm.array()).all();
  };
  std::vector<std::size_t> cand;
  for (std::size_t i = 0; i < owner.size(); ++i)
    if (candidate(i)) cand.push_back(i);
  if (cand.empty()) return out;

  // 2. Cleaning: Euclidean clusters; small ones are noise (speckle, flying pixels).
  std::vector<Eigen::Vector3f> cpts;
  cpts.reserve(cand.size());
  for (auto i : cand) cpts.push_back(scene_in_template.points[i]);
  const auto pc = detail::to_pcl(cpts);
  auto tree = std::make_shared<pcl::search::KdTree<pcl::PointXYZ>>(false);
  tree->setInputCloud(pc);
  const double tol = settings.cluster_tolerance_mm > 0 ? settings.cluster_tolerance_mm : 3.0 * std::max(0.2, templ.fine_spacing());
  pcl::EuclideanClusterExtraction<pcl::PointXYZ> ec;
  ec.setClusterTolerance(tol);
  ec.setMinClusterSize(std::max(1, settings.min_cluster_points));
  ec.setMaxClusterSize(std::numeric_limits<int>::max());
  ec.setSearchMethod(tree);
  ec.setInputCloud(pc);
  std::vector<pcl::PointIndices> clusters;
  ec.extract(clusters);

  // 3. Measure. Each template point stands for a patch of surface (area from its local
  //    spacing). A patch carries material when the scene point nearest to its centre, dropped
  //    along the normal onto the template (its foot), is material, and then the patch's height
  //    is that point's: nearest-neighbour resampling of the scan onto the template's patches.
  //    Counting only the patches that have a material point of their own (and filling holes
  //    inside) loses the rim: a scan voxelized in the fixture frame, at the template's pitch but
  //    not on its grid, leaves patches without a point of their own, and along the rim they
  //    cannot be told from outside; a riser's footprint comes out 2-10 % small (test
  //    Excess.ADiscSampledOnAnotherGridHasItsWholeFootprint).
  std::vector<char> material(scene_in_template.size(), 0);
  for (const auto& c : clusters)
    for (const auto idx : c.indices) {
      const auto i = cand[static_cast<std::size_t>(idx)];
      material[i] = 1;
      out.points.push_back(scene_in_template.points[i]);
      out.heights_mm.push_back(height[i]);
      out.max_height_mm = std::max(out.max_height_mm, static_cast<double>(height[i]));
    }
  if (out.points.empty()) return out;
  std::vector<Eigen::Vector3f> feet;
  std::vector<std::size_t> foot_of;  // scene point of each foot
  feet.reserve(scene_in_template.size());
  foot_of.reserve(scene_in_template.size());
  for (std::size_t i = 0; i < scene_in_template.size(); ++i) {
    if (owner[i] < 0) continue;
    feet.push_back(scene_in_template.points[i] - height[i] * T.fine.normals[static_cast<std::size_t>(owner[i])]);
    foot_of.push_back(i);
  }
  const auto feet_tree = detail::make_tree(feet);
  // The patches to decide: those within reach of a material point's foot. Farther than reach
  // from every foot is a patch the scan did not see (a shadow): no material is claimed there.
  const double spacing = std::max(1e-6, templ.fine_spacing());
  const auto reach = static_cast<float>(1.5 * spacing);
  std::vector<char> near_material(T.fine.size(), 0);
  pcl::Indices nn;
  std::vector<float> d2;
  for (std::size_t f = 0; f < feet.size(); ++f) {
    if (!material[foot_of[f]]) continue;
    pcl::PointXYZ q;
    q.getVector3fMap() = feet[f];
    T.fine_tree->radiusSearch(q, reach, nn, d2);
    for (const auto m : nn) near_material[static_cast<std::size_t>(m)] = 1;
  }
  // Patch area: the square of the mean distance to the 4 nearest template points (exact
  // on the voxel grid the template is resampled to).
  constexpr int k = 4;
  pcl::Indices knn(k + 1);
  std::vector<float> kd2(k + 1);
  for (std::size_t j = 0; j < T.fine.size(); ++j) {
    if (!near_material[j]) continue;
    const auto [f, fd2] = detail::nearest(*feet_tree, T.fine.points[j]);
    if (f < 0 || fd2 > reach * reach) continue;
    const auto i = foot_of[static_cast<std::size_t>(f)];
    if (!material[i]) continue;
    pcl::PointXYZ q;
    q.getVector3fMap() = T.fine.points[j];
    const int found = T.fine_tree->nearestKSearch(q, k + 1, knn, kd2);
    double sum = 0.0;
    for (int m = 1; m < found; ++m) sum += std::sqrt(static_cast<double>(kd2[static_cast<std::size_t>(m)]));
    const double side = found > 1 ? sum / (found - 1) : 0.0;
    out.footprint_mm2 += side * side;
    out.volume_mm3 += side * side * height[i];
  }
  return out;
}

}  // namespace fettle::vision
