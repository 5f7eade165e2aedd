#pragma once
// Shared by fettle-sim's scan, grind and evaluate commands.
#include <chrono>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <optional>
#include <random>
#include <sstream>
#include <string>
#include <utility>

#include "fettle/config/load.hpp"
#include "fettle/core/error.hpp"
#include "fettle/sim/errors.hpp"
#include "fettle/sim/sim.hpp"

namespace fettle::sim::app {

/// Now as "YYYY-MM-DD HH:MM UTC", for the summaries the measuring commands write.
inline std::string utc_now() {
  const auto t = std::chrono::system_clock::to_time_t(std::chrono::system_clock::now());
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%d %H:%M UTC", &tm);
  return buf;
}

struct ScannerOptions {
  std::filesystem::path cell;  ///< optional cell file: slide.photo_positions_mm and [safety]
  int width = 0, height = 0;   ///< 0 = the default 2064 x 1544
  double noise_mm = 0.05;
  bool no_noise = false;
  std::vector<double> positions_mm;  ///< overrides the cell's photo positions
};

inline void add_scanner_options(CLI::App* cmd, ScannerOptions& o) {
  cmd->add_option("--cell", o.cell, "Cell file: slide.photo_positions_mm and [safety] limits")->check(CLI::ExistingFile);
  cmd->add_option("--width", o.width, "Image width in pixels (default 2064; the camera is scaled)");
  cmd->add_option("--height", o.height, "Image height in pixels (default 1544)");
  cmd->add_option("--noise-mm", o.noise_mm, "Depth noise sigma at 600 mm, head-on (mm)")->check(CLI::Range(0.0, 10.0));
  cmd->add_flag("--no-noise", o.no_noise, "Ideal range images: no noise, dropouts, flying pixels or outliers");
  cmd->add_option("--positions-mm", o.positions_mm, "Slide photo positions (mm), overriding the cell file");
}

inline ScannerConfig scanner_config(const ScannerOptions& o, CellLimits* limits = nullptr) {
  ScannerConfig c;
  if (!o.cell.empty()) {
    const auto cell = config::load_cell(o.cell);
    c.photo_positions_mm = cell.slide.photo_positions_mm;
    if (limits != nullptr) {
      const auto& s = cell.safety;
      limits->workspace_min_mm = Vec3(s.workspace_min_mm[0], s.workspace_min_mm[1], s.workspace_min_mm[2]);
      limits->workspace_max_mm = Vec3(s.workspace_max_mm[0], s.workspace_max_mm[1], s.workspace_max_mm[2]);
      limits->max_speed_mm_s = s.max_speed_mm_s;
      limits->max_spindle_rpm = s.max_spindle_rpm;
    }
  }
  if (!o.positions_mm.empty()) c.photo_positions_mm = o.positions_mm;
  if (o.width > 0 || o.height > 0) {
    const int w = o.width > 0 ? o.width : c.intrinsics.width * o.height / c.intrinsics.height;
    const int h = o.height > 0 ? o.height : c.intrinsics.height * o.width / c.intrinsics.width;
    c.intrinsics = c.intrinsics.scaled(w, h);
  }
  c.noise.sigma_z_mm = o.noise_mm;
  c.noise.enabled = !o.no_noise;
  return c;
}

/// --errors FILE and --cell-seed N (docs/simulator.md, "Error budget").
struct ErrorOptions {
  std::filesystem::path file;
  std::uint64_t cell_seed = 1;
};

inline void add_error_options(CLI::App* cmd, ErrorOptions& o) {
  cmd->add_option("--errors", o.file,
                  "Error budget file ([errors]: calibration, slide, intrinsics, path, depth, form, wheel wear; "
                  "config/sim/errors-realistic.toml); the cell is not told")
      ->check(CLI::ExistingFile);
  // "random": a cell drawn now (printed, so the run can be repeated), as the castings of
  // `--seeds random:N` are: a claim about the cell comes from cells nobody looked at first.
  const CLI::Validator drawn(
      [](std::string& text) {
        if (text != "random") return std::string();
        std::random_device rd;
        text = std::to_string(std::uniform_int_distribution<std::uint64_t>(1000, 99999999)(rd));
        std::printf("cell seed %s (drawn now for --cell-seed random; repeat with --cell-seed %s)\n", text.c_str(),
                    text.c_str());
        std::fflush(stdout);
        return std::string();
      },
      "", "random");
  cmd->add_option("--cell-seed", o.cell_seed,
                  "Draws the cell's errors (--errors), the same for every casting; N or random (drawn now, printed)")
      ->transform(drawn)
      ->capture_default_str();
}

/// The budget of --errors, if given.
inline std::optional<config::ErrorBudget> error_budget(const ErrorOptions& o) {
  if (o.file.empty()) return std::nullopt;
  return config::load_error_budget(o.file);
}

/// The simulated castings' recipe: `recipe`, with the budget's form deviation when it has one.
inline config::PartRecipe world_of(config::PartRecipe recipe, const std::optional<config::ErrorBudget>& budget) {
  if (budget && budget->form_deviation_mm) recipe.geometry.variation.form_deviation_mm = *budget->form_deviation_mm;
  return recipe;
}

/// "WIDTHxHEIGHT" of a simulated camera's range map (--resolution); UserError naming `option` otherwise.
inline std::pair<unsigned, unsigned> parse_resolution(const std::string& text, const std::string& option = "--resolution") {
  unsigned w = 0, h = 0;
  char x = 0;
  std::istringstream in(text);
  if (!(in >> w >> x >> h) || x != 'x' || w < 64 || h < 48 || w > 4128 || h > 3088)
    throw UserError(option + " '" + text + "': expected WIDTHxHEIGHT from 64x48 to 4128x3088, e.g. 1032x772");
  return {w, h};
}

/// A progress line on stderr (rewritten in place on a terminal).
inline Progress progress_printer() {
  return [last = std::chrono::steady_clock::time_point{}](std::size_t done, std::size_t total,
                                                          const std::string& what) mutable {
    const auto now = std::chrono::steady_clock::now();
    if (done != total && now - last < std::chrono::milliseconds(500)) return;
    last = now;
    std::fprintf(stderr, "%s: %zu / %zu (%.0f %%)\n", what.c_str(), done, total,
                 100.0 * static_cast<double>(done) / static_cast<double>(std::max<std::size_t>(1, total)));
  };
}

inline double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace fettle::sim::app
