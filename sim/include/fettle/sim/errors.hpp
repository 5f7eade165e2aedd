#pragma once
// The error budget applied to the simulated world (config::ErrorBudget; docs/simulator.md,
// "Error budget"). What is drawn once per cell (from `cell_seed`: the same for every casting of
// a run, as a real calibration error is) and what per capture; the scanner renders the true
// world, and the cell decodes what it gets with what it believes (the calibration file's pose,
// the nominal intrinsics, the commanded slide position).
#include <cstdint>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "fettle/config/errors.hpp"
#include "fettle/sim/sim.hpp"

namespace fettle::sim {

/// The errors of one cell, drawn from its seed.
struct CellErrors {
  config::ErrorBudget budget;
  std::uint64_t cell_seed = 1;
  Transform T_nominal_true = Transform::Identity();  ///< the true camera frame in the believed one (hand-eye error)
  Vec3 hand_eye_pivot_camera = Vec3::Zero();          ///< the point the hand-eye rotation turns about (believed camera frame)
  CameraIntrinsics intrinsics_true;                   ///< what the scanner really has
  Vec3 path_bias_mm = Vec3::Zero();                   ///< the executed path's constant offset (base frame)
  /// The smooth depth error: sum of plane waves over the pixel grid.
  struct Wave {
    double kx = 0.0, ky = 0.0, phase = 0.0, amplitude_mm = 0.0;
  };
  std::vector<Wave> depth_waves;

  /// How far the hand-eye error moves the pivot's point (= the budget's hand_eye_mm).
  [[nodiscard]] double hand_eye_error_at_pivot_mm() const;
  /// The slide's true position error for capture `view` of casting `seed` (mm).
  [[nodiscard]] double slide_error_mm(std::uint64_t seed, std::size_t view) const;
  /// The smooth depth error at pixel (u, v), mm.
  [[nodiscard]] double correlated_depth_mm(double u, double v) const;
  /// Adds the smooth depth error to every valid pixel of a range image (Z, mm).
  void add_correlated_depth(RangeImageF32& range) const;
  /// The true wear rate of the cell's wheel `tool` (mm of radius per cm3 removed): the budget's
  /// rate off by up to its spread, the same for every casting of the run.
  [[nodiscard]] double wheel_wear_mm_per_cm3(const std::string& tool) const;
  /// Everything drawn, for the truth JSON.
  [[nodiscard]] nlohmann::json to_json() const;
};

/// Draws a cell's errors; `nominal` is the scanner as the cell believes it is (the intrinsics
/// it decodes with; its pose and photo positions place the hand-eye error's pivot).
CellErrors draw_cell_errors(const config::ErrorBudget& budget, std::uint64_t cell_seed, const ScannerConfig& nominal);

/// The scanner as it really is: camera mounted with the hand-eye error, true intrinsics, the
/// budget's depth noise (sigma 0: no i.i.d. noise).
ScannerConfig true_scanner(const ScannerConfig& nominal, const CellErrors& errors);

/// One capture as the cell gets it, beside the truth.
struct CellCapture {
  Capture capture;                  ///< cloud and range as decoded by the cell; `truth` is the truth
  Transform believed_T_base_camera;  ///< the calibration file's pose at the commanded slide position
  double commanded_slide_mm = 0.0;
};

/// Capture `view` of casting `seed` at commanded slide position `slide_mm`, as the cell gets it:
/// rendered by `scanner` (the true one) at the slide's true position, the smooth depth error
/// added, unprojected with the nominal intrinsics, labelled with the believed camera pose.
CellCapture capture_as_cell(const Scanner& scanner, const ScannerConfig& nominal, const CellErrors& errors,
                            const Casting& casting, double slide_mm, std::uint64_t seed, std::size_t view);

/// What an integrator who measured a cell with this budget's errors would state as its
/// accuracies ([safety]; docs/compensation.md, "What every path keeps"): each the error's
/// largest size at the recipe's regions, the calibration's as an end-to-end check of the cell
/// sees it (the scan's error at the part, whatever part of the chain it comes from).
struct StatedAccuracy {
  double lever_mm = 0.0;     ///< the farthest region from the hand-eye rotation's pivot
  double hand_eye_mm = 0.0;  ///< the hand-eye's translation plus its rotation over the lever
  /// The scanner's intrinsics: the principal point's error over a pixel's footprint at the
  /// region plus the focal length's share of its distance from the optical axis, at the worst
  /// region and view (the same for every casting, a calibration error like the hand-eye's).
  double scanner_mm = 0.0;
  double slide_mm = 0.0;  ///< the slide's repeatability
  [[nodiscard]] double calibration_mm() const { return hand_eye_mm + scanner_mm + slide_mm; }
  double robot_mm = 0.0;          ///< the path's offset (drawn in a random direction)
  double tcp_mm = 0.0;            ///< the TCP's length error (along the tool's axis)
  double repeatability_mm = 0.0;  ///< ISO 9283: 3 sigma of the path's noise
};
StatedAccuracy stated_accuracy(const config::PartRecipe& recipe, const config::ErrorBudget& budget,
                               const ScannerConfig& nominal);

/// The grinding options the budget implies (path noise, the cell's path bias, TCP length error).
void apply_to_grinding(const CellErrors& errors, GrindOptions& options);

}  // namespace fettle::sim
