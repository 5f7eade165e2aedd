// Robust fits: RANSAC plane / line, direct least-squares ellipse (Fitzgibbon) in RANSAC.
#include "fettle/planning/fit.hpp"

#include <algorithm>
#include <cmath>
#include <random>

#include <Eigen/Eigenvalues>
#include <Eigen/LU>

namespace fettle::planning {
namespace {

/// Indices of at most `max_count` points spread evenly over the input (for scoring).
std::vector<std::size_t> scoring_subset(std::size_t n, std::size_t max_count = 3000) {
  std::vector<std::size_t> idx;
  const std::size_t step = n > max_count ? (n + max_count - 1) / max_count : 1;
  for (std::size_t i = 0; i < n; i += step) idx.push_back(i);
  return idx;
}

template <std::size_t K>
bool draw_sample(std::mt19937_64& rng, std::size_t n, std::array<std::size_t, K>& out) {
  if (n < K) return false;
  std::uniform_int_distribution<std::size_t> pick(0, n - 1);
  for (std::size_t k = 0; k < K; ++k) {
    bool fresh = false;
    for (int attempt = 0; attempt < 20 && !fresh; ++attempt) {
      out[k] = pick(rng);
      fresh = std::find(out.begin(), out.begin() + static_cast<std::ptrdiff_t>(k), out[k]) ==
              out.begin() + static_cast<std::ptrdiff_t>(k);
    }
    if (!fresh) return false;
  }
  return true;
}

}  // namespace

// --- plane ------------------------------------------------------------------------------------

std::optional<Plane> fit_plane_lsq(const std::vector<Vec3>& points) {
  if (points.size() < 3) return std::nullopt;
  Vec3 mean = Vec3::Zero();
  for (const auto& p : points) mean += p;
  mean /= static_cast<double>(points.size());
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const auto& p : points) cov += (p - mean) * (p - mean).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);
  const auto ev = es.eigenvalues();
  if (ev(1) <= 1e-12 * std::max(1.0, ev(2))) return std::nullopt;  // collinear
  Plane plane;
  plane.normal = es.eigenvectors().col(0).normalized();
  plane.d = -plane.normal.dot(mean);
  plane.inliers = points.size();
  return plane;
}

std::optional<Plane> fit_plane_ransac(const std::vector<Vec3>& points, const RansacOptions& options) {
  return fit_plane_ransac(points, options, {});
}

std::optional<Plane> fit_plane_ransac(const std::vector<Vec3>& points, const RansacOptions& options,
                                      const std::function<bool(std::size_t, const Vec3&)>& admit) {
  if (points.size() < 3) return std::nullopt;
  const auto inlier = [&](const Plane& plane, std::size_t i) {
    return std::abs(plane.signed_distance(points[i])) <= options.inlier_mm && (!admit || admit(i, plane.normal));
  };
  std::mt19937_64 rng(options.seed);
  const auto subset = scoring_subset(points.size());
  std::optional<Plane> best;
  std::size_t best_count = 0;
  // With an admission test a hypothesis counts only when its own three points are admitted: the
  // points the plane is for may be a small share (a fin among a body's form deviation, 1 point
  // in 7), and samples of the rest make planes that admit nothing. Up to 100 draws per
  // hypothesis are made to find `iterations` of them.
  const long max_draws = admit ? 100L * options.iterations : options.iterations;
  int hypotheses = 0;
  for (long draw = 0; draw < max_draws && hypotheses < options.iterations; ++draw) {
    std::array<std::size_t, 3> s{};
    if (!draw_sample(rng, points.size(), s)) continue;
    const Vec3 nrm = (points[s[1]] - points[s[0]]).cross(points[s[2]] - points[s[0]]);
    if (nrm.norm() < 1e-9) continue;
    Plane cand{nrm.normalized(), 0.0, 0};
    cand.d = -cand.normal.dot(points[s[0]]);
    if (admit && !(admit(s[0], cand.normal) && admit(s[1], cand.normal) && admit(s[2], cand.normal))) continue;
    ++hypotheses;
    std::size_t count = 0;
    for (auto i : subset) count += inlier(cand, i) ? 1 : 0;
    if (count > best_count) best_count = count, best = cand;
  }
  if (!best) return admit ? std::nullopt : fit_plane_lsq(points);
  for (int refine = 0; refine < 2; ++refine) {
    std::vector<Vec3> inl;
    for (std::size_t i = 0; i < points.size(); ++i)
      if (inlier(*best, i)) inl.push_back(points[i]);
    auto refit = fit_plane_lsq(inl);
    if (!refit) break;
    // the refit keeps the sampled plane's orientation (admit may depend on the normal's sign)
    if (admit && refit->normal.dot(best->normal) < 0) refit->normal = -refit->normal, refit->d = -refit->d;
    best = refit;
  }
  std::size_t count = 0;
  for (std::size_t i = 0; i < points.size(); ++i) count += inlier(*best, i) ? 1 : 0;
  best->inliers = count;
  return best;
}

