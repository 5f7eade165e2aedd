// fettle-sim scan --part FILE --seed N --out DIR: simulated captures of a casting.
#include <chrono>
#include <cstdio>
#include <iostream>
#include <memory>

#include "fettle/cli/cli.hpp"
#include "fettle/core/error.hpp"
#include "sim_common.hpp"

namespace {

using namespace fettle::sim;  // NOLINT(google-build-using-namespace)

struct Args {
  std::filesystem::path part, out;
  std::uint64_t seed = 1;
  bool golden = false;
  std::filesystem::path png;
  app::ScannerOptions scanner;
};

int scan(const Args& a) {
  const auto recipe = fettle::config::load_part(a.part);
  const auto t0 = std::chrono::steady_clock::now();
  const Casting casting = a.golden ? Casting::golden(recipe, a.seed) : Casting::make(recipe, a.seed);
  std::fprintf(stderr, "built casting %llu of %s in %.2f s\n", static_cast<unsigned long long>(a.seed),
               recipe.id.c_str(), app::seconds_since(t0));
  const Scanner scanner(app::scanner_config(a.scanner));
  const auto& positions = scanner.config().photo_positions_mm;
  for (std::size_t v = 0; v < positions.size(); ++v) {
    std::fprintf(stderr, "rendering view %zu of %zu (slide %.1f mm, %d x %d px)\n", v + 1, positions.size(),
                 positions[v], scanner.config().intrinsics.width, scanner.config().intrinsics.height);
    const auto t1 = std::chrono::steady_clock::now();
    const Capture c = scanner.capture(casting, positions[v], v);
    const double render_s = app::seconds_since(t1);
    const std::string stem = "view" + std::to_string(v);
    std::fprintf(stderr, "writing view %zu of %zu to %s\n", v + 1, positions.size(), a.out.string().c_str());
    if (auto s = write_capture(a.out, stem, c); !s) throw fettle::UserError(s.error().message);
    if (v == 0 && !a.png.empty())
      if (auto s = write_height_png(a.png, c); !s) throw fettle::UserError(s.error().message);
    std::printf("view %zu: slide %.1f mm, %zu valid points of %zu, rendered in %.2f s -> %s/%s.{ply,pcd,c16,f32,truth.json}\n",
                v, positions[v], c.cloud.count_valid(), c.cloud.size(), render_s, a.out.string().c_str(), stem.c_str());
  }
  const auto p = fettle::Pose::from_transform(casting.T_base_part());
  std::printf("part %s seed %llu placed at (%.2f, %.2f, %.2f) mm, yaw %.2f deg\n", recipe.id.c_str(),
              static_cast<unsigned long long>(a.seed), p.position_mm.x(), p.position_mm.y(), p.position_mm.z(),
              fettle::rad_to_deg(std::atan2(casting.T_base_part().linear()(1, 0), casting.T_base_part().linear()(0, 0))));
  std::printf("%-20s %-15s %14s %14s\n", "region", "type", "volume mm3", "max height mm");
  for (const auto& r : casting.material())
    std::printf("%-20s %-15s %14.1f %14.2f\n", r.name.c_str(), fettle::config::to_string(r.type), r.volume_mm3,
                r.max_height_mm);
  return 0;
}

FETTLE_COMMAND("scan", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* cmd = app.add_subcommand("scan", "Scan a simulated casting: PLY, PCD, range images and ground truth per view");
  cmd->add_option("--part", a->part, "Part recipe with a [geometry] table")->required()->check(CLI::ExistingFile);
  cmd->add_option("--seed", a->seed, "Casting number (its flash, riser, form deviation and placement)");
  cmd->add_option("--out", a->out, "Output directory")->required();
  cmd->add_flag("--golden", a->golden, "Scan the golden template (the part ground to specification)");
  cmd->add_option("--png", a->png, "Also write a PNG of view 0 coloured by height");
  app::add_scanner_options(cmd, a->scanner);
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a] { return scan(*a); }}};
});

}  // namespace
