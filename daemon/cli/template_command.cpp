// fettle template build --part P --calib CAL --views DIR (--cell C | --positions-mm ...) --out
// golden.ply: the template of a golden (hand-fettled) casting from views of it on the fixture,
// for [template] source = "scan" (process::build_template; docs/vision.md, "A template from a
// golden casting"). DIR holds view0.ply, view1.ply, ... (camera frame, mm: what the cell's
// camera or `fettle-sim scan --fettled` writes), taken at the slide positions given.
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <regex>
#include <string>
#include <vector>

#include "fettle/cli/cli.hpp"
#include "fettle/config/calibration.hpp"
#include "fettle/config/load.hpp"
#include "fettle/process/pipeline.hpp"
#include "fettle/vision/cloud.hpp"

namespace {

namespace fs = std::filesystem;

struct Args {
  fs::path part, calib, views, cell, out;
  std::vector<double> positions_mm;
  std::vector<double> box_mm;
  fettle::process::TemplateBuildSettings settings;
};

/// DIR/view<N>.ply in the order of N.
std::vector<fs::path> view_files(const fs::path& dir) {
  std::vector<std::pair<int, fs::path>> found;
  const std::regex name(R"(view(\d+)\.ply)");
  std::error_code ec;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    std::smatch m;
    const std::string file = it->path().filename().string();
    if (std::regex_match(file, m, name)) found.emplace_back(std::stoi(m[1].str()), it->path());
  }
  if (ec) throw fettle::UserError(dir.string() + ": cannot read the views directory: " + ec.message());
  std::sort(found.begin(), found.end());
  std::vector<fs::path> out;
  for (auto& [n, p] : found) out.push_back(std::move(p));
  return out;
}

int build(const Args& a) {
  const auto recipe = fettle::config::load_part(a.part);
  const auto calibration = fettle::config::load_calibration(a.calib);
  if (!calibration.T_base_camera)
    throw fettle::UserError(a.calib.string() + ": has no [T_base_camera]; run `fettle calibrate hand-eye` first");
  std::vector<double> positions = a.positions_mm;
  if (positions.empty() && !a.cell.empty()) positions = fettle::config::load_cell(a.cell).slide.photo_positions_mm;
  const auto files = view_files(a.views);
  if (files.empty()) throw fettle::UserError(a.views.string() + ": no view0.ply, view1.ply, ... in it");
  if (positions.size() != files.size())
    throw fettle::UserError(a.views.string() + ": " + std::to_string(files.size()) + " views but " +
                            std::to_string(positions.size()) + " slide positions (--positions-mm or the cell file's "
                            "[slide] photo_positions_mm): one per view");
  std::vector<fettle::process::View> views;
  for (std::size_t k = 0; k < files.size(); ++k) {
    const auto cloud = fettle::vision::load_cloud(files[k]);
    fettle::vision::require_millimetres(cloud, files[k].string());
    fettle::process::View v;
    v.cloud.width = static_cast<std::uint32_t>(cloud.size());
    v.cloud.height = 1;
    v.cloud.points = cloud.points;
    v.T_base_camera = fettle::config::T_base_camera_at(*calibration.T_base_camera, positions[k]);
    v.slide_position_mm = positions[k];
    std::fprintf(stderr, "view %zu: %s, %zu points, slide at %.1f mm\n", k, files[k].string().c_str(), cloud.size(),
                 positions[k]);
    views.push_back(std::move(v));
  }
  auto settings = a.settings;
  if (a.box_mm.size() == 6) {
    settings.box_min_mm = fettle::Vec3(a.box_mm[0], a.box_mm[1], a.box_mm[2]);
    settings.box_max_mm = fettle::Vec3(a.box_mm[3], a.box_mm[4], a.box_mm[5]);
    if (!(settings.box_min_mm.array() < settings.box_max_mm.array()).all())
      throw fettle::UserError("--box-mm: each of XMIN YMIN ZMIN must be below its XMAX YMAX ZMAX");
  }
  const auto built = fettle::process::build_template(recipe, views, settings);
  if (!built) throw fettle::UserError(a.views.string() + ": " + built.error().message + " [" + built.error().code + "]");
  fettle::vision::save_ply(a.out, built->cloud);
  const auto box = fettle::vision::bounds(built->cloud);
  const Eigen::Vector3f lo = box.min, hi = box.max;
  std::printf("%s: %zu points with normals (part frame, mm; %zu fused, %zu beside the casting dropped), "
              "x %.1f..%.1f, y %.1f..%.1f, z %.1f..%.1f mm\n",
              a.out.string().c_str(), built->cloud.size(), built->fused_points, built->dropped_points, lo.x(), hi.x(),
              lo.y(), hi.y(), lo.z(), hi.z());
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("template", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* tmpl = app.add_subcommand("template", "The part's golden template ([template] source = \"scan\")");
  tmpl->require_subcommand(1);
  auto* cmd = tmpl->add_subcommand("build", "Build the template from views of a golden casting on the fixture");
  cmd->add_option("--part", a->part, "Part recipe (.toml): its fixture pose and vision settings")
      ->required()
      ->check(CLI::ExistingFile);
  cmd->add_option("--calib", a->calib, "Calibration file with T_base_camera")->required()->check(CLI::ExistingFile);
  cmd->add_option("--views", a->views, "Directory with view0.ply, view1.ply, ... (camera frame, mm)")
      ->required()
      ->check(CLI::ExistingDirectory);
  auto* positions = cmd->add_option("--positions-mm", a->positions_mm, "Slide position of each view (mm)");
  cmd->add_option("--cell", a->cell, "Cell file whose [slide] photo_positions_mm the views were taken at")
      ->check(CLI::ExistingFile)
      ->excludes(positions);
  cmd->add_option("--out", a->out, "Template PLY to write (part frame, normals)")->required();
  cmd->add_option("--box-mm", a->box_mm,
                  "XMIN YMIN ZMIN XMAX YMAX ZMAX: the casting's box in the part frame (mm, with a margin); "
                  "needed when a clamp stands within about 10 mm of it")
      ->expected(6);
  cmd->add_option("--voxel-mm", a->settings.voxel_mm, "Point spacing of the template")->check(CLI::Range(0.05, 5.0));
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a] { return build(*a); }}};
});

}  // namespace