// --- line ---------------------------------------------------------------------------------------

std::optional<Line> fit_line_lsq(const std::vector<Vec3>& points) {
  if (points.size() < 2) return std::nullopt;
  Vec3 mean = Vec3::Zero();
  for (const auto& p : points) mean += p;
  mean /= static_cast<double>(points.size());
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const auto& p : points) cov += (p - mean) * (p - mean).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);
  if (es.eigenvalues()(2) <= 1e-12) return std::nullopt;
  return Line{mean, es.eigenvectors().col(2).normalized(), points.size()};
}

std::optional<Line> fit_line_ransac(const std::vector<Vec3>& points, const RansacOptions& options) {
  if (points.size() < 2) return std::nullopt;
  std::mt19937_64 rng(options.seed);
  const auto subset = scoring_subset(points.size());
  std::optional<Line> best;
  std::size_t best_count = 0;
  for (int it = 0; it < options.iterations; ++it) {
    std::array<std::size_t, 2> s{};
    if (!draw_sample(rng, points.size(), s)) continue;
    const Vec3 dir = points[s[1]] - points[s[0]];
    if (dir.norm() < 1e-9) continue;
    Line cand{points[s[0]], dir.normalized(), 0};
    std::size_t count = 0;
    for (auto i : subset) count += cand.distance(points[i]) <= options.inlier_mm ? 1 : 0;
    if (count > best_count) best_count = count, best = cand;
  }
  if (!best) return fit_line_lsq(points);
  for (int refine = 0; refine < 2; ++refine) {
    std::vector<Vec3> inl;
    for (const auto& p : points)
      if (best->distance(p) <= options.inlier_mm) inl.push_back(p);
    auto refit = fit_line_lsq(inl);
    if (!refit) break;
    best = refit;
  }
  std::size_t count = 0;
  for (const auto& p : points) count += best->distance(p) <= options.inlier_mm ? 1 : 0;
  best->inliers = count;
  return best;
}

// --- conic / ellipse ------------------------------------------------------------------------------

double Conic::sampson_distance(const Eigen::Vector2d& p) const {
  const double g = gradient(p).norm();
  const double f = std::abs(value(p));
  return g > 1e-12 ? f / g : (f < 1e-12 ? 0.0 : std::numeric_limits<double>::infinity());
}

bool Conic::is_ellipse() const {
  if (B * B - 4 * A * C >= 0) return false;
  return ellipse_geometry(*this).has_value();
}

Eigen::Vector2d EllipseGeometry::point(double t) const {
  const double c = std::cos(angle_rad), s = std::sin(angle_rad);
  const double x = semi_major * std::cos(t), y = semi_minor * std::sin(t);
  return center + Eigen::Vector2d(c * x - s * y, s * x + c * y);
}

std::optional<EllipseGeometry> ellipse_geometry(const Conic& q) {
  Eigen::Matrix2d H;
  H << 2 * q.A, q.B, q.B, 2 * q.C;
  if (std::abs(H.determinant()) < 1e-15) return std::nullopt;
  EllipseGeometry e;
  e.center = H.inverse() * Eigen::Vector2d(-q.D, -q.E);
  const double f0 = q.value(e.center);
  Eigen::Matrix2d M;
  M << q.A, q.B / 2, q.B / 2, q.C;
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> es(M);
  const double l0 = es.eigenvalues()(0), l1 = es.eigenvalues()(1);
  if (l0 * l1 <= 0) return std::nullopt;
  const double a0 = -f0 / l0, a1 = -f0 / l1;
  if (a0 <= 0 || a1 <= 0) return std::nullopt;
  // the larger semi-axis belongs to the eigenvalue with the smaller magnitude
  const bool first_major = std::abs(l0) < std::abs(l1);
  e.semi_major = std::sqrt(first_major ? a0 : a1);
  e.semi_minor = std::sqrt(first_major ? a1 : a0);
  const Eigen::Vector2d axis = es.eigenvectors().col(first_major ? 0 : 1);
  e.angle_rad = std::atan2(axis.y(), axis.x());
  return e;
}

