#pragma once
// PLC link (Modbus TCP): [plc] in the cell file.
#include <array>
#include <filesystem>
#include <string>
#include <vector>

namespace fettle::config {

struct PlcSection {
  std::string address = "127.0.0.1";
  int port = 502;
  int unit_id = 1;
  int register_base = 0;  ///< holding-register address of the map's first register
  int response_timeout_ms = 200;
  int poll_period_ms = 50;
  int heartbeat_timeout_ms = 1000;  ///< the PLC's heartbeat stale longer than this → link fault
  int reconnect_initial_ms = 100;
  int reconnect_max_ms = 5000;
};

}  // namespace fettle::config
