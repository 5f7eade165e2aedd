#pragma once
// Grinding spindle drive (CANopen CiA 402): [spindle] in the cell file.
// See docs/spindle-canopen.md for the objects and the start-up sequence.
#include <array>
#include <filesystem>
#include <string>
#include <vector>

namespace fettle::config {

struct SpindleSection {
  /// socketcan: a CAN_RAW socket on `interface` (can0, vcan0);
  /// socketcand: CAN frames over TCP with socketcand's rawmode protocol (address:port, bus `interface`);
  /// sim: the simulated drive on an in-process bus (same process only).
  std::string transport = "socketcan";
  std::string interface = "can0";
  std::string address = "127.0.0.1";  ///< socketcand server (transport = "socketcand")
  int port = 29536;                   ///< socketcand server port (socketcand's default)
  int node_id = 1;
  int master_node_id = 127;  ///< our own heartbeat's node id, monitored by the drive through its 0x1016
  std::string mode = "profile_velocity";  ///< profile_velocity (0x6060=3) | velocity (vl, 0x6060=2)
  int heartbeat_producer_ms = 100;
  int heartbeat_timeout_ms = 300;
  int sdo_timeout_ms = 200;
  int spin_up_timeout_ms = 10000;
  double at_speed_tolerance_rpm = 100.0;
  double max_rpm = 12000.0;
};

}  // namespace fettle::config