std::optional<Conic> fit_ellipse_direct(const std::vector<Eigen::Vector2d>& points) {
  const std::size_t n = points.size();
  if (n < 5) return std::nullopt;
  // normalise (centre, unit rms radius) for conditioning
  Eigen::Vector2d m = Eigen::Vector2d::Zero();
  for (const auto& p : points) m += p;
  m /= static_cast<double>(n);
  double rms = 0;
  for (const auto& p : points) rms += (p - m).squaredNorm();
  rms = std::sqrt(rms / static_cast<double>(n));
  if (rms < 1e-12) return std::nullopt;
  const double s = rms;
  Eigen::Matrix3d S1 = Eigen::Matrix3d::Zero(), S2 = Eigen::Matrix3d::Zero(), S3 = Eigen::Matrix3d::Zero();
  for (const auto& p : points) {
    const double x = (p.x() - m.x()) / s, y = (p.y() - m.y()) / s;
    const Eigen::Vector3d d1(x * x, x * y, y * y), d2(x, y, 1.0);
    S1 += d1 * d1.transpose();
    S2 += d1 * d2.transpose();
    S3 += d2 * d2.transpose();
  }
  Eigen::FullPivLU<Eigen::Matrix3d> lu(S3);
  if (!lu.isInvertible()) return std::nullopt;
  const Eigen::Matrix3d T = -lu.solve(S2.transpose());
  const Eigen::Matrix3d M = S1 + S2 * T;
  Eigen::Matrix3d Mc;  // C1^-1 * M with C1 = [[0,0,2],[0,-1,0],[2,0,0]]
  Mc.row(0) = M.row(2) / 2.0;
  Mc.row(1) = -M.row(1);
  Mc.row(2) = M.row(0) / 2.0;
  Eigen::EigenSolver<Eigen::Matrix3d> es(Mc);
  int pick = -1;
  double best = std::numeric_limits<double>::infinity();
  for (int k = 0; k < 3; ++k) {
    const Eigen::Vector3d v = es.eigenvectors().col(k).real();
    const double cond = 4 * v(0) * v(2) - v(1) * v(1);
    if (cond > 0 && std::abs(es.eigenvalues()(k).imag()) < 1e-9) {
      // the valid solution has the smallest non-negative eigenvalue
      const double ev = es.eigenvalues()(k).real();
      if (ev < best) best = ev, pick = k;
    }
  }
  if (pick < 0) return std::nullopt;
  const Eigen::Vector3d a1 = es.eigenvectors().col(pick).real();
  const Eigen::Vector3d a2 = T * a1;
  // back to the original coordinates
  const double Ap = a1(0), Bp = a1(1), Cp = a1(2), Dp = a2(0), Ep = a2(1), Fp = a2(2);
  const double s2 = s * s, mx = m.x(), my = m.y();
  Conic c;
  c.A = Ap / s2;
  c.B = Bp / s2;
  c.C = Cp / s2;
  c.D = (-2 * Ap * mx - Bp * my) / s2 + Dp / s;
  c.E = (-Bp * mx - 2 * Cp * my) / s2 + Ep / s;
  c.F = (Ap * mx * mx + Bp * mx * my + Cp * my * my) / s2 - (Dp * mx + Ep * my) / s + Fp;
  double norm = std::sqrt(c.A * c.A + c.B * c.B + c.C * c.C + c.D * c.D + c.E * c.E + c.F * c.F);
  if (!(norm > 0) || !std::isfinite(norm)) return std::nullopt;
  if (c.A < 0) norm = -norm;  // A > 0: the inside of the ellipse is negative
  c.A /= norm, c.B /= norm, c.C /= norm, c.D /= norm, c.E /= norm, c.F /= norm;
  c.inliers = n;
  return c;
}

std::optional<Conic> fit_ellipse_ransac(const std::vector<Eigen::Vector2d>& points, const RansacOptions& options) {
  if (points.size() < 6) return fit_ellipse_direct(points);
  std::mt19937_64 rng(options.seed);
  const auto subset = scoring_subset(points.size());
  std::optional<Conic> best;
  std::size_t best_count = 0;
  std::vector<Eigen::Vector2d> sample(6);
  for (int it = 0; it < options.iterations; ++it) {
    std::array<std::size_t, 6> s{};
    if (!draw_sample(rng, points.size(), s)) continue;
    for (std::size_t k = 0; k < 6; ++k) sample[k] = points[s[k]];
    auto cand = fit_ellipse_direct(sample);
    if (!cand || !cand->is_ellipse()) continue;
    std::size_t count = 0;
    for (auto i : subset) count += cand->sampson_distance(points[i]) <= options.inlier_mm ? 1 : 0;
    if (count > best_count) best_count = count, best = cand;
  }
  if (!best) return fit_ellipse_direct(points);
  for (int refine = 0; refine < 3; ++refine) {
    std::vector<Eigen::Vector2d> inl;
    for (const auto& p : points)
      if (best->sampson_distance(p) <= options.inlier_mm) inl.push_back(p);
    auto refit = fit_ellipse_direct(inl);
    if (!refit || !refit->is_ellipse()) break;
    best = refit;
  }
  std::size_t count = 0;
  for (const auto& p : points) count += best->sampson_distance(p) <= options.inlier_mm ? 1 : 0;
  best->inliers = count;
  return best;
}

}  // namespace fettle::planning
