// fettle plan --part part.toml --scan SCAN --calib CALIB --out DIR: the daemon's processing
// pipeline (fettle::process::process: locate, extract, plan, validate) on one scan file.
// The scan is in the camera frame (mm; PLY or PCD, e.g. a view written by `fettle-sim scan`),
// CALIB the calibration file whose T_base_camera maps it into the robot base frame.
// Writes DIR/trajectory.json, DIR/trajectory.csv, DIR/preview.png and DIR/report.json.
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <memory>

#include <nlohmann/json.hpp>

#include "fettle/config/calibration.hpp"
#include "fettle/config/load.hpp"
#include "fettle/core/atomic_file.hpp"
#include "fettle/cli/cli.hpp"
#include "fettle/process/pipeline.hpp"
#include "fettle/vision/cloud.hpp"

namespace {

namespace fs = std::filesystem;

struct Args {
  fs::path part, scan, calib, out, cell, golden;
  double slide_position_mm = 0.0;
};

int plan(const Args& a) {
  auto recipe = fettle::config::load_part(a.part);
  const auto calibration = fettle::config::load_calibration(a.calib);
  if (!calibration.T_base_camera)
    throw fettle::UserError(a.calib.string() + ": has no [T_base_camera]; run `fettle calibrate hand-eye` first");
  fettle::config::CellConfig cell;
  if (!a.cell.empty()) cell = fettle::config::load_cell(a.cell);
  fettle::process::LoadOptions lo;
  if (!a.golden.empty()) {
    lo.golden = fettle::vision::load_cloud(a.golden);
    lo.golden_identity = fs::absolute(a.golden).string() + " " + std::to_string(fs::file_size(a.golden));
  }
  const auto loaded = fettle::process::load_recipe(recipe, lo);
  std::cerr << "recipe " << recipe.id << ": template " << loaded.templ.whole().fine().size() << " points"
            << (loaded.template_from_cache ? " (from cache)" : " (built)") << ", " << loaded.load_ms << " ms\n";

  const auto scan = fettle::vision::load_cloud(a.scan);
  fettle::vision::require_millimetres(scan, a.scan.string());
  fettle::process::View view;
  view.cloud.width = static_cast<std::uint32_t>(scan.size());
  view.cloud.height = 1;
  view.cloud.points = scan.points;
  view.T_base_camera = *calibration.T_base_camera;
  view.slide_position_mm = a.slide_position_mm;
  const auto out = fettle::process::process(loaded, cell, {view}, [](std::size_t done, std::size_t total, const std::string& step) {
    std::fprintf(stderr, "[%zu/%zu] %s\n", done, total, step.c_str());
  });
  if (!out) throw fettle::UserError(a.scan.string() + ": " + out.error().message + " [" + out.error().code + "]");

  std::error_code ec;
  fs::create_directories(a.out, ec);
  if (ec) throw fettle::UserError(a.out.string() + ": cannot create the output directory: " + ec.message());
  if (auto st = fettle::process::write_outputs(a.out, *out); !st) throw fettle::UserError(st.error().message);
  nlohmann::ordered_json report;
  report["part_id"] = recipe.id;
  report["scan"] = a.scan.string();
  const auto cal_id = fettle::config::calibration_identity(calibration);
  report["calibration"] = {
      {"file", a.calib.string()}, {"id", cal_id.id}, {"date", cal_id.date}, {"sha256", cal_id.sha256}};
  nlohmann::ordered_json timings = nlohmann::ordered_json::object();
  for (const auto& t : out->timings) timings[t.step + "_ms"] = t.ms;
  timings["total_ms"] = out->total_ms;
  report["timings"] = timings;
  auto regions = nlohmann::ordered_json::array();
  std::printf("%-20s %-15s %8s %8s %12s %10s %8s %9s\n", "region", "type", "fitness", "excess", "volume mm3",
              "height mm", "points", "plan ms");
  for (const auto& m : out->regions) {
    regions.push_back({{"name", m.name},
                       {"type", fettle::config::to_string(m.type)},
                       {"scene_points", m.scene_points},
                       {"fitness", m.fitness},
                       {"rmse_mm", m.rmse_mm},
                       {"excess_points", m.excess_points},
                       {"excess_volume_mm3", m.excess_volume_mm3},
                       {"excess_max_height_mm", m.excess_max_height_mm},
                       {"trajectory_points", m.trajectory_points},
                       {"segments", m.segments},
                       {"plan_ms", m.plan_ms}});
    std::printf("%-20s %-15s %8.3f %8zu %12.1f %10.2f %8zu %9.1f\n", m.name.c_str(), fettle::config::to_string(m.type),
                m.fitness, m.excess_points, m.excess_volume_mm3, m.excess_max_height_mm, m.trajectory_points, m.plan_ms);
  }
  report["regions"] = regions;
  report["trajectory_points"] = out->trajectory.points.size();
  if (auto st = fettle::write_file_atomic(a.out / "report.json", report.dump(2) + "\n"); !st)
    throw fettle::UserError(st.error().message);
  std::printf("%zu trajectory points; %s/{trajectory.json,trajectory.csv,preview.png,report.json}\n",
              out->trajectory.points.size(), a.out.string().c_str());
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("plan", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* cmd = app.add_subcommand("plan", "Locate, extract and plan the grinding trajectory of one scan");
  cmd->add_option("--part", a->part, "Part recipe (.toml)")->required()->check(CLI::ExistingFile);
  cmd->add_option("--scan", a->scan, "Scan (PLY or PCD, camera frame, mm)")->required()->check(CLI::ExistingFile);
  cmd->add_option("--calib", a->calib, "Calibration file with T_base_camera")->required()->check(CLI::ExistingFile);
  cmd->add_option("--out", a->out, "Output directory (trajectory.json, trajectory.csv, preview.png, report.json)")->required();
  cmd->add_option("--cell", a->cell, "Cell file for the [safety] limits (default: built-in defaults)")->check(CLI::ExistingFile);
  cmd->add_option("--golden", a->golden, "Golden template (part frame, mm); default: the recipe's (see fettle-sim golden)")
      ->check(CLI::ExistingFile);
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a] { return plan(*a); }}};
});

}  // namespace
