#include "fettle/config/load.hpp"

#include <algorithm>
#include <limits>
#include <set>
#include <tuple>

#include "fettle/core/log.hpp"
#include "reader.hpp"
#include "sections.hpp"

namespace fettle::config {

using detail::Need;
using detail::Range;
using detail::Report;
using detail::TableReader;

const char* to_string(RegionType type) {
  switch (type) {
    case RegionType::ring_flash:
      return "ring_flash";
    case RegionType::riser:
      return "riser";
    case RegionType::straight_flash:
      return "straight_flash";
    case RegionType::circle_flash:
      return "circle_flash";
  }
  return "?";
}

const char* to_string(ToolShape shape) {
  switch (shape) {
    case ToolShape::cylinder:
      return "cylinder";
    case ToolShape::ball:
      return "ball";
    case ToolShape::cone:
      return "cone";
  }
  return "?";
}

namespace {
using namespace detail;  // NOLINT(google-build-using-namespace)

std::string check_level(const std::string& s) {
  if (log::is_level_name(s)) return "";
  std::string allowed;
  for (const auto& n : log::level_names()) allowed += (allowed.empty() ? "" : ", ") + n;
  return "\"" + s + "\" is not a log level (allowed: " + allowed + ")";
}

void read_cell_section(TableReader& t, CellSection& c) {
  t.string("name", c.name, Need::required);
  t.path("state_dir", c.state_dir);
  t.integer("workers", c.workers, {0, 256});
  t.boolean("verification_scan", c.verification_scan);
  std::set<int> ids;
  t.tables("recipes", [&](TableReader& r, std::size_t) {
    RecipeRef ref;
    r.integer("plc_recipe_id", ref.plc_recipe_id, {1, 65535}, Need::required);
    r.path("file", ref.file, Need::required, /*must_exist=*/true);
    if (ref.plc_recipe_id != 0 && !ids.insert(ref.plc_recipe_id).second)
      r.error("plc_recipe_id", "recipe id " + std::to_string(ref.plc_recipe_id) + " is used twice");
    c.recipes.push_back(ref);
  });
}

void read_cell(TableReader& root, CellConfig& cfg) {
  if (auto t = root.table("cell", Need::required)) read_cell_section(*t, cfg.cell);
  if (auto t = root.table("logging")) {
    t->choice("level", cfg.logging.level, log::level_names());
    t->string_map("components", cfg.logging.components, check_level);
  }
  read_plc(root, cfg.plc);
  read_camera(root, cfg.slide, cfg.camera);
  read_robot(root, cfg.robot);
  read_spindle(root, cfg.spindle);
  read_calibration(root, cfg.calibration);
  if (auto t = root.table("safety", Need::required)) {
    auto& s = cfg.safety;
    t->vec3("workspace_min_mm", s.workspace_min_mm, kCoordMm, Need::required);
    t->vec3("workspace_max_mm", s.workspace_max_mm, kCoordMm, Need::required);
    for (int i = 0; i < 3; ++i) {
      if (s.workspace_min_mm[static_cast<std::size_t>(i)] >= s.workspace_max_mm[static_cast<std::size_t>(i)]) {
        t->error("workspace_max_mm", "must be greater than workspace_min_mm on every axis (axis " +
                                         std::string(1, static_cast<char>('x' + i)) + " is not)");
        break;
      }
    }
    t->number("tool_axis_cone_deg", s.tool_axis_cone_deg, {0.0, 180.0});
    t->number("max_speed_mm_s", s.max_speed_mm_s, {0.1, 5000.0});
    t->number("max_spindle_rpm", s.max_spindle_rpm, {1.0, 100000.0});
    t->number("safe_height_mm", s.safe_height_mm, {0.0, 2000.0});
    t->number("min_clearance_mm", s.min_clearance_mm, {0.0, 10.0});
    t->number("calibration_accuracy_mm", s.calibration_accuracy_mm, {0.0, 5.0});
    t->number("robot_accuracy_mm", s.robot_accuracy_mm, {0.0, 5.0});
    t->number("tcp_accuracy_mm", s.tcp_accuracy_mm, {0.0, 5.0});
    t->number("robot_repeatability_mm", s.robot_repeatability_mm, {0.0, 5.0});
  }
  if (auto t = root.table("control")) {
    t->path("socket", cfg.control.socket);
    // a Unix socket's path fits sockaddr_un's sun_path (108 bytes with its NUL)
    if (cfg.control.socket.string().size() > 107)
      t->error("socket", "is " + std::to_string(cfg.control.socket.string().size()) +
                             " bytes long: a Unix socket path is at most 107 bytes");
  }
  if (auto t = root.table("records")) {
    t->integer("keep_cycles", cfg.records.keep_cycles, {1, 10000000});
    t->number("keep_mb", cfg.records.keep_mb, {1.0, 1e9});
    t->number("min_free_mb", cfg.records.min_free_mb, {0.0, 1e9});
  }
  if (auto t = root.table("compensation")) {
    auto& c = cfg.compensation;
    t->boolean("enabled", c.enabled);
    t->number("gain", c.gain, {0.01, 1.0});
    t->number("max_offset_mm", c.max_offset_mm, {0.0, 5.0});
    t->integer("min_points", c.min_points, {1, 1000000});
    t->path("state_file", c.state_file);
  }
}

void read_part(TableReader& root, PartRecipe& part) {
  read_geometry(root, part.geometry);
  read_vision(root, part.vision);
  if (auto t = root.table("part", Need::required)) {
    t->string("id", part.id, Need::required);
    t->string("description", part.description, Need::optional, true);
  }
  if (auto t = root.table("template", Need::required)) {
    t->choice("source", part.template_source.kind, {"simulator", "scan"}, Need::required);
    if (part.template_source.kind == "scan") t->path("scan", part.template_source.scan, Need::required, true);
    else t->path("scan", part.template_source.scan);  // simulator: where `fettle-sim golden` writes it
    t->number("voxel_mm", part.template_source.voxel_mm, {0.01, 50.0});
  }
  if (auto t = root.table("verification")) {
    auto& v = part.verification;
    t->number("ok_max_share_over_0_3_pct", v.ok_max_share_over_0_3_pct, {0.0, 100.0});
    t->number("ok_max_share_over_0_5_pct", v.ok_max_share_over_0_5_pct, {0.0, 100.0});
    t->number("gouge_depth_mm", v.gouge_depth_mm, {0.0, 50.0});
    t->number("nok_max_share_gouged_pct", v.nok_max_share_gouged_pct, {0.0, 100.0});
    t->number("max_regrind_height_mm", v.max_regrind_height_mm, {0.0, 100.0});
    t->number("jump_edge_mm", v.jump_edge_mm, {0.0, 1000.0});
    t->number("footprint_margin_mm", v.footprint_margin_mm, {0.0, 100.0});
    t->number("gouge_confirm_radius_mm", v.gouge_confirm_radius_mm, {0.1, 20.0});
  }
  if (auto t = root.table("fixture")) {
    auto& f = part.fixture;
    t->vec3("position_mm", f.position_mm, kCoordMm);
    t->vec3("rotation_deg", f.rotation_deg, {-180.0, 180.0});
    t->number("position_tolerance_mm", f.position_tolerance_mm, {0.0, 500.0});
    t->number("rotation_tolerance_deg", f.rotation_tolerance_deg, {0.0, 180.0});
  }
  std::set<std::string> tool_names;
  root.tables(
      "tools",
      [&](TableReader& t, std::size_t) {
        Tool tool;
        t.string("name", tool.name, Need::required);
        t.enumeration("shape", tool.shape,
                      {{"cylinder", ToolShape::cylinder}, {"ball", ToolShape::ball}, {"cone", ToolShape::cone}},
                      Need::required);
        t.number("diameter_mm", tool.diameter_mm, {0.1, 500.0}, Need::required);
        t.number("length_mm", tool.length_mm, {0.1, 500.0});
        if (tool.shape == ToolShape::cone) t.number("cone_angle_deg", tool.cone_angle_deg, {1.0, 89.0}, Need::required);
        t.vec3("tcp_mm", tool.tcp_mm, {-2000.0, 2000.0});
        t.number("wear_mm_per_cm3", tool.wear_mm_per_cm3, {0.0, 1.0});
        t.number("wear_tolerance_pct", tool.wear_tolerance_pct, {0.0, 100.0});
        t.number("max_wear_mm", tool.max_wear_mm, {0.0, 0.5 * tool.diameter_mm});
        if (!tool.name.empty() && !tool_names.insert(tool.name).second)
          t.error("name", "tool \"" + tool.name + "\" is defined twice");
        part.tools.push_back(tool);
      },
      Need::required);
  std::set<std::string> region_names;
  root.tables(
      "regions",
      [&](TableReader& t, std::size_t) {
        Region r;
        t.string("name", r.name, Need::required);
        t.enumeration("type", r.type,
                      {{"ring_flash", RegionType::ring_flash},
                       {"riser", RegionType::riser},
                       {"straight_flash", RegionType::straight_flash},
                       {"circle_flash", RegionType::circle_flash}},
                      Need::required);
        t.string("tool", r.tool, Need::required);
        if (!r.tool.empty() && !tool_names.contains(r.tool))
          t.error("tool", "no [[tools]] entry is named \"" + r.tool + "\"");
        t.vec3("roi_center_mm", r.roi_center_mm, kCoordMm, Need::required);
        t.vec3("roi_size_mm", r.roi_size_mm, {0.1, 5000.0}, Need::required);
        t.number("feed_mm_s", r.feed_mm_s, {0.1, 1000.0});
        t.number("spindle_rpm", r.spindle_rpm, {100.0, 100000.0});
        t.number("excess_threshold_mm", r.excess_threshold_mm, {0.0, 50.0});
        t.number("allowance_mm", r.allowance_mm, {0.0, 10.0});
        t.enumeration("pose", r.pose, {{"region", RegionPose::region}, {"part", RegionPose::part}});
        // Keys of one region type are unknown for the others: a misplaced key is an error.
        switch (r.type) {
          case RegionType::ring_flash:
          case RegionType::circle_flash:
            t.number("chamfer_deg", r.chamfer_deg, {5.0, 85.0});
            t.number("point_spacing_mm", r.point_spacing_mm, {0.05, 1.0});
            t.number("overlap_mm", r.overlap_mm, {0.0, 100.0});
            t.enumeration("contact", r.contact,
                          {{"chamfer", FlashContact::chamfer}, {"periphery", FlashContact::periphery}});
            break;
          case RegionType::riser:
            t.number("depth_per_pass_mm", r.depth_per_pass_mm, {0.01, 20.0});
            t.number("stepover_mm", r.stepover_mm, {0.1, 100.0});
            t.number("margin_mm", r.margin_mm, {0.0, 100.0});
            break;
          case RegionType::straight_flash:
            t.integer("passes", r.passes, {1, 50});
            t.number("point_spacing_mm", r.point_spacing_mm, {0.05, 1.0});
            break;
        }
        if (!r.name.empty() && !region_names.insert(r.name).second)
          t.error("name", "region \"" + r.name + "\" is defined twice");
        part.regions.push_back(r);
      },
      Need::required);
}

template <class Config, class ReadFn>
std::vector<Diagnostic> read_file(const std::filesystem::path& file, Config& cfg, ReadFn read) {
  Report report(file.string());
  auto table = detail::parse_file(file, report);
  if (table) {
    cfg.source = std::filesystem::absolute(file).lexically_normal();
    TableReader root(*table, "", report, cfg.source.parent_path());
    read(root, cfg);
    root.finish();
  }
  auto d = report.diagnostics();
  std::stable_sort(d.begin(), d.end(), [](const Diagnostic& a, const Diagnostic& b) {
    return std::tie(a.line, a.column) < std::tie(b.line, b.column);
  });
  return d;
}

}  // namespace

CellConfig load_cell(const std::filesystem::path& file) {
  CellConfig cfg;
  if (auto d = read_file(file, cfg, read_cell); !d.empty()) throw ConfigError(std::move(d));
  return cfg;
}

PartRecipe load_part(const std::filesystem::path& file) {
  PartRecipe part;
  if (auto d = read_file(file, part, read_part); !d.empty()) throw ConfigError(std::move(d));
  return part;
}

ErrorBudget load_error_budget(const std::filesystem::path& file) {
  ErrorBudget e;
  if (auto d = read_file(file, e, detail::read_errors); !d.empty()) throw ConfigError(std::move(d));
  return e;
}

std::vector<Diagnostic> check_file(const std::filesystem::path& file, FileKind kind) {
  if (kind == FileKind::automatic) {
    kind = FileKind::cell;
    // through the reader's own checks (a FIFO, a huge or too deeply nested file is refused, not
    // parsed); its problems are reported by the reader below
    detail::Report probe(file);
    if (const auto doc = detail::parse_file(file, probe); doc && doc->contains("part")) kind = FileKind::part;
  }
  if (kind == FileKind::part) {
    PartRecipe part;
    return read_file(file, part, read_part);
  }
  CellConfig cfg;
  auto diagnostics = read_file(file, cfg, read_cell);
  // A cell file is only valid if the recipes it names are.
  if (diagnostics.empty()) {
    for (const auto& r : cfg.cell.recipes) {
      PartRecipe part;
      auto d = read_file(r.file, part, read_part);
      diagnostics.insert(diagnostics.end(), d.begin(), d.end());
    }
  }
  return diagnostics;
}

log::Options logging_options(const LoggingSection& logging, std::string program,
                             std::optional<std::string> override_level) {
  log::Options o;
  o.program = std::move(program);
  o.default_level = logging.level;
  o.component_levels = logging.components;
  o.override_level = std::move(override_level);
  return o;
}

}  // namespace fettle::config
