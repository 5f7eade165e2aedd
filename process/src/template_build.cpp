// `fettle template build`: a golden casting's template from views of it on the fixture
// (fettle/process/pipeline.hpp, build_template).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <deque>
#include <limits>
#include <unordered_map>

#include "fettle/process/pipeline.hpp"
#include "fettle/config/roi.hpp"
#include "fettle/vision/inspect.hpp"
#include "fettle/vision/preprocess.hpp"
#include "internal.hpp"

namespace fettle::process {

namespace {

/// Template points each region's ROI must hold.
constexpr std::size_t kMinRegionPoints = 50;

/// The indices of the largest piece of `points` no gap wider than `gap` divides: connected
/// components of the occupied cells of a `gap` grid (26-neighbours).
std::vector<std::size_t> largest_piece(const std::vector<Eigen::Vector3f>& points, double gap) {
  const CellKeys keys{gap};
  std::unordered_map<std::int64_t, std::vector<std::size_t>> cells;
  for (std::size_t i = 0; i < points.size(); ++i) cells[keys.key(points[i].cast<double>())].push_back(i);
  std::unordered_map<std::int64_t, int> label;
  std::vector<std::size_t> best;
  int next = 0;
  for (const auto& [start, members] : cells) {
    if (label.count(start) != 0) continue;
    std::vector<std::size_t> piece;
    std::deque<std::array<std::int64_t, 3>> todo{keys.coords(points[members.front()].cast<double>())};
    label[start] = next;
    while (!todo.empty()) {
      const auto k = todo.front();
      todo.pop_front();
      const auto& in = cells.at(CellKeys::pack(k[0], k[1], k[2]));
      piece.insert(piece.end(), in.begin(), in.end());
      for (int dz = -1; dz <= 1; ++dz)
        for (int dy = -1; dy <= 1; ++dy)
          for (int dx = -1; dx <= 1; ++dx) {
            const std::array<std::int64_t, 3> n{k[0] + dx, k[1] + dy, k[2] + dz};
            const auto p = CellKeys::pack(n[0], n[1], n[2]);
            if (cells.count(p) == 0 || label.count(p) != 0) continue;
            label[p] = next;
            todo.push_back(n);
          }
    }
    ++next;
    if (piece.size() > best.size()) best = std::move(piece);
  }
  std::sort(best.begin(), best.end());
  return best;
}

}  // namespace

Result<BuiltTemplate> build_template(const config::PartRecipe& recipe, const std::vector<View>& views,
                                     const TemplateBuildSettings& settings) {
  auto fused = fuse_in_base(views, recipe.vision.jump_edge_mm);
  if (!fused) return fused.error();
  BuiltTemplate out;
  out.fused_points = fused->size();
  // The golden casting sits on the fixture as the castings will: its part frame is the
  // fixture's nominal one, the table its z = 0 plane.
  const Transform T_part_base = vision::nominal_T_fixture_part(recipe).inverse();
  vision::Cloud part = vision::transformed(*fused, T_part_base);
  part.normals.clear();
  const bool boxed = (settings.box_min_mm.array() < settings.box_max_mm.array()).all();
  constexpr double kAll = std::numeric_limits<double>::max();
  Vec3 lo = boxed ? settings.box_min_mm : Vec3(-kAll, -kAll, -kAll);
  const Vec3 hi = boxed ? settings.box_max_mm : Vec3(kAll, kAll, kAll);
  lo.z() = std::max(lo.z(), settings.above_table_mm);
  const vision::Cloud above = vision::crop_box(part, Transform::Identity(), lo, hi);
  if (above.points.size() < 100)
    return Error{"template.empty", "the views hold " + std::to_string(above.points.size()) + " points more than " +
                                       std::to_string(settings.above_table_mm) +
                                       " mm above the fixture's table: is the golden casting on the fixture?"};
  // Clamps and clutter beside it: the largest piece is the casting.
  const auto keep = largest_piece(above.points, settings.cluster_gap_mm);
  vision::Cloud piece;
  piece.points.reserve(keep.size());
  for (const auto i : keep) piece.points.push_back(above.points[i]);
  out.dropped_points = above.points.size() - piece.points.size();
  piece = vision::voxel_downsample(piece, settings.voxel_mm);
  piece = vision::remove_statistical_outliers(piece, recipe.vision.outlier_neighbours, recipe.vision.outlier_std_ratio);
  // Normals by PCA over the fused cloud, each turned towards the camera that saw the nearest
  // point of a view: a normal turned towards one viewpoint above the part points into the part
  // on every wall facing away from it.
  vision::estimate_normals(piece, settings.normal_neighbours, Eigen::Vector3f(0.0F, 0.0F, 1e4F));
  std::vector<Eigen::Vector3f> seen_from(piece.size(), Eigen::Vector3f(0.0F, 0.0F, 1e4F));
  {
    std::unordered_map<std::int64_t, Eigen::Vector3f> camera_at;  // by 2 mm cell: the camera nearest above
    const CellKeys keys{2.0};
    const auto pack = [&keys](const Eigen::Vector3f& p) { return keys.key(p.cast<double>()); };
    for (const auto& v : views) {
      const Transform T_part_camera = T_part_base * v.T_base_camera;
      const Eigen::Vector3f eye = T_part_camera.translation().cast<float>();
      const Eigen::Isometry3f T = T_part_camera.cast<float>();
      for (const auto& p : v.cloud.points)
        if (p.allFinite()) camera_at.emplace(pack(T * p), eye);
    }
    for (std::size_t i = 0; i < piece.size(); ++i)
      if (const auto it = camera_at.find(pack(piece.points[i])); it != camera_at.end()) seen_from[i] = it->second;
  }
  for (std::size_t i = 0; i < piece.size(); ++i)
    if (piece.normals[i].dot(seen_from[i] - piece.points[i]) < 0.0F) piece.normals[i] = -piece.normals[i];
  // Every region must find its surface in the template: a template of a clamp (an empty
  // fixture) or of a casting far off its nominal pose would otherwise pass.
  for (const auto& region : recipe.regions) {
    std::size_t inside = 0;
    for (const auto& p : piece.points)
      if (config::roi_contains(region, p)) ++inside;
    if (inside < kMinRegionPoints)
      return Error{"template.regions",
                   "region '" + region.name + "': " + std::to_string(inside) + " template points in its ROI (at least " +
                       std::to_string(kMinRegionPoints) +
                       "): is the golden casting on the fixture at its nominal pose ([fixture] of the recipe)?"};
  }
  out.cloud = std::move(piece);
  return out;
}

}  // namespace fettle::process
