// fettle locate --template T --scene S: where is the template in the scene?
// Any two PLY/PCD clouds in any (common) unit; prints one JSON object on stdout.
#include <chrono>
#include <filesystem>
#include <iostream>
#include <memory>

#include <nlohmann/json.hpp>

#include "fettle/cli/cli.hpp"
#include "fettle/vision/cloud.hpp"
#include "fettle/vision/registration.hpp"

namespace {

struct Args {
  std::filesystem::path template_file;
  std::filesystem::path scene_file;
  double min_fitness = 0.3;
  std::size_t coarse_points = 3000;
};

int locate(const Args& args) {
  const auto t0 = std::chrono::steady_clock::now();
  const auto templ = fettle::vision::load_cloud(args.template_file);
  const auto scene = fettle::vision::load_cloud(args.scene_file);
  fettle::vision::LocateSettings settings;
  settings.min_fitness = args.min_fitness;
  settings.coarse_points = args.coarse_points;
  const auto r = fettle::vision::locate(templ, scene, settings);
  if (!r) {
    throw fettle::UserError("locate " + args.template_file.string() + " in " + args.scene_file.string() + ": " +
                            r.error().message + " [" + r.error().code + "]");
  }
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  nlohmann::json out;
  nlohmann::json M = nlohmann::json::array();
  for (int i = 0; i < 4; ++i) {
    nlohmann::json row = nlohmann::json::array();
    for (int j = 0; j < 4; ++j) row.push_back(r->T_scene_template.matrix()(i, j));
    M.push_back(row);
  }
  out["T_scene_template"] = M;
  out["fitness"] = r->fitness;
  out["rmse"] = r->rmse;
  out["inliers"] = r->inliers;
  out["converged"] = r->converged;
  out["seconds"] = seconds;
  std::cout << out.dump() << "\n";
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("locate", [](CLI::App& app, const fettle::cli::Common&) {
  auto args = std::make_shared<Args>();
  auto* cmd = app.add_subcommand(
      "locate", "Find a template cloud in a scene cloud (PLY/PCD, any unit): prints T_scene_template as JSON");
  cmd->add_option("--template", args->template_file, "Template cloud (PLY or PCD)")->required();
  cmd->add_option("--scene", args->scene_file, "Scene cloud (PLY or PCD), same unit as the template")->required();
  cmd->add_option("--min-fitness", args->min_fitness,
                  "Fraction of template points that must find scene support (default 0.3)")
      ->check(CLI::Range(0.0, 1.0));
  cmd->add_option("--coarse-points", args->coarse_points, "Template points used for feature matching (default 3000)")
      ->check(CLI::Range(100, 1000000));
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [args] { return locate(*args); }}};
});

}  // namespace
