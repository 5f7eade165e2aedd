#pragma once
#include <filesystem>
#include <fstream>
#include <string>

#include "fettle/config/load.hpp"
#include "fettle/sim/sim.hpp"

namespace sim_test {

inline const std::filesystem::path kPumpBody = std::filesystem::path(FETTLE_SOURCE_DIR) / "config/parts/pump-body.toml";

inline fettle::config::PartRecipe pump_body() { return fettle::config::load_part(kPumpBody); }

/// A small scanner (fast tests): the default camera scaled to width x height.
inline fettle::sim::ScannerConfig small_scanner(int width = 516, int height = 386) {
  fettle::sim::ScannerConfig c;
  c.intrinsics = c.intrinsics.scaled(width, height);
  return c;
}

inline double pi() { return 3.14159265358979323846; }

}  // namespace sim_test
