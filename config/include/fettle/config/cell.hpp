#pragma once
// The cell configuration: one file per cell (config/cell.sim.toml, config/cell.example.toml).
// Plain structs with units in field names; parsed only by fettle::config.
#include <array>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

namespace fettle::config {

struct RecipeRef {
  int plc_recipe_id = 0;              ///< the id the PLC sends with a cycle request
  std::filesystem::path file;         ///< the part recipe (absolute after loading)
};

struct CellSection {
  std::string name;
  std::filesystem::path state_dir = "/var/lib/fettle";  ///< cycle records and the journal
  int workers = 0;                                       ///< vision/planning threads; 0 = one per core
  bool verification_scan = true;                         ///< scan again after grinding
  std::vector<RecipeRef> recipes;
};

struct LoggingSection {
  std::string level = "info";
  std::map<std::string, std::string> components;  ///< per-component level
};

struct PlcSection {
  std::string address = "127.0.0.1";
  int port = 502;
  int unit_id = 1;
  int register_base = 0;            ///< holding-register address of the map's first register
  int response_timeout_ms = 200;
  int poll_period_ms = 50;
  int heartbeat_timeout_ms = 1000;  ///< the PLC's heartbeat stale longer than this → link fault
  int reconnect_initial_ms = 100;
  int reconnect_max_ms = 5000;
};

struct SlideSection {
  std::vector<double> photo_positions_mm{0.0};  ///< slide positions where the camera takes a view
  int travel_timeout_ms = 15000;
};

struct CameraSection {
  std::string address;      ///< IPv4 of the GigE Vision camera (or use serial)
  std::string serial;       ///< serial number (or use address)
  int frame_timeout_ms = 5000;
  int retries = 2;
  double exposure_us = 20000.0;
};

struct RobotSection {
  std::string address = "127.0.0.1";
  int port = 30100;
  std::string cell_id;
  int reply_timeout_ms = 2000;
  int ping_period_ms = 1000;
  int missed_pings = 3;          ///< this many pings without PONG → link down
  int chunk_points = 20;         ///< trajectory points per upload chunk
  int run_timeout_ms = 600000;
};

struct SpindleSection {
  std::string transport = "socketcan";  ///< socketcan | sim
  std::string interface = "can0";
  int node_id = 1;
  std::string mode = "profile_velocity";  ///< profile_velocity (0x6060=3) | velocity (vl, 0x6060=2)
  int heartbeat_producer_ms = 100;
  int heartbeat_timeout_ms = 300;
  int sdo_timeout_ms = 200;
  int spin_up_timeout_ms = 10000;
  double at_speed_tolerance_rpm = 100.0;
  double max_rpm = 12000.0;
};

struct SafetySection {
  std::array<double, 3> workspace_min_mm{-1000.0, -1000.0, -100.0};
  std::array<double, 3> workspace_max_mm{1000.0, 1000.0, 1200.0};
  double tool_axis_cone_deg = 60.0;  ///< tool axis within this angle of straight down
  double max_speed_mm_s = 250.0;
  double max_spindle_rpm = 12000.0;
  double safe_height_mm = 100.0;     ///< air moves at least this far above the part
};

struct ControlSection {
  std::filesystem::path socket = "/run/fettle/fettled.sock";
};

struct RecordsSection {
  int keep_cycles = 1000;
  double keep_mb = 20000.0;
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
};

}  // namespace fettle::config
