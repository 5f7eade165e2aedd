// fettle-sim evaluate: the paper's section-4 tables on simulated castings.
#include <cstdio>
#include <memory>

#include "fettle/cli/cli.hpp"
#include "fettle/core/error.hpp"
#include "sim_common.hpp"

namespace {

using namespace fettle::sim;  // NOLINT(google-build-using-namespace)

struct Args {
  std::filesystem::path part;
  std::vector<std::uint64_t> seeds{1};
  std::vector<std::filesystem::path> trajectories;
  bool perfect = false;
  app::ScannerOptions scanner;
};

int evaluate_cmd(const Args& a) {
  const auto recipe = fettle::config::load_part(a.part);
  if (!a.trajectories.empty() && a.trajectories.size() != a.seeds.size())
    throw fettle::UserError("give one --trajectory per --seeds entry (" + std::to_string(a.seeds.size()) + ")");
  CellLimits limits;
  const Scanner scanner(app::scanner_config(a.scanner, &limits));
  // Every trajectory is read and checked before any casting is ground or scanned.
  std::vector<fettle::Trajectory> trajectories;
  for (const auto& path : a.trajectories) {
    trajectories.push_back(read_trajectory(path));
    if (auto s = validate_trajectory(trajectories.back(), limits); !s)
      throw fettle::UserError(path.string() + ": " + s.error().message);
  }
  std::vector<Casting> ground;
  std::vector<std::vector<Capture>> scans;
  std::vector<Evaluation> template_eval;
  std::vector<std::pair<std::uint64_t, std::vector<RegionTruth>>> truth;  // material left, per casting
  for (std::size_t i = 0; i < a.seeds.size(); ++i) {
    Casting c = Casting::make(recipe, a.seeds[i]);
    std::vector<Gouge> gouges;
    if (!a.trajectories.empty()) {
      const auto& t = trajectories[i];
      GrindOptions opt;
      opt.noise_seed = a.seeds[i];
      auto runs = grind_by_region(c, t, recipe, opt, {}, limits, app::progress_printer());
      if (!runs) throw fettle::UserError(a.trajectories[i].string() + ": " + runs.error().message);
      gouges = runs->total.gouges;
    } else if (a.perfect) {
      // Oracle: all flash and riser material removed exactly (no tool), to see the floor
      // the scanner's noise alone sets on the counts.
      c.remove_all_material();
    }
    std::fprintf(stderr, "scanning casting %llu (%zu views)\n", static_cast<unsigned long long>(a.seeds[i]),
                 scanner.config().photo_positions_mm.size());
    truth.emplace_back(a.seeds[i], c.material());
    auto caps = scanner.capture_all(c);
    template_eval.push_back(evaluate_against_template(recipe, caps, c, gouges));
    scans.push_back(std::move(caps));
    ground.push_back(std::move(c));
  }
  const char* state = !a.trajectories.empty() ? "after grinding" : a.perfect ? "perfectly ground (oracle)" : "as cast";
  std::printf("== Template comparison (%s): points farther than 0.3/0.4/0.5 mm from the golden template ==\n", state);
  std::printf("%s", format_table(template_eval).c_str());
  // The scan's largest residual includes the scanner's outliers; the simulator knows what is left.
  std::printf("== Material left (simulator truth): volume mm3 / largest height above the golden surface mm ==\n");
  for (const auto& [seed, regions] : truth) {
    std::printf("casting %-4llu", static_cast<unsigned long long>(seed));
    for (const auto& r : regions) std::printf("  %s %.1f / %.2f", r.name.c_str(), r.volume_mm3, r.max_height_mm);
    std::printf("\n");
  }
  if (ground.size() > 1) {
    std::vector<Evaluation> batch;
    for (std::size_t i = 1; i < ground.size(); ++i) batch.push_back(evaluate_against_part(recipe, scans[i], ground[0]));
    std::printf("== Batch consistency (%s): castings against casting %llu ==\n", state,
                static_cast<unsigned long long>(a.seeds[0]));
    std::printf("%s", format_table(batch).c_str());
  }
  return 0;
}

FETTLE_COMMAND("evaluate", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* cmd = app.add_subcommand("evaluate", "Template comparison and batch consistency tables (Zhu et al. 2022, sec. 4)");
  cmd->add_option("--part", a->part, "Part recipe with a [geometry] table")->required()->check(CLI::ExistingFile);
  cmd->add_option("--seeds", a->seeds, "Castings of the batch (the first is the batch reference)")->delimiter(',');
  cmd->add_option("--trajectory", a->trajectories, "Trajectory per casting, in --seeds order")->check(CLI::ExistingFile);
  cmd->add_flag("--perfect", a->perfect, "Remove all material exactly (oracle) instead of grinding");
  app::add_scanner_options(cmd, a->scanner);
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a] { return evaluate_cmd(*a); }}};
});

}  // namespace
