// Evaluation after Zhu et al. 2022, section 4: per region ROI, scanned points farther from
// the reference surface than 0.3 / 0.4 / 0.5 mm ("template comparison" against the golden
// part, "batch consistency" against another ground casting).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>

#include "casting_model.hpp"

namespace fettle::sim {
namespace {

std::vector<Eigen::Vector3f> points_in_part(const std::vector<Capture>& captures) {
  std::vector<Eigen::Vector3f> out;
  for (const auto& c : captures) {
    const Eigen::Isometry3f T = (c.truth.T_base_part.inverse() * c.truth.T_base_camera).cast<float>();
    for (const auto& p : c.cloud.points)
      if (p.allFinite()) out.push_back(T * p);
  }
  return out;
}

Evaluation evaluate_all(const config::PartRecipe& recipe, const std::vector<Capture>& captures,
                        const std::function<double(const Vec3&)>& distance) {
  Evaluation e;
  const auto pts = points_in_part(captures);
  for (const auto& r : recipe.regions) e.regions.push_back(evaluate_region(r, pts, distance));
  return e;
}

}  // namespace

RegionEvaluation evaluate_region(const config::Region& region, const std::vector<Eigen::Vector3f>& points_part,
                                 const std::function<double(const Vec3&)>& distance_mm) {
  RegionEvaluation r;
  r.name = region.name;
  const Eigen::Vector3f c(static_cast<float>(region.roi_center_mm[0]), static_cast<float>(region.roi_center_mm[1]),
                          static_cast<float>(region.roi_center_mm[2]));
  const Eigen::Vector3f h(static_cast<float>(region.roi_size_mm[0] / 2), static_cast<float>(region.roi_size_mm[1] / 2),
                          static_cast<float>(region.roi_size_mm[2] / 2));
  for (const auto& p : points_part) {
    if (((p - c).cwiseAbs() - h).maxCoeff() > 0) continue;
    ++r.roi_points;
    const double d = distance_mm(p.cast<double>());
    if (d > 0.3) ++r.over_0_3;
    if (d > 0.4) ++r.over_0_4;
    if (d > 0.5) ++r.over_0_5;
    r.max_residual_mm = std::max(r.max_residual_mm, d);
  }
  return r;
}

Evaluation evaluate_against_template(const config::PartRecipe& recipe, const std::vector<Capture>& captures,
                                     const Casting& casting, const std::vector<Gouge>& gouges) {
  auto e = evaluate_all(recipe, captures, [&](const Vec3& p) { return casting.distance_to_golden_mm(p); });
  e.label = "template comparison, casting " + std::to_string(casting.seed());
  const auto& all = gouges.empty() ? casting.model().gouges : gouges;
  e.gouge_count = all.size();
  for (const auto& g : all) e.max_gouge_depth_mm = std::max(e.max_gouge_depth_mm, g.depth_mm);
  return e;
}

Evaluation evaluate_against_part(const config::PartRecipe& recipe, const std::vector<Capture>& captures,
                                 const Casting& reference) {
  auto e = evaluate_all(recipe, captures, [&](const Vec3& p) { return reference.distance_to_surface_mm(p); });
  e.label = "batch consistency against casting " + std::to_string(reference.seed());
  return e;
}

std::string format_table(const std::vector<Evaluation>& evaluations) {
  std::ostringstream s;
  char line[256];
  for (const auto& e : evaluations) {
    s << e.label << "\n";
    std::snprintf(line, sizeof line, "  %-20s %10s %10s %10s %10s %12s\n", "region", "ROI points", "> 0.3 mm",
                  "> 0.4 mm", "> 0.5 mm", "max resid mm");
    s << line;
    for (const auto& r : e.regions) {
      std::snprintf(line, sizeof line, "  %-20s %10zu %10zu %10zu %10zu %12.3f\n", r.name.c_str(), r.roi_points,
                    r.over_0_3, r.over_0_4, r.over_0_5, r.max_residual_mm);
      s << line;
    }
    std::snprintf(line, sizeof line, "  gouges: %zu, max gouge depth %.3f mm\n", e.gouge_count, e.max_gouge_depth_mm);
    s << line;
  }
  return s.str();
}

}  // namespace fettle::sim
