// Setup of the processing pipeline (fettle/process/pipeline.hpp): the recipe, its golden
// template, the vision template and the planner's signed distance (both cached on disk).
#include "fettle/process/pipeline.hpp"

#include <algorithm>
#include <limits>
#include <sstream>
#include <string>
#include <system_error>

#include "fettle/config/load.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/planning/sdf_grid.hpp"
#include "fettle/planning/surface.hpp"
#include "internal.hpp"

namespace fettle::process {

namespace fs = std::filesystem;

namespace {

/// The planner's signed distance: the exact sample-based one (sdf_from_samples) evaluated once
/// on a banded grid (planning::SdfGrid), read from `<recipe dir>/.<recipe stem>.planning-cache/`
/// when its key (hash of the samples and of every setting) matches, else built in parallel and
/// written there. A stale or corrupt cache is rebuilt with a warning, never trusted.
planning::SignedDistance signed_distance_grid(const config::PartRecipe& recipe, const LoadOptions& options,
                                              const std::vector<Vec3>& pts, const std::vector<Vec3>& nrm,
                                              double search_mm, LoadedRecipe& out) {
  constexpr double kCellMm = 4.0;
  auto exact = planning::sdf_from_samples(pts, nrm, kCellMm, search_mm);
  const planning::SdfGridSettings gs;
  Vec3 lo = Vec3::Constant(std::numeric_limits<double>::infinity()), hi = -lo;
  for (const auto& p : pts) lo = lo.cwiseMin(p), hi = hi.cwiseMax(p);
  std::ostringstream params;
  params.precision(17);
  params << "sdf_from_samples 4 cell " << kCellMm << " search " << search_mm << " grid voxel " << gs.voxel_mm << " band "
         << gs.band_mm << " tol " << gs.exact_tol_mm << " far " << gs.far_voxel_mm << " " << gs.far_band_mm << " "
         << gs.far_tol_mm << " jump " << gs.kink_jump_mm;
  const auto key = planning::sdf_grid_key(pts, nrm, params.str());
  fs::path dir = options.sdf_cache_dir;
  if (dir.empty() && recipe.vision.cache && !recipe.source.empty()) dir = planning_cache_dir(recipe.source);
  const bool cache = !dir.empty();
  const fs::path file = cache ? sdf_grid_file(dir) : fs::path{};
  auto logger = log::get("planning");
  if (cache) {
    std::string why;
    std::error_code ec;
    const bool present = fs::exists(file, ec);
    if (auto grid = planning::SdfGrid::load(file, key, exact, &why)) {
      out.sdf_grid = grid->stats();
      out.sdf_from_cache = true;
      return grid->function();
    }
    if (present) logger->warn("signed-distance grid cache not used, rebuilding it: {}", why);
  }
  logger->info("building the template's signed-distance grid ({} samples, voxel {} mm, band {} mm)", pts.size(),
               gs.voxel_mm, gs.band_mm);
  const auto grid = planning::SdfGrid::build(exact, lo, hi, gs, [&](const char* lattice, std::size_t done, std::size_t total) {
    logger->info("signed-distance grid: {} lattice {}/{} bricks", lattice, done, total);
  });
  const auto& st = grid.stats();
  logger->info("signed-distance grid: {} band bricks of {}, {} far bricks, {:.1f} MiB; {} band and {} far cells answered "
               "exactly; built in {:.1f} s",
               st.bricks, st.brick_slots, st.far_bricks, static_cast<double>(st.memory_bytes) / (1024.0 * 1024.0),
               st.exact_cells, st.far_exact_cells, st.build_ms / 1000.0);
  out.sdf_grid = st;
  if (cache) {
    std::error_code ec;
    fs::create_directories(file.parent_path(), ec);
    if (Status s = grid.save(file, key); !s) logger->warn("signed-distance grid cache not written: {}", s.error().message);
  }
  return grid.function();
}

}  // namespace

config::Tool worn_tool(const config::Tool& tool, const ToolWearMm& wear) {
  config::Tool out = tool;
  if (const auto it = wear.find(tool.name); it != wear.end())
    out.diameter_mm = std::max(0.1, tool.diameter_mm - 2.0 * std::max(0.0, it->second));
  return out;
}

const config::Region* LoadedRecipe::region(const std::string& name) const {
  for (const auto& r : recipe.regions)
    if (r.name == name) return &r;
  return nullptr;
}

const config::Tool& LoadedRecipe::tool_for(const config::Region& region) const {
  for (const auto& t : recipe.tools)
    if (t.name == region.tool) return t;
  throw UserError(recipe.source.string() + ": region '" + region.name + "' names tool '" + region.tool +
                  "', which has no [[tools]] entry");
}

fs::path golden_path(const config::PartRecipe& recipe) {
  if (!recipe.template_source.scan.empty()) return recipe.template_source.scan;
  const fs::path dir = recipe.source.empty() ? fs::current_path() : recipe.source.parent_path();
  const std::string stem = recipe.source.empty() ? recipe.id : recipe.source.stem().string();
  return dir / (stem + ".golden.ply");
}

fs::path planning_cache_dir(const fs::path& recipe_file) {
  return recipe_file.parent_path() / ("." + recipe_file.stem().string() + ".planning-cache");
}

fs::path sdf_grid_file(const fs::path& planning_cache_dir) { return planning_cache_dir / "sdf-grid.bin"; }

LoadedRecipe load_recipe(const config::PartRecipe& recipe, const LoadOptions& options) {
  const auto t0 = Clock::now();
  LoadedRecipe out;
  out.recipe = recipe;
  const std::string where = recipe.source.empty() ? recipe.id : recipe.source.string();
  for (const auto& r : recipe.regions) (void)out.tool_for(r);  // every region has its tool
  vision::Cloud golden;
  if (options.golden) {
    golden = *options.golden;
    out.golden_identity = options.golden_identity.empty() ? "memory:" + recipe.id : options.golden_identity;
  } else {
    out.golden_file = golden_path(recipe);
    std::error_code ec;
    if (!fs::exists(out.golden_file, ec)) {
      const std::string how = recipe.template_source.kind == "simulator"
                                  ? "write it with `fettle-sim golden --part " + where + " --out " +
                                        out.golden_file.string() + "`"
                                  : "check [template] scan";
      throw UserError(where + ": golden template " + out.golden_file.string() + " not found: " + how);
    }
    golden = vision::load_cloud(out.golden_file);
    out.golden_identity = fs::absolute(out.golden_file).string() + " " +
                          std::to_string(fs::file_size(out.golden_file, ec)) + " " +
                          std::to_string(fs::last_write_time(out.golden_file, ec).time_since_epoch().count());
  }
  if (golden.empty()) throw UserError(where + ": the golden template has no points");
  vision::require_millimetres(golden, "golden template of " + where);
  out.templ = vision::PartTemplate::load_or_build(recipe, golden, out.golden_identity, &out.template_from_cache,
                                                  options.template_cache_dir);
  // The planner's signed distance: from the golden samples themselves where they carry normals
  // (the simulator's golden part: exact outward normals), else from the vision template's fine
  // cloud. The template is voxel-averaged, which blends the normals of the two faces at every
  // edge into a diagonal one and puts a false 0.1-0.2 mm gouge just above the edge.
  const auto& fine = golden.has_normals() ? golden : out.templ.whole().fine();
  if (!fine.has_normals()) throw UserError(where + ": the template has no normals (a bug in the vision stage)");
  std::vector<Vec3> pts, nrm;
  pts.reserve(fine.size());
  nrm.reserve(fine.size());
  for (std::size_t i = 0; i < fine.size(); ++i) {
    pts.push_back(fine.points[i].cast<double>());
    nrm.push_back(fine.normals[i].cast<double>());
  }
  double search_mm = 20.0;
  for (const auto& t : recipe.tools) search_mm = std::max(search_mm, 0.5 * t.diameter_mm + 5.0);
  out.template_points = fine.points;
  out.template_sdf = signed_distance_grid(recipe, options, pts, nrm, search_mm, out);
  out.load_ms = ms_since(t0);
  return out;
}

LoadedRecipe load_recipe(const fs::path& part_file, const LoadOptions& options) {
  return load_recipe(config::load_part(part_file), options);
}

}  // namespace fettle::process
