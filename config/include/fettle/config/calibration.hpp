#pragma once
// Calibration: [calibration] in the cell file names the calibration file, and the
// calibration file itself (camera intrinsics, T_base_camera, T_camera_projector and the
// residuals of the procedures that produced them). Its id and date go into every cycle
// report. Format: docs/calibration.md; example: config/calibration.sim.toml.
#include <array>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "fettle/config/diagnostics.hpp"
#include "fettle/core/geometry.hpp"

namespace fettle::config {

struct CalibrationSection {
  std::filesystem::path file;  ///< calibration file (T_base_camera, intrinsics); empty = none yet
};

/// Pinhole camera with OpenCV's distortion model (k1 k2 p1 p2 [k3 [k4 k5 k6 ...]]).
struct CameraIntrinsics {
  int width_px = 0;
  int height_px = 0;
  double fx_px = 0.0;
  double fy_px = 0.0;
  double cx_px = 0.0;
  double cy_px = 0.0;
  double skew = 0.0;
  std::vector<double> distortion;  ///< OpenCV order; empty = none
  double rms_px = 0.0;             ///< reprojection RMS of the calibration (0 = nominal values)
  int views = 0;                   ///< views used (0 = nominal values)
};

/// Per-pose residual of a hand-eye calibration.
struct PoseResidual {
  std::string name;
  double translation_mm = 0.0;
  double rotation_deg = 0.0;
  bool outlier = false;
};

struct HandEyeResiduals {
  std::string method;  ///< "nominal", "board" or "sphere"
  int poses = 0;       ///< poses used
  double rms_mm = 0.0;
  double max_mm = 0.0;
  double rms_deg = 0.0;  ///< 0 for the sphere method (positions only)
  double max_deg = 0.0;
  std::vector<PoseResidual> per_pose;
};

/// The calibration file.
struct CalibrationFile {
  std::filesystem::path source;  ///< where it was read from (empty if built in memory)
  std::string id;                ///< identity, copied into every cycle report
  std::string date;              ///< when it was made, ISO 8601 UTC ("YYYY-MM-DDThh:mm:ssZ" or the date alone)
  std::string note;              ///< free text
  std::optional<CameraIntrinsics> intrinsics;
  std::optional<Transform> T_base_camera;       ///< camera points -> robot base frame (mm)
  std::optional<Transform> T_flange_board;      ///< board-based hand-eye by-product
  std::optional<Transform> T_camera_projector;  ///< projector points -> camera frame (mm)
  std::optional<HandEyeResiduals> hand_eye;
  double stereo_rms_px = 0.0;  ///< camera-projector calibration RMS (0 = none or nominal)
  std::string sha256;          ///< SHA-256 (hex) of the file's bytes as read; empty if built in memory
};

/// What identifies the calibration a cycle ran with; the daemon and `fettle plan` copy it into
/// every cycle report.
struct CalibrationIdentity {
  std::string id;
  std::string date;
  std::string sha256;          ///< of the file's bytes as loaded (empty: built in memory, never read)
  std::filesystem::path file;  ///< where it was read from (empty: built in memory)
  /// One line for logs and reports: `id (date) sha256:<first 12 hex digits> file`.
  std::string to_string() const;
};

/// The identity of a loaded calibration file (no file access: the hash was taken when it was read).
CalibrationIdentity calibration_identity(const CalibrationFile& calibration);
/// The camera's pose with the slide at slide_mm: the calibration holds it with the slide at
/// 0 mm, and the slide moves the camera along base +x.
Transform T_base_camera_at(const Transform& T_base_camera, double slide_mm);
/// One robot pose of a live hand-eye calibration (`fettle calibrate hand-eye --live --poses`).
struct CalibrationPose {
  std::string name;        ///< default "pose<N>"
  Pose T_base_tool;        ///< TCP (the sphere centre) in the base frame; orientation default: tool down
};
/// Reads a pose file: [[pose]] tables with position_mm = [x, y, z] and optional name and
/// quaternion_wxyz (default [0, 1, 0, 0], the tool pointing down). Throws ConfigError.
std::vector<CalibrationPose> load_calibration_poses(const std::filesystem::path& file);

/// SHA-256 of a byte string, as 64 lower-case hex digits.
std::string sha256_hex(const std::string& bytes);

/// Reads a calibration file; throws ConfigError listing every problem found.
CalibrationFile load_calibration(const std::filesystem::path& file);
/// Checks a calibration file without throwing: the problems found (empty = valid).
std::vector<Diagnostic> check_calibration(const std::filesystem::path& file);
/// The TOML text of a calibration file (with comments saying what each key is).
std::string to_toml(const CalibrationFile& calibration);
/// Writes a calibration file atomically; throws UserError if it cannot be written.
void write_calibration(const std::filesystem::path& file, const CalibrationFile& calibration);
/// The current UTC time as ISO 8601, "YYYY-MM-DDThh:mm:ssZ".
std::string utc_now_iso8601();

}  // namespace fettle::config
