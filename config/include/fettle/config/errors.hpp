#pragma once
// The simulator's error budget: the errors a real cell meets that the simulated world injects
// (`fettle-sim trial --errors FILE`, docs/simulator.md "Error budget"). A TOML file with one
// [errors] table; every key optional, 0 = off, units in the names. config/sim/errors-ideal.toml
// is the simulator's own world, config/sim/errors-realistic.toml a real cell's.
#include <filesystem>
#include <optional>
#include <string>

namespace fettle::config {

struct ErrorBudget {
  double hand_eye_mm = 0.0;   ///< the true camera pose is off the calibration by this translation ...
  double hand_eye_deg = 0.0;  ///< ... and this rotation (random directions, drawn once per cell) ...
  /// ... turning about the fixture's origin ("fixture": where a calibration's target sits, so the
  /// error there is the translation alone, as a calibration fitted there is right there to within
  /// its residual) or about the camera's optical centre ("camera": the rotation's lever is the
  /// working distance, 0.05 deg x 600 mm = 0.52 mm at the part, as with a calibration taken
  /// elsewhere than the part sits).
  std::string hand_eye_pivot = "fixture";
  double slide_repeatability_mm = 0.0;  ///< per capture, the slide's true position is off by N(0, this)
  double intrinsics_focal_pct = 0.0;    ///< the scanner's true focal length is off by this (once per cell)
  double intrinsics_center_px = 0.0;    ///< and its principal point by this
  double path_noise_mm = 0.0;           ///< the executed path: N(0, this) per axis per pose ...
  double path_bias_mm = 0.0;            ///< ... plus a constant offset of this size in a random direction per cell
  double tcp_length_mm = 0.0;           ///< the tool is this much longer than the robot is told
  double depth_noise_mm = 0.0;          ///< i.i.d. depth noise sigma at 600 mm
  double depth_correlated_mm = 0.0;     ///< a smooth depth error of this RMS ...
  double depth_correlation_px = 0.0;    ///< ... with this correlation length in pixels
  double interreflection_mm = 0.0;      ///< extra depth error in concave corners (not modelled yet: refused)
  std::optional<double> form_deviation_mm;  ///< the body's smooth form deviation; replaces the recipe's
  double wheel_wear_mm_per_cm3 = 0.0;   ///< a tool's radius shrinks this much per cm3 it removed; the cell is not told
  /// Each wheel's true rate is off wheel_wear_mm_per_cm3 by up to this share (uniform, either
  /// sign, drawn once per cell and tool): one wheel is not another, and a rate the recipe states
  /// is its maker's, not this wheel's.
  double wheel_wear_spread_pct = 0.0;
  /// Every wheel is this much smaller than its nominal radius when the run starts (a cell whose
  /// wheels ground castings before; the cell is not told): the worn-wheel case without grinding
  /// dozens of castings first. A wheel changed during the run is new (0).
  double wheel_worn_start_mm = 0.0;
  std::filesystem::path source;         ///< the file read (absolute)
};

/// Reads an error budget file; throws ConfigError naming file:line and the key.
ErrorBudget load_error_budget(const std::filesystem::path& file);

}  // namespace fettle::config
