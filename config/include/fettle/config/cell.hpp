#pragma once
// The cell configuration: one file per cell (config/cell.sim.toml, config/cell.example.toml).
// Plain structs with units in field names; parsed only by fettle::config.
#include <array>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include "fettle/config/calibration.hpp"
#include "fettle/config/camera.hpp"
#include "fettle/config/plc.hpp"
#include "fettle/config/robot.hpp"
#include "fettle/config/spindle.hpp"

namespace fettle::config {

struct RecipeRef {
  int plc_recipe_id = 0;       ///< the id the PLC sends with a cycle request
  std::filesystem::path file;  ///< the part recipe (absolute after loading)
};

struct CellSection {
  std::string name;
  std::filesystem::path state_dir = "/var/lib/fettle";  ///< cycle records and the journal
  int workers = 0;                                      ///< vision/planning threads; 0 = one per core
  bool verification_scan = true;                        ///< scan again after grinding
  std::vector<RecipeRef> recipes;
};

struct LoggingSection {
  std::string level = "info";
  std::map<std::string, std::string> components;  ///< per-component level
};

struct SafetySection {
  std::array<double, 3> workspace_min_mm{-1000.0, -1000.0, -100.0};
  std::array<double, 3> workspace_max_mm{1000.0, 1000.0, 1200.0};
  double tool_axis_cone_deg = 60.0;  ///< tool axis within this angle of straight down
  double max_speed_mm_s = 250.0;
  double max_spindle_rpm = 12000.0;
  double safe_height_mm = 100.0;  ///< air moves at least this far above the part
  /// Every pose of a trajectory keeps the tool at least this far from the located template
  /// (planning::validate): the cell's stated uncertainty of where the part's surface is
  /// (localisation, calibration, robot path). A region's allowance_mm must be at least this.
  double min_clearance_mm = 0.05;
  /// The cell's stated accuracies, each a bound (the largest error expected, as datasheets and
  /// ISO 9283 state them; 0 = not stated). Every path keeps at least the root sum of squares of
  /// the calibration, robot and TCP accuracy plus the repeatability from the template along each
  /// surface's normal, less what the cell has learned of its own bias
  /// (process::placement_uncertainty, docs/compensation.md).
  double calibration_accuracy_mm = 0.0;  ///< hand-eye calibration's error at the part
  double robot_accuracy_mm = 0.0;        ///< path accuracy: a constant offset of the path, any direction
  double tcp_accuracy_mm = 0.0;          ///< the tool length's (TCP's) error: along the tool's axis only
  double robot_repeatability_mm = 0.0;   ///< path repeatability (ISO 9283: mean + 3 sigma)
};

struct ControlSection {
  std::filesystem::path socket = "/run/fettle/fettled.sock";
};

struct RecordsSection {
  int keep_cycles = 1000;
  double keep_mb = 20000.0;
  double min_free_mb = 500.0;  ///< free space kept on the state directory's file system (oldest records go first)
};

/// The cell learns its own bias (docs/compensation.md): after each verified cycle, where the
/// tool cut against where it was told to cut (the re-scan's cut surfaces against the commanded
/// tool surface) corrects every later path. Tests: Compensation.*, trial --learning.
struct CompensationSection {
  bool enabled = true;
  double gain = 0.5;             ///< share of each cycle's measured offset taken into the estimate (0-1]
  double max_offset_mm = 0.5;    ///< the estimate is bounded to this length (base frame)
  int min_points = 50;           ///< cut-surface points a direction needs to be estimated along it
  /// Where the estimate is kept across restarts; empty: <state_dir>/compensation.json.
  std::filesystem::path state_file;
};

struct CellConfig {
  std::filesystem::path source;  ///< the file this was read from
  CellSection cell;
  LoggingSection logging;
  PlcSection plc;
  SlideSection slide;
  CameraSection camera;
  RobotSection robot;
  SpindleSection spindle;
  SafetySection safety;
  ControlSection control;
  RecordsSection records;
  CalibrationSection calibration;
  CompensationSection compensation;
};

}  // namespace fettle::config
