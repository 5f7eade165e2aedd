// The error budget applied to the simulated world (fettle/sim/errors.hpp).
#include "fettle/sim/errors.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>

#include "casting_model.hpp"

namespace fettle::sim {

namespace {
constexpr std::uint64_t kSalt = 0xE5507B;

/// A unit vector in a uniformly random direction.
Vec3 random_direction(Rng& rng) {
  const double z = rng.uniform(-1.0, 1.0);
  const double a = rng.uniform(0.0, 2.0 * std::numbers::pi);
  const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
  return {r * std::cos(a), r * std::sin(a), z};
}

Vec3 hand_eye_pivot_in_camera(const config::ErrorBudget& budget, const ScannerConfig& nominal) {
  if (budget.hand_eye_pivot == "camera") return Vec3::Zero();
  // The fixture's origin (base frame origin: the table top under the slide's mid position) seen
  // from the camera at the middle of its photo positions, where a calibration's target sits.
  double mid = 0.0;
  if (!nominal.photo_positions_mm.empty()) {
    const auto [lo, hi] = std::minmax_element(nominal.photo_positions_mm.begin(), nominal.photo_positions_mm.end());
    mid = 0.5 * (*lo + *hi);
  }
  return nominal.T_base_camera(mid).inverse() * Vec3::Zero();
}
}  // namespace

CellErrors draw_cell_errors(const config::ErrorBudget& budget, std::uint64_t cell_seed, const ScannerConfig& nominal) {
  CellErrors e;
  e.budget = budget;
  e.cell_seed = cell_seed;
  Rng rng(cell_seed, kSalt);
  // Hand-eye: a rigid error of exactly the budget's size in random directions: the translation
  // is the error at the pivot, the rotation turns about it.
  const Vec3 t = random_direction(rng) * budget.hand_eye_mm;
  const Vec3 axis = random_direction(rng);
  e.hand_eye_pivot_camera = hand_eye_pivot_in_camera(budget, nominal);
  const Eigen::Matrix3d R = Eigen::AngleAxisd(budget.hand_eye_deg * std::numbers::pi / 180.0, axis).toRotationMatrix();
  e.T_nominal_true = Transform::Identity();
  e.T_nominal_true.linear() = R;
  e.T_nominal_true.translation() = t + e.hand_eye_pivot_camera - R * e.hand_eye_pivot_camera;
  // Intrinsics: focal length off by the budget's share (either sign), centre by its size.
  e.intrinsics_true = nominal.intrinsics;
  const double sign = rng.uniform() < 0.5 ? -1.0 : 1.0;
  e.intrinsics_true.fx *= 1.0 + sign * budget.intrinsics_focal_pct / 100.0;
  e.intrinsics_true.fy *= 1.0 + sign * budget.intrinsics_focal_pct / 100.0;
  const double ca = rng.uniform(0.0, 2.0 * std::numbers::pi);
  e.intrinsics_true.cx += budget.intrinsics_center_px * std::cos(ca);
  e.intrinsics_true.cy += budget.intrinsics_center_px * std::sin(ca);
  // Path bias: a constant offset of the budget's size.
  e.path_bias_mm = random_direction(rng) * budget.path_bias_mm;
  // Smooth depth error: 8 plane waves with wavelengths around 2 pi x the correlation length; the
  // sum's RMS is depth_correlated_mm.
  if (budget.depth_correlated_mm > 0.0) {
    constexpr int kWaves = 8;
    for (int k = 0; k < kWaves; ++k) {
      const double dir = rng.uniform(0.0, std::numbers::pi);
      const double wavelength = 2.0 * std::numbers::pi * budget.depth_correlation_px * rng.uniform(0.75, 1.25);
      const double kmag = 2.0 * std::numbers::pi / wavelength;
      e.depth_waves.push_back({kmag * std::cos(dir), kmag * std::sin(dir), rng.uniform(0.0, 2.0 * std::numbers::pi),
                               budget.depth_correlated_mm * std::sqrt(2.0 / kWaves)});
    }
  }
  return e;
}

double CellErrors::hand_eye_error_at_pivot_mm() const {
  return (T_nominal_true * hand_eye_pivot_camera - hand_eye_pivot_camera).norm();
}

double CellErrors::slide_error_mm(std::uint64_t seed, std::size_t view) const {
  if (budget.slide_repeatability_mm <= 0.0) return 0.0;
  Rng rng(cell_seed ^ kSalt, seed, view);
  return budget.slide_repeatability_mm * rng.gaussian();
}

double CellErrors::correlated_depth_mm(double u, double v) const {
  double s = 0.0;
  for (const auto& w : depth_waves) s += w.amplitude_mm * std::sin(w.kx * u + w.ky * v + w.phase);
  return s;
}

void CellErrors::add_correlated_depth(RangeImageF32& range) const {
  if (depth_waves.empty()) return;
  for (std::size_t k = 0; k < range.data.size(); ++k)
    if (std::isfinite(range.data[k]))
      range.data[k] += static_cast<float>(correlated_depth_mm(static_cast<double>(k % range.width),
                                                              static_cast<double>(k / range.width)));
}

double CellErrors::wheel_wear_mm_per_cm3(const std::string& tool) const {
  std::uint64_t h = 1469598103934665603ULL;  // FNV-1a of the name: the draw does not depend on the tools' order
  for (const unsigned char ch : tool) h = (h ^ ch) * 1099511628211ULL;
  Rng rng(cell_seed, kSalt, h);
  return budget.wheel_wear_mm_per_cm3 * (1.0 + budget.wheel_wear_spread_pct / 100.0 * rng.uniform(-1.0, 1.0));
}

nlohmann::json CellErrors::to_json() const {
  const auto& b = budget;
  const Eigen::AngleAxisd aa(T_nominal_true.linear());
  return {{"file", b.source.string()},
          {"cell_seed", cell_seed},
          {"budget",
           {{"hand_eye_mm", b.hand_eye_mm}, {"hand_eye_deg", b.hand_eye_deg}, {"hand_eye_pivot", b.hand_eye_pivot},
            {"slide_repeatability_mm", b.slide_repeatability_mm}, {"intrinsics_focal_pct", b.intrinsics_focal_pct},
            {"intrinsics_center_px", b.intrinsics_center_px}, {"path_noise_mm", b.path_noise_mm},
            {"path_bias_mm", b.path_bias_mm}, {"tcp_length_mm", b.tcp_length_mm}, {"depth_noise_mm", b.depth_noise_mm},
            {"depth_correlated_mm", b.depth_correlated_mm}, {"depth_correlation_px", b.depth_correlation_px},
            {"form_deviation_mm", b.form_deviation_mm ? nlohmann::json(*b.form_deviation_mm) : nlohmann::json(nullptr)},
            {"wheel_wear_mm_per_cm3", b.wheel_wear_mm_per_cm3},
            {"wheel_wear_spread_pct", b.wheel_wear_spread_pct},
            {"wheel_worn_start_mm", b.wheel_worn_start_mm}}},
          {"drawn",
           {{"hand_eye_translation_mm",
             {T_nominal_true.translation().x(), T_nominal_true.translation().y(), T_nominal_true.translation().z()}},
            {"hand_eye_pivot_camera_mm", {hand_eye_pivot_camera.x(), hand_eye_pivot_camera.y(), hand_eye_pivot_camera.z()}},
            {"hand_eye_error_at_pivot_mm", hand_eye_error_at_pivot_mm()},
            {"hand_eye_rotation_deg", aa.angle() * 180.0 / std::numbers::pi},
            {"hand_eye_axis", {aa.axis().x(), aa.axis().y(), aa.axis().z()}},
            {"intrinsics_true", {{"fx", intrinsics_true.fx}, {"fy", intrinsics_true.fy}, {"cx", intrinsics_true.cx}, {"cy", intrinsics_true.cy}}},
            {"path_bias_mm", {path_bias_mm.x(), path_bias_mm.y(), path_bias_mm.z()}},
            {"depth_waves", depth_waves.size()}}}};
}

ScannerConfig true_scanner(const ScannerConfig& nominal, const CellErrors& errors) {
  ScannerConfig c = nominal;
  c.T_slide_camera = nominal.T_slide_camera * errors.T_nominal_true;
  c.intrinsics = errors.intrinsics_true;
  c.noise.sigma_z_mm = errors.budget.depth_noise_mm;
  return c;
}

CellCapture capture_as_cell(const Scanner& scanner, const ScannerConfig& nominal, const CellErrors& errors,
                            const Casting& casting, double slide_mm, std::uint64_t seed, std::size_t view) {
  CellCapture out{scanner.capture(casting, slide_mm + errors.slide_error_mm(seed, view), view),
                  nominal.T_base_camera(slide_mm), slide_mm};
  const auto& K = nominal.intrinsics;
  const auto& T = errors.intrinsics_true;
  const bool same_intrinsics = K.fx == T.fx && K.fy == T.fy && K.cx == T.cx && K.cy == T.cy;
  if (same_intrinsics && errors.depth_waves.empty()) return out;
  auto& c = out.capture;
  errors.add_correlated_depth(c.range);
  const auto W = static_cast<std::size_t>(c.range.width);
  for (std::size_t k = 0; k < c.range.data.size() && k < c.cloud.points.size(); ++k) {
    const float z = c.range.data[k];
    if (!std::isfinite(z)) continue;
    const double u = static_cast<double>(k % W), v = static_cast<double>(k / W);
    c.cloud.points[k] = (K.ray(u, v) * static_cast<double>(z)).cast<float>();
  }
  return out;
}

StatedAccuracy stated_accuracy(const config::PartRecipe& recipe, const config::ErrorBudget& budget,
                               const ScannerConfig& nominal) {
  StatedAccuracy a;
  for (const auto& r : recipe.regions) {
    const Vec3 at(r.roi_center_mm[0], r.roi_center_mm[1], r.roi_center_mm[2]);
    a.lever_mm = std::max(a.lever_mm, budget.hand_eye_pivot == "camera"
                                          ? (at - nominal.T_base_camera(0.0).translation()).norm()
                                          : at.norm());
    for (const double slide : nominal.photo_positions_mm) {
      const Vec3 p = nominal.T_base_camera(slide).inverse() * at;  // camera frame, z along the axis
      a.scanner_mm = std::max(a.scanner_mm, budget.intrinsics_center_px * p.z() / nominal.intrinsics.fx +
                                                budget.intrinsics_focal_pct / 100.0 * p.head<2>().norm());
    }
  }
  a.hand_eye_mm = budget.hand_eye_mm + budget.hand_eye_deg * std::numbers::pi / 180.0 * a.lever_mm;
  a.slide_mm = budget.slide_repeatability_mm;
  a.robot_mm = budget.path_bias_mm;
  a.tcp_mm = budget.tcp_length_mm;
  a.repeatability_mm = 3.0 * budget.path_noise_mm;
  return a;
}

void apply_to_grinding(const CellErrors& errors, GrindOptions& options) {
  options.path_noise_mm = errors.budget.path_noise_mm;
  options.path_bias_mm = errors.path_bias_mm;
  options.tcp_length_error_mm = errors.budget.tcp_length_mm;
}

}  // namespace fettle::sim
