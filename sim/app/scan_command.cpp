// fettle-sim scan --part FILE --seed N --out DIR: simulated captures of a casting.
#include <chrono>
#include <cstdio>
#include <iostream>
#include <memory>
#include <optional>

#include <nlohmann/json.hpp>

#include "fettle/cli/cli.hpp"
#include "fettle/config/load.hpp"
#include "fettle/core/atomic_file.hpp"
#include "fettle/core/error.hpp"
#include "fettle/vision/inspect.hpp"
#include "sim_common.hpp"

namespace {

using namespace fettle::sim;  // NOLINT(google-build-using-namespace)

struct Args {
  std::filesystem::path part, out;
  std::uint64_t seed = 1;
  bool golden = false;
  bool fettled = false;
  std::filesystem::path png;
  app::ScannerOptions scanner;
  app::ErrorOptions errors;
};

int scan(const Args& a) {
  const auto budget = app::error_budget(a.errors);
  const auto recipe = app::world_of(fettle::config::load_part(a.part), budget);
  const auto t0 = std::chrono::steady_clock::now();
  Casting casting = a.golden ? Casting::golden(recipe, a.seed) : Casting::make(recipe, a.seed);
  if (a.fettled) {  // a golden casting as a foundry has one: hand-fettled, its form deviation kept
    casting.remove_all_material();
    casting.set_T_base_part(fettle::vision::nominal_T_fixture_part(recipe));
  }
  std::fprintf(stderr, "built casting %llu of %s in %.2f s\n", static_cast<unsigned long long>(a.seed),
               recipe.id.c_str(), app::seconds_since(t0));
  auto nominal = app::scanner_config(a.scanner);
  if (!a.scanner.cell.empty()) {
    // the camera where the cell's calibration says, as `fettle plan --calib` and `fettle template
    // build --calib` take the views (fettle-sim cell places it so too)
    const auto positions = nominal.photo_positions_mm;
    nominal.place_in_cell(fettle::config::load_cell(a.scanner.cell));
    nominal.photo_positions_mm = positions;
  }
  std::optional<CellErrors> errors;
  if (budget) errors = draw_cell_errors(*budget, a.errors.cell_seed, nominal);
  const Scanner scanner(errors ? true_scanner(nominal, *errors) : nominal);
  const auto& positions = nominal.photo_positions_mm;
  nlohmann::json slide_errors = nlohmann::json::array();
  for (std::size_t v = 0; v < positions.size(); ++v) {
    std::fprintf(stderr, "rendering view %zu of %zu (slide %.1f mm, %d x %d px)\n", v + 1, positions.size(),
                 positions[v], scanner.config().intrinsics.width, scanner.config().intrinsics.height);
    const auto t1 = std::chrono::steady_clock::now();
    // With --errors: as the cell gets it (the truth files keep the truth; errors.json the draw).
    const Capture c = errors ? capture_as_cell(scanner, nominal, *errors, casting, positions[v], a.seed, v).capture
                             : scanner.capture(casting, positions[v], v);
    if (errors) slide_errors.push_back(c.truth.slide_position_mm - positions[v]);
    const double render_s = app::seconds_since(t1);
    const std::string stem = "view" + std::to_string(v);
    std::fprintf(stderr, "writing view %zu of %zu to %s\n", v + 1, positions.size(), a.out.string().c_str());
    if (auto s = write_capture(a.out, stem, c); !s) throw fettle::UserError(s.error().message);
    if (v == 0 && !a.png.empty())
      if (auto s = write_height_png(a.png, c); !s) throw fettle::UserError(s.error().message);
    std::printf("view %zu: slide %.1f mm, %zu valid points of %zu, rendered in %.2f s -> %s/%s.{ply,pcd,c16,f32,truth.json}\n",
                v, positions[v], c.cloud.count_valid(), c.cloud.size(), render_s, a.out.string().c_str(), stem.c_str());
  }
  if (errors) {
    auto j = errors->to_json();
    j["slide_errors_mm"] = slide_errors;
    j["believed_T_base_camera_note"] = "the cell believes the camera is where --cell's calibration says";
    if (auto s = fettle::write_file_atomic(a.out / "errors.json", j.dump(2) + "\n"); !s)
      throw fettle::UserError(s.error().message);
    std::printf("errors drawn for cell seed %llu -> %s/errors.json\n", static_cast<unsigned long long>(a.errors.cell_seed),
                a.out.string().c_str());
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
  auto* golden = cmd->add_flag("--golden", a->golden, "Scan the golden template (the part ground to specification)");
  cmd->add_flag("--fettled", a->fettled,
                "Scan casting --seed hand-fettled (every flash and riser ground off, its form deviation kept) at the "
                "fixture's nominal pose: the golden casting `fettle template build` makes a template from")
      ->excludes(golden);
  cmd->add_option("--png", a->png, "Also write a PNG of view 0 coloured by height");
  app::add_scanner_options(cmd, a->scanner);
  app::add_error_options(cmd, a->errors);
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a] { return scan(*a); }}};
});

}  // namespace
