// fettle-sim grind --part FILE --seed N --trajectory FILE [--out DIR]: execute a trajectory
// on a simulated casting, report material removed and gouges, optionally rescan.
#include <chrono>
#include <cstdio>
#include <memory>

#include <nlohmann/json.hpp>

#include "fettle/core/atomic_file.hpp"
#include "fettle/cli/cli.hpp"
#include "fettle/core/error.hpp"
#include "sim_common.hpp"

namespace {

using namespace fettle::sim;  // NOLINT(google-build-using-namespace)

struct Args {
  std::filesystem::path part, trajectory, out;
  std::uint64_t seed = 1;
  std::string tool;
  double path_noise_mm = 0.02;
  std::vector<double> bias_mm{0.0, 0.0, 0.0};
  bool rescan = false;
  app::ScannerOptions scanner;
  app::ErrorOptions errors;
};

int grind_cmd(const Args& a) {
  const auto budget = app::error_budget(a.errors);
  const auto recipe = fettle::config::load_part(a.part);
  const auto trajectory = read_trajectory(a.trajectory);
  CellLimits limits;
  const ScannerConfig scfg = app::scanner_config(a.scanner, &limits);
  if (auto s = validate_trajectory(trajectory, limits); !s)
    throw fettle::UserError(a.trajectory.string() + ": " + s.error().message);
  Casting casting = Casting::make(app::world_of(recipe, budget), a.seed);
  GrindOptions opt;
  opt.path_noise_mm = a.path_noise_mm;
  opt.path_bias_mm = fettle::Vec3(a.bias_mm[0], a.bias_mm[1], a.bias_mm[2]);
  opt.noise_seed = a.seed;
  // --errors: the budget's path noise, the cell's path bias and TCP error replace the options'.
  if (budget) apply_to_grinding(draw_cell_errors(*budget, a.errors.cell_seed, scfg), opt);
  const auto t0 = std::chrono::steady_clock::now();
  auto ground = grind_by_region(casting, trajectory, recipe, opt, a.tool, limits, app::progress_printer());
  if (!ground) throw fettle::UserError(a.trajectory.string() + ": " + ground.error().message);
  const GrindResult& res = ground->total;
  std::printf("%-20s %-12s %10s %8s %14s\n", "run (region)", "tool", "poses", "gouges", "max depth mm");
  for (const auto& run : ground->runs)
    std::printf("%-20s %-12s %10zu %8zu %14.3f\n", run.region.empty() ? "(none)" : run.region.c_str(), run.tool.c_str(),
                run.result.poses, run.result.gouges.size(), run.result.max_gouge_depth_mm());
  std::printf("executed %zu interpolated poses in %zu run(s) in %.2f s\n", res.poses, ground->runs.size(),
              app::seconds_since(t0));
  std::printf("%-20s %14s %14s %14s\n", "region", "before mm3", "after mm3", "max height mm");
  for (std::size_t i = 0; i < res.before.size(); ++i)
    std::printf("%-20s %14.1f %14.1f %14.2f\n", res.before[i].name.c_str(), res.before[i].volume_mm3,
                res.after[i].volume_mm3, res.after[i].max_height_mm);
  std::printf("removed %.1f mm3; gouges: %zu, max depth %.3f mm\n", res.removed_mm3(), res.gouges.size(),
              res.max_gouge_depth_mm());
  if (!a.out.empty()) {
    std::filesystem::create_directories(a.out);
    nlohmann::ordered_json j;
    j["part_id"] = recipe.id;
    j["seed"] = a.seed;
    auto runs = nlohmann::ordered_json::array();
    for (const auto& run : ground->runs) runs.push_back({{"region", run.region}, {"tool", run.tool}, {"poses", run.result.poses}});
    j["runs"] = runs;
    j["tool"] = ground->runs.empty() ? std::string() : ground->runs.front().tool;
    j["poses"] = res.poses;
    j["removed_mm3"] = res.removed_mm3();
    auto regions = nlohmann::ordered_json::array();
    for (std::size_t i = 0; i < res.before.size(); ++i)
      regions.push_back({{"name", res.before[i].name},
                         {"volume_before_mm3", res.before[i].volume_mm3},
                         {"volume_after_mm3", res.after[i].volume_mm3},
                         {"max_height_after_mm", res.after[i].max_height_mm}});
    j["regions"] = regions;
    auto gouges = nlohmann::ordered_json::array();
    for (const auto& g : res.gouges)
      gouges.push_back({{"position_mm", {g.position_mm.x(), g.position_mm.y(), g.position_mm.z()}},
                        {"depth_mm", g.depth_mm},
                        {"pose_index", g.pose_index}});
    j["gouges"] = gouges;
    if (auto s = fettle::write_file_atomic(a.out / "grind.json", j.dump(2) + "\n"); !s)
      throw fettle::UserError(s.error().message);
    if (a.rescan) {
      const Scanner scanner(scfg);
      const auto caps = scanner.capture_all(casting);
      for (std::size_t v = 0; v < caps.size(); ++v)
        if (auto s = write_capture(a.out, "ground-view" + std::to_string(v), caps[v]); !s)
          throw fettle::UserError(s.error().message);
      std::printf("rescanned the ground part: %zu views in %s\n", caps.size(), a.out.string().c_str());
    }
  }
  return 0;
}

FETTLE_COMMAND("grind", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* cmd = app.add_subcommand("grind", "Execute a trajectory (JSON or CSV) on a simulated casting");
  cmd->add_option("--part", a->part, "Part recipe with a [geometry] table")->required()->check(CLI::ExistingFile);
  cmd->add_option("--seed", a->seed, "Casting number");
  cmd->add_option("--trajectory", a->trajectory, "Trajectory file (see docs/simulator.md)")->required()->check(CLI::ExistingFile);
  cmd->add_option("--tool", a->tool, "Tool name from the recipe for every point (default: each region's own tool, by the trajectory's segment_regions)");
  cmd->add_option("--path-noise-mm", a->path_noise_mm, "Executed path noise sigma per axis (mm)")->check(CLI::Range(0.0, 5.0));
  cmd->add_option("--bias-mm", a->bias_mm, "Executed path bias x y z (mm), a calibration error")->expected(3);
  cmd->add_option("--out", a->out, "Write grind.json (and the rescan with --rescan) here");
  app::add_error_options(cmd, a->errors);
  cmd->add_flag("--rescan", a->rescan, "Scan the ground part again (needs --out)");
  app::add_scanner_options(cmd, a->scanner);
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a] { return grind_cmd(*a); }}};
});

}  // namespace
