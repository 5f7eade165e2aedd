#pragma once
// Robot controller link (TCP line protocol): [robot] in the cell file.
#include <array>
#include <filesystem>
#include <string>
#include <vector>

namespace fettle::config {

struct RobotSection {
  std::string address = "127.0.0.1";
  int port = 30100;
  std::string cell_id;
  int reply_timeout_ms = 2000;
  int ping_period_ms = 1000;
  int missed_pings = 3;   ///< this many pings without PONG → link down
  int chunk_points = 20;  ///< trajectory points per upload chunk
  int run_timeout_ms = 600000;
  int reconnect_initial_ms = 100;  ///< reconnect backoff after the link went down, doubling ...
  int reconnect_max_ms = 5000;     ///< ... up to this
};

}  // namespace fettle::config
