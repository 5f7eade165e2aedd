#pragma once
// Robust geometric fits used by the planner: RANSAC plane and 3-D line, and the direct
// least-squares ellipse (Fitzgibbon, Pilu & Fisher 1999, in the numerically stable form of
// Halir & Flusser 1998) inside RANSAC followed by an inlier refit.
// All fits are deterministic for a given `seed`.
#include <cstdint>
#include <functional>
#include <optional>
#include <vector>

#include <Eigen/Core>

#include "fettle/core/geometry.hpp"

namespace fettle::planning {

struct RansacOptions {
  double inlier_mm = 0.5;         ///< a point within this distance of the model is an inlier
  int iterations = 200;
  std::uint64_t seed = 1;
};

/// Plane a·x + b·y + c·z + d = 0 with (a, b, c) a unit normal.
struct Plane {
  Vec3 normal = Vec3::UnitZ();
  double d = 0.0;
  std::size_t inliers = 0;
  [[nodiscard]] double signed_distance(const Vec3& p) const { return normal.dot(p) + d; }
  [[nodiscard]] Vec3 project(const Vec3& p) const { return p - signed_distance(p) * normal; }
};

/// Line through `point` along the unit `direction`.
struct Line {
  Vec3 point = Vec3::Zero();
  Vec3 direction = Vec3::UnitX();
  std::size_t inliers = 0;
  [[nodiscard]] double distance(const Vec3& p) const {
    const Vec3 v = p - point;
    return (v - v.dot(direction) * direction).norm();
  }
};

/// General conic A x² + B xy + C y² + D x + E y + F = 0 (coefficients normalised to unit norm).
struct Conic {
  double A = 0, B = 0, C = 0, D = 0, E = 0, F = 0;
  std::size_t inliers = 0;

  [[nodiscard]] double value(const Eigen::Vector2d& p) const {
    return A * p.x() * p.x() + B * p.x() * p.y() + C * p.y() * p.y() + D * p.x() + E * p.y() + F;
  }
  [[nodiscard]] Eigen::Vector2d gradient(const Eigen::Vector2d& p) const {
    return {2 * A * p.x() + B * p.y() + D, B * p.x() + 2 * C * p.y() + E};
  }
  /// Approximate (Sampson) geometric distance |F| / |∇F|.
  [[nodiscard]] double sampson_distance(const Eigen::Vector2d& p) const;
  /// True if the conic is a real, non-degenerate ellipse (B² − 4AC < 0).
  [[nodiscard]] bool is_ellipse() const;
};

/// Centre / semi-axes / rotation form of an ellipse.
struct EllipseGeometry {
  Eigen::Vector2d center = Eigen::Vector2d::Zero();
  double semi_major = 0.0, semi_minor = 0.0;
  double angle_rad = 0.0;  ///< rotation of the major axis from +x
  /// Point at parameter t: center + R(angle) (a cos t, b sin t).
  [[nodiscard]] Eigen::Vector2d point(double t) const;
};
std::optional<EllipseGeometry> ellipse_geometry(const Conic& conic);

/// Least-squares plane through all points (PCA). nullopt for < 3 points or collinear points.
std::optional<Plane> fit_plane_lsq(const std::vector<Vec3>& points);
/// RANSAC plane then a least-squares refit on the inliers.
std::optional<Plane> fit_plane_ransac(const std::vector<Vec3>& points, const RansacOptions& options = {});
/// The same, where point i is an inlier of a plane with unit normal n only if it is near the
/// plane and `admit(i, n)` holds: the fit finds the plane of the points that belong to it by
/// more than their position (a parting line's fin against a wall the plane cuts, not a face
/// the plane lies on). The refit and `inliers` use the admitted inliers.
std::optional<Plane> fit_plane_ransac(const std::vector<Vec3>& points, const RansacOptions& options,
                                      const std::function<bool(std::size_t, const Vec3&)>& admit);

std::optional<Line> fit_line_lsq(const std::vector<Vec3>& points);
std::optional<Line> fit_line_ransac(const std::vector<Vec3>& points, const RansacOptions& options = {});

/// Fitzgibbon's direct least-squares ellipse fit (always an ellipse for non-degenerate data).
std::optional<Conic> fit_ellipse_direct(const std::vector<Eigen::Vector2d>& points);
/// RANSAC over 6-point direct fits (Sampson distance), then refits on the inliers.
std::optional<Conic> fit_ellipse_ransac(const std::vector<Eigen::Vector2d>& points, const RansacOptions& options = {});

}  // namespace fettle::planning
