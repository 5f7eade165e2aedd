// fettle inspect --part part.toml --scan SCAN --out DIR: the vision stage on one scan.
// Writes DIR/report.json (per region: pose, fitness, excess material), DIR/deviation.png
// (top view of the scan in the part frame, coloured by distance to the template) and
// DIR/<region>-excess.ply.
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <memory>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "fettle/config/load.hpp"
#include "fettle/core/atomic_file.hpp"
#include "fettle/cli/cli.hpp"
#include "fettle/vision/cloud.hpp"
#include "fettle/vision/inspect.hpp"

namespace {

namespace fs = std::filesystem;
using nlohmann::json;

struct Args {
  fs::path part;
  fs::path scan;
  fs::path out;
  fs::path golden;
};

json matrix_json(const fettle::Transform& T) {
  json M = json::array();
  for (int i = 0; i < 4; ++i) {
    json row = json::array();
    for (int j = 0; j < 4; ++j) row.push_back(T.matrix()(i, j));
    M.push_back(row);
  }
  return M;
}

void write_deviation_png(const fs::path& file, const fettle::vision::Inspection& ins) {
  const auto& pts = ins.scene_part.points;
  if (pts.empty()) return;
  const auto b = fettle::vision::bounds(ins.scene_part);
  const double extent = std::max(b.max.x() - b.min.x(), b.max.y() - b.min.y());
  const double mm_per_px = std::max(0.25, extent / 1600.0);
  const int w = static_cast<int>((b.max.x() - b.min.x()) / mm_per_px) + 1;
  const int h = static_cast<int>((b.max.y() - b.min.y()) / mm_per_px) + 1;
  cv::Mat top(h, w, CV_32F, cv::Scalar(-1e9));
  cv::Mat dev(h, w, CV_32F, cv::Scalar(0));
  for (std::size_t i = 0; i < pts.size(); ++i) {
    const float d = ins.deviation_mm[i];
    if (!std::isfinite(d)) continue;
    const int u = static_cast<int>((pts[i].x() - b.min.x()) / mm_per_px);
    const int v = h - 1 - static_cast<int>((pts[i].y() - b.min.y()) / mm_per_px);  // y up in the image
    if (pts[i].z() > top.at<float>(v, u)) {
      top.at<float>(v, u) = pts[i].z();
      dev.at<float>(v, u) = d;
    }
  }
  // -1 mm (blue) .. 0 (green) .. +1 mm and above (red); empty pixels white.
  cv::Mat grey(h, w, CV_8U);
  for (int v = 0; v < h; ++v)
    for (int u = 0; u < w; ++u)
      grey.at<std::uint8_t>(v, u) = static_cast<std::uint8_t>(std::clamp((dev.at<float>(v, u) + 1.0f) * 127.5f, 0.0f, 255.0f));
  cv::Mat color;
  cv::applyColorMap(grey, color, cv::COLORMAP_JET);
  for (int v = 0; v < h; ++v)
    for (int u = 0; u < w; ++u)
      if (top.at<float>(v, u) < -1e8f) color.at<cv::Vec3b>(v, u) = cv::Vec3b(255, 255, 255);
  if (!cv::imwrite(file.string(), color)) throw fettle::UserError(file.string() + ": cannot write the PNG");
}

int inspect(const Args& args) {
  const auto recipe = fettle::config::load_part(args.part);
  fs::path golden_file = args.golden;
  if (golden_file.empty()) {
    if (recipe.template_source.kind != "scan")
      throw fettle::UserError(args.part.string() + ": [template] source = \"" + recipe.template_source.kind +
                              "\"; fettle inspect needs a golden cloud: pass --golden golden.ply (part frame, mm) "
                              "or set source = \"scan\" with scan = \"golden.ply\"");
    golden_file = recipe.template_source.scan;
  }
  const auto golden = fettle::vision::load_cloud(golden_file);
  std::error_code ec;
  const auto identity = fs::absolute(golden_file).string() + " " + std::to_string(fs::file_size(golden_file, ec)) + " " +
                        std::to_string(fs::last_write_time(golden_file, ec).time_since_epoch().count());
  bool cached = false;
  const auto templ = fettle::vision::PartTemplate::load_or_build(recipe, golden, identity, &cached);
  std::cerr << "template: " << templ.whole().fine().size() << " points, " << templ.regions().size() << " regions"
            << (cached ? " (from cache)" : " (built)") << "\n";
  const auto scan = fettle::vision::load_cloud(args.scan);
  fettle::vision::require_millimetres(scan, args.scan.string());
  const auto r = fettle::vision::inspect(recipe, templ, scan);
  if (!r) throw fettle::UserError(args.scan.string() + ": " + r.error().message + " [" + r.error().code + "]");

  fs::create_directories(args.out, ec);
  if (ec) throw fettle::UserError(args.out.string() + ": cannot create the output directory: " + ec.message());
  json report;
  report["part_id"] = recipe.id;
  report["scan"] = args.scan.string();
  report["seconds"] = r->seconds;
  report["T_scene_part"] = matrix_json(r->whole.T_scene_template);
  report["fitness"] = r->whole.fitness;
  report["rmse_mm"] = r->whole.rmse;
  bool all_ok = true;
  json regions = json::array();
  for (const auto& rr : r->regions) {
    json j;
    j["name"] = rr.name;
    j["ok"] = rr.ok();
    if (!rr.ok()) {
      j["error"] = rr.error->message;
      j["code"] = rr.error->code;
      all_ok = false;
    }
    j["scene_points"] = rr.scene_points;
    j["T_scene_region"] = matrix_json(rr.registration.T_scene_template);
    j["fitness"] = rr.registration.fitness;
    j["rmse_mm"] = rr.registration.rmse;
    j["inliers"] = rr.registration.inliers;
    j["converged"] = rr.registration.converged;
    j["excess"] = {{"points", rr.excess.points.size()},
                   {"volume_mm3", rr.excess.volume_mm3},
                   {"max_height_mm", rr.excess.max_height_mm},
                   {"footprint_mm2", rr.excess.footprint_mm2},
                   {"file", rr.name + "-excess.ply"}};
    fettle::vision::Cloud ex;
    ex.points = rr.excess.points;
    fettle::vision::save_ply(args.out / (rr.name + "-excess.ply"), ex);
    regions.push_back(j);
  }
  report["regions"] = regions;
  if (const auto st = fettle::write_file_atomic(args.out / "report.json", report.dump(2) + "\n"); !st)
    throw fettle::UserError(st.error().message);
  write_deviation_png(args.out / "deviation.png", *r);
  std::cout << (args.out / "report.json").string() << "\n";
  if (!all_ok) {
    for (const auto& rr : r->regions)
      if (!rr.ok()) std::cerr << "error: " << rr.error->message << "\n";
    return fettle::exit_code::failure;
  }
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("inspect", [](CLI::App& app, const fettle::cli::Common&) {
  auto args = std::make_shared<Args>();
  auto* cmd = app.add_subcommand("inspect", "Locate a part's regions in a scan and measure the excess material");
  cmd->add_option("--part", args->part, "Part recipe (.toml)")->required()->check(CLI::ExistingFile);
  cmd->add_option("--scan", args->scan, "Scan (PLY or PCD, mm, fixture frame)")->required();
  cmd->add_option("--out", args->out, "Output directory (report.json, deviation.png, <region>-excess.ply)")->required();
  cmd->add_option("--golden", args->golden, "Golden cloud (part frame, mm); default: the recipe's [template] scan");
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [args] { return inspect(*args); }}};
});

}  // namespace
