#pragma once
// Grinding spindle drive (CANopen CiA 402): [spindle] in the cell file.
#include <array>
#include <filesystem>
#include <string>
#include <vector>

namespace fettle::config {

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

}  // namespace fettle::config
