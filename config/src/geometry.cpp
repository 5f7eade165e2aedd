// [geometry] in a part recipe: the parametric casting the simulator builds.
#include "fettle/config/geometry.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <set>
#include <sstream>

#include "sections.hpp"

namespace fettle::config::detail {
namespace {

constexpr Range<double> kLen{-5000.0, 5000.0};
constexpr Range<double> kPos{0.01, 5000.0};

std::string fmt(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

void range(TableReader& t, std::string_view key, ValueRange& out, Range<double> allowed, Need need = Need::optional) {
  std::vector<double> v{out.min, out.max};
  const auto before = t.report().diagnostics().size();
  t.numbers(key, v, allowed, 2, 2, need);
  if (t.report().diagnostics().size() != before || v.size() != 2) return;
  if (v[0] > v[1]) {
    t.error(key, "must be [min, max] with min <= max, got [" + fmt(v[0]) + ", " + fmt(v[1]) + "]");
    return;
  }
  out = {v[0], v[1]};
}

void xy(TableReader& t, std::string_view key, std::array<double, 2>& out, Need need = Need::optional) {
  std::vector<double> v{out[0], out[1]};
  const auto before = t.report().diagnostics().size();
  t.numbers(key, v, kLen, 2, 2, need);
  if (t.report().diagnostics().size() == before && v.size() == 2) out = {v[0], v[1]};
}

void cylinder(TableReader& t, BodyCylinder& c) {
  xy(t, "center_mm", c.center_mm, Need::required);
  t.number("radius_mm", c.radius_mm, kPos, Need::required);
  t.number("base_z_mm", c.base_z_mm, {0.0, 5000.0});
  t.number("top_z_mm", c.top_z_mm, kPos, Need::required);
  if (c.top_z_mm <= c.base_z_mm) t.error("top_z_mm", "must be above base_z_mm (" + fmt(c.base_z_mm) + ")");
}

std::string where_xy(double x, double y) { return "(" + fmt(x) + ", " + fmt(y) + ")"; }

/// Regions of the recipe: their ROIs must touch the body and features must name them.
/// The region tables are read (with their own checks) by the part loader; here the file
/// is parsed again only to point at the offending line.
void check_regions(TableReader& root, const PartGeometry& g, const std::vector<std::pair<std::string, std::string>>& links) {
  detail::Report again(root.report().file());
  auto parsed = detail::parse_file(root.report().file(), again);
  if (!parsed) return;  // the loader reports syntax errors
  const toml::table& doc = *parsed;
  double x0 = 1e300, y0 = 1e300, x1 = -1e300, y1 = -1e300, z1 = 0.0;
  auto grow = [&](double ax, double ay, double bx, double by, double top) {
    x0 = std::min(x0, ax), y0 = std::min(y0, ay), x1 = std::max(x1, bx), y1 = std::max(y1, by);
    z1 = std::max(z1, top);
  };
  for (const auto& b : g.blocks) grow(b.min_mm[0], b.min_mm[1], b.max_mm[0], b.max_mm[1], b.max_mm[2]);
  auto gc = [&](const BodyCylinder& c) {
    grow(c.center_mm[0] - c.radius_mm, c.center_mm[1] - c.radius_mm, c.center_mm[0] + c.radius_mm,
         c.center_mm[1] + c.radius_mm, c.top_z_mm);
  };
  for (const auto& c : g.cylinders) gc(c);
  for (const auto& r : g.ring_flashes) gc(r.cylinder);
  if (x0 > x1) return;
  std::set<std::string> names;
  if (const auto* regions = doc["regions"].as_array()) {
    std::size_t i = 0;
    for (const auto& node : *regions) {
      const auto* t = node.as_table();
      ++i;
      if (t == nullptr) continue;
      if (const auto* n = t->get_as<std::string>("name")) names.insert(n->get());
      const auto* c = t->get_as<toml::array>("roi_center_mm");
      if (c == nullptr || c->size() != 3) continue;
      double v[3];
      bool ok = true;
      for (std::size_t k = 0; k < 3; ++k) {
        const auto d = (*c)[k].value<double>();
        ok = ok && d.has_value();
        v[k] = d.value_or(0.0);
      }
      if (!ok) continue;
      constexpr double margin = 10.0;
      if (v[0] < x0 - margin || v[0] > x1 + margin || v[1] < y0 - margin || v[1] > y1 + margin || v[2] < -margin ||
          v[2] > z1 + 60.0) {
        root.report().add(c->source(), "regions[" + std::to_string(i - 1) + "].roi_center_mm",
                          "region ROI centre (" + fmt(v[0]) + ", " + fmt(v[1]) + ", " + fmt(v[2]) +
                              ") is off the body described in [geometry] (body spans x " + fmt(x0) + " to " +
                              fmt(x1) + ", y " + fmt(y0) + " to " + fmt(y1) + ", z 0 to " + fmt(z1) +
                              "); move the ROI onto the part");
      }
    }
  }
  for (const auto& [key_path, region] : links) {
    if (names.contains(region)) continue;
    const toml::node* node = doc.at_path(key_path).node();
    root.report().add(node != nullptr ? node->source() : doc.source(), key_path,
                      "no [[regions]] entry is named \"" + region + "\"");
  }
}

}  // namespace

void read_geometry(TableReader& root, PartGeometry& g) {
  auto t = root.table("geometry");
  if (!t) return;
  g.present = true;
  t->number("surface_grid_mm", g.surface_grid_mm, {0.02, 2.0});
  t->number("material_grid_mm", g.material_grid_mm, {0.01, 0.05});
  t->integer("clamps", g.clamps, {0, 8});
  t->integer("clutter_items", g.clutter_items, {0, 50});
  if (auto v = t->table("variation")) {
    v->number("form_deviation_mm", g.variation.form_deviation_mm, {0.0, 5.0});
    v->number("placement_tolerance_mm", g.variation.placement_tolerance_mm, {0.0, 100.0});
    v->number("placement_tolerance_deg", g.variation.placement_tolerance_deg, {0.0, 45.0});
    v->number("placement_tilt_deg", g.variation.placement_tilt_deg, {0.0, 5.0});
  }
  t->tables(
      "blocks",
      [&](TableReader& b, std::size_t) {
        BodyBlock block;
        b.vec3("min_mm", block.min_mm, kLen, Need::required);
        b.vec3("max_mm", block.max_mm, kLen, Need::required);
        if (block.min_mm[2] < 0.0) b.error("min_mm", "z must be >= 0 (the part's bottom is on z = 0)");
        std::vector<double> slope{0.0, 0.0};
        b.numbers("top_slope_deg", slope, {-60.0, 60.0}, 2, 2);
        if (slope.size() == 2) block.top_slope_deg = {slope[0], slope[1]};
        for (int a = 0; a < 3; ++a) {
          const auto i = static_cast<std::size_t>(a);
          if (block.max_mm[i] <= block.min_mm[i]) {
            b.error("max_mm", std::string("must be greater than min_mm on every axis (axis ") +
                                  static_cast<char>('x' + a) + " is not)");
            return;
          }
        }
        const double hx = 0.5 * (block.max_mm[0] - block.min_mm[0]);
        const double hy = 0.5 * (block.max_mm[1] - block.min_mm[1]);
        const double drop = std::abs(std::tan(block.top_slope_deg[0] * std::numbers::pi / 180.0)) * hx +
                            std::abs(std::tan(block.top_slope_deg[1] * std::numbers::pi / 180.0)) * hy;
        if (block.max_mm[2] - drop <= block.min_mm[2])
          b.error("top_slope_deg", "the tilted top would go below the block's bottom (it drops " + fmt(drop) +
                                       " mm at a corner); make the block taller or the slope smaller");
        g.blocks.push_back(block);
      },
      Need::required);
  t->tables("cylinders", [&](TableReader& c, std::size_t) {
    BodyCylinder cyl;
    cylinder(c, cyl);
    g.cylinders.push_back(cyl);
  });
  std::vector<std::pair<std::string, std::string>> links;
  t->tables("ring_flashes", [&](TableReader& r, std::size_t i) {
    RingFlash f;
    r.string("region", f.region, Need::required);
    cylinder(r, f.cylinder);
    r.number("parting_z_mm", f.parting_z_mm, kPos, Need::required);
    range(r, "thickness_mm", f.thickness_mm, {0.05, 10.0});
    range(r, "extent_mm", f.extent_mm, {0.1, 50.0});
    r.number("edge_irregularity_mm", f.edge_irregularity_mm, {0.0, 10.0});
    r.number("gap_fraction", f.gap_fraction, {0.0, 0.9});
    if (f.parting_z_mm - 0.5 * f.thickness_mm.max < f.cylinder.base_z_mm ||
        f.parting_z_mm + 0.5 * f.thickness_mm.max > f.cylinder.top_z_mm)
      r.error("parting_z_mm", "the fin (up to " + fmt(f.thickness_mm.max) + " mm thick) must lie between base_z_mm " +
                                  fmt(f.cylinder.base_z_mm) + " and top_z_mm " + fmt(f.cylinder.top_z_mm));
    if (f.edge_irregularity_mm >= f.extent_mm.min)
      r.error("edge_irregularity_mm", "must be smaller than the smallest extent (" + fmt(f.extent_mm.min) + " mm)");
    links.emplace_back("geometry.ring_flashes[" + std::to_string(i) + "].region", f.region);
    g.ring_flashes.push_back(f);
  });
  // Features standing on the body must stand on it.
  auto on_body = [&](TableReader& r, std::string_view key, double x, double y) {
    if (std::isnan(config::nominal_top_z_mm(g, x, y)))
      r.error(key, "point " + where_xy(x, y) + " is off the body (no block or cylinder under it)");
  };
  t->tables("risers", [&](TableReader& r, std::size_t i) {
    Riser f;
    r.string("region", f.region, Need::required);
    xy(r, "center_mm", f.center_mm, Need::required);
    range(r, "diameter_mm", f.diameter_mm, {0.5, 500.0});
    range(r, "height_mm", f.height_mm, {0.1, 500.0});
    range(r, "top_tilt_deg", f.top_tilt_deg, {0.0, 45.0});
    r.number("roughness_mm", f.roughness_mm, {0.0, 10.0});
    on_body(r, "center_mm", f.center_mm[0], f.center_mm[1]);
    links.emplace_back("geometry.risers[" + std::to_string(i) + "].region", f.region);
    g.risers.push_back(f);
  });
  t->tables("straight_flashes", [&](TableReader& r, std::size_t i) {
    StraightFlash f;
    r.string("region", f.region, Need::required);
    xy(r, "start_mm", f.start_mm, Need::required);
    r.number("direction_deg", f.direction_deg, {-360.0, 360.0});
    range(r, "length_mm", f.length_mm, {0.5, 5000.0});
    range(r, "height_mm", f.height_mm, {0.05, 100.0});
    range(r, "thickness_mm", f.thickness_mm, {0.05, 20.0});
    r.number("edge_irregularity_mm", f.edge_irregularity_mm, {0.0, 10.0});
    on_body(r, "start_mm", f.start_mm[0], f.start_mm[1]);
    const double a = f.direction_deg * std::numbers::pi / 180.0;
    on_body(r, "length_mm", f.start_mm[0] + f.length_mm.max * std::cos(a), f.start_mm[1] + f.length_mm.max * std::sin(a));
    links.emplace_back("geometry.straight_flashes[" + std::to_string(i) + "].region", f.region);
    g.straight_flashes.push_back(f);
  });
  t->finish();
  check_regions(root, g, links);
}

}  // namespace fettle::config::detail

namespace fettle::config {

double nominal_top_z_mm(const PartGeometry& g, double x, double y) {
  double top = std::nan("");
  auto take = [&](double z) { top = std::isnan(top) ? z : std::max(top, z); };
  for (const auto& b : g.blocks) {
    if (x < b.min_mm[0] || x > b.max_mm[0] || y < b.min_mm[1] || y > b.max_mm[1]) continue;
    const double cx = 0.5 * (b.min_mm[0] + b.max_mm[0]);
    const double cy = 0.5 * (b.min_mm[1] + b.max_mm[1]);
    take(b.max_mm[2] + std::tan(b.top_slope_deg[0] * std::numbers::pi / 180.0) * (x - cx) +
         std::tan(b.top_slope_deg[1] * std::numbers::pi / 180.0) * (y - cy));
  }
  auto cyl = [&](const BodyCylinder& c) {
    if (std::hypot(x - c.center_mm[0], y - c.center_mm[1]) <= c.radius_mm) take(c.top_z_mm);
  };
  for (const auto& c : g.cylinders) cyl(c);
  for (const auto& r : g.ring_flashes) cyl(r.cylinder);
  return top;
}

}  // namespace fettle::config
