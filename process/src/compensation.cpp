// The cell learns its own bias (fettle/process/compensation.hpp says how).
#include "fettle/process/compensation.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <optional>
#include <sstream>
#include <unordered_map>

#include <Eigen/Eigenvalues>
#include <nlohmann/json.hpp>

#include "fettle/core/atomic_file.hpp"
#include "fettle/process/footprint.hpp"
#include "internal.hpp"

namespace fettle::process {

namespace {

/// Tool poses by the grid cells their bounding boxes, grown by `grow`, overlap.
class ToolIndex {
 public:
  ToolIndex(std::vector<ToolSolid> poses, double cell, double grow) : poses_(std::move(poses)), keys_{cell} {
    for (std::size_t i = 0; i < poses_.size(); ++i) {
      const auto l = keys_.coords(poses_[i].box_min(grow)), h = keys_.coords(poses_[i].box_max(grow));
      for (auto z = l[2]; z <= h[2]; ++z)
        for (auto y = l[1]; y <= h[1]; ++y)
          for (auto x = l[0]; x <= h[0]; ++x) cells_[CellKeys::pack(x, y, z)].push_back(i);
    }
  }
  /// The smallest signed distance of q to any pose's tool, with that tool's normal; false when
  /// no pose is near.
  bool nearest(const Vec3& q, double& sd, Vec3& normal) const {
    const auto it = cells_.find(keys_.key(q));
    if (it == cells_.end()) return false;
    bool found = false;
    Vec3 n;
    for (auto i : it->second) {
      const double d = poses_[i].distance(q, n);
      if (!found || d < sd) sd = d, normal = n, found = true;
    }
    return found;
  }
  [[nodiscard]] bool empty() const { return poses_.empty(); }

 private:
  std::vector<ToolSolid> poses_;
  CellKeys keys_;
  std::unordered_map<std::int64_t, std::vector<std::size_t>> cells_;
};

/// The commanded tool poses that cut: every pose and move sample but the air moves (cone tools
/// are not measured, the header says so).
std::vector<ToolSolid> commanded_tools(const LoadedRecipe& loaded, const std::vector<Trajectory>& ground) {
  std::vector<ToolSolid> out;
  for_each_tool_pose(loaded, ground, false, [&](std::size_t, const config::Tool& tool, const Pose& m) {
    if (tool.shape == config::ToolShape::cone) return;
    out.push_back(ToolSolid::of(tool, m.to_transform()));
  });
  return out;
}

/// The first scan's surface as seen from above: the highest point of each base-frame x-y cell.
/// Where the re-scan lies clearly below it, material was removed: the tool cut there (it did
/// not only pass by a surface it left as it was).
class HeightColumns {
 public:
  HeightColumns(const vision::Inspection& before, double cell) : cell_(cell) {
    const Eigen::Isometry3f T = before.whole.T_scene_template.cast<float>();
    for (const auto& p : before.scene_part.points) {
      const Eigen::Vector3f b = T * p;
      const auto k = key(b.x(), b.y());
      const auto it = top_.find(k);
      if (it == top_.end()) top_.emplace(k, b.z());
      else it->second = std::max(it->second, b.z());
    }
  }
  /// How far the first scan's surface stood above q (nullopt: the first scan saw nothing there).
  [[nodiscard]] std::optional<double> removed_above(const Vec3& q) const {
    const auto it = top_.find(key(q.x(), q.y()));
    if (it == top_.end()) return std::nullopt;
    return static_cast<double>(it->second) - q.z();
  }
  [[nodiscard]] bool empty() const { return top_.empty(); }

 private:
  [[nodiscard]] std::int64_t key(double x, double y) const {
    const auto cx = static_cast<std::int64_t>(std::floor(x / cell_));
    const auto cy = static_cast<std::int64_t>(std::floor(y / cell_));
    return (cx << 32) ^ (cy & 0xFFFFFFFF);
  }
  double cell_;
  std::unordered_map<std::int64_t, float> top_;
};

struct Sample {
  double sd;
  Vec3 n;
};

std::string fmt3(const Vec3& v, int precision) {
  char buf[96];
  std::snprintf(buf, sizeof buf, "(%.*f, %.*f, %.*f)", precision, v.x(), precision, v.y(), precision, v.z());
  return buf;
}

}  // namespace

int CutOffset::observed_directions() const { return static_cast<int>(std::lround(observed.trace())); }

std::string CutOffset::describe() const {
  return fmt3(offset_mm, 3) + " mm +- " + fmt3(std_mm, 3) + " from " + std::to_string(points) + " cut-surface points, " +
         std::to_string(observed_directions()) + " of 3 directions observed";
}

Result<CutOffset> measure_cut_offset(const LoadedRecipe& loaded, const vision::Inspection& before,
                                     const std::vector<Trajectory>& ground, const VerificationResult& after,
                                     const CutOffsetSettings& settings) {
  const ToolIndex tools(commanded_tools(loaded, ground), 8.0, settings.band_mm);
  const HeightColumns first_scan(before, settings.column_mm);
  if (tools.empty() || first_scan.empty())
    return Error{"compensation.no_cut", "no cut to measure: " +
                                            std::string(tools.empty() ? "no grinding pose" : "no first scan") +
                                            " in this cycle"};
  // The re-scanned ROI points (base frame) near the commanded tool surface, where material was
  // removed.
  std::vector<Sample> samples;
  for (const auto& r : after.regions) {
    const Eigen::Isometry3d T = r.T_base_region;
    for (const auto& p : r.roi_points_part) {
      const Vec3 q = T * p.cast<double>();
      const auto removed = first_scan.removed_above(q);
      if (!removed || *removed < settings.removed_min_mm) continue;
      Sample s{};
      if (!tools.nearest(q, s.sd, s.n) || std::abs(s.sd) > settings.band_mm) continue;
      samples.push_back(s);
    }
  }
  if (samples.size() < settings.min_points)
    return Error{"compensation.no_cut", "no cut to measure: " + std::to_string(samples.size()) +
                                            " re-scanned points near the commanded tool surface where material was "
                                            "removed (at least " + std::to_string(settings.min_points) + ")"};
  // Robust least squares sd_i = n_i . b: points off the fit by more than a shrinking gate are
  // left out (material the tool did not reach, a neighbouring surface it passed by), the rest
  // weighted by Huber's rule.
  CutOffset out;
  Vec3 b = Vec3::Zero();
  Eigen::Matrix3d P = Eigen::Matrix3d::Zero();    // projector onto the observed directions
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();  // of b
  double sigma = 0.0;
  std::size_t used = 0;
  constexpr double kHuberMm = 0.05;
  for (const double gate : {settings.band_mm, 0.5 * settings.band_mm, 0.3, 0.2, 0.15, 0.15}) {
    Eigen::Matrix3d N = Eigen::Matrix3d::Zero();
    Vec3 g = Vec3::Zero();
    double e2 = 0.0, wsum = 0.0;
    used = 0;
    for (const auto& s : samples) {
      const double e = s.sd - s.n.dot(b);
      if (std::abs(e) > gate) continue;
      const double w = std::abs(e) <= kHuberMm ? 1.0 : kHuberMm / std::abs(e);
      N += w * s.n * s.n.transpose();
      g += w * s.sd * s.n;
      e2 += w * e * e;
      wsum += w;
      ++used;
    }
    if (used < settings.min_points) break;
    sigma = std::sqrt(e2 / wsum);
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(N);
    b.setZero();
    P.setZero();
    cov.setZero();
    for (int k = 0; k < 3; ++k) {
      const double lambda = eig.eigenvalues()(k);
      if (!(lambda >= static_cast<double>(settings.min_points))) continue;
      const Vec3 v = eig.eigenvectors().col(k);
      b += (v.dot(g) / lambda) * v;
      P += v * v.transpose();
      cov += (sigma * sigma / lambda) * v * v.transpose();
    }
  }
  if (used < settings.min_points || P.trace() < 0.5)
    return Error{"compensation.no_cut", "no cut to measure: " + std::to_string(used) +
                                            " re-scanned points lie on the commanded tool surface (at least " +
                                            std::to_string(settings.min_points) + " along one direction)"};
  out.offset_mm = b;
  out.observed = P;
  out.std_mm = cov.diagonal().cwiseMax(0.0).cwiseSqrt();
  out.points = used;
  out.rms_mm = sigma;
  return out;
}

namespace {

/// The projector onto the span of a symmetric positive semi-definite matrix's eigenvectors
/// whose eigenvalues are at least half the largest possible one (a projector's 1).
Eigen::Matrix3d projector_onto(const Eigen::Matrix3d& M) {
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(0.5 * (M + M.transpose()));
  Eigen::Matrix3d P = Eigen::Matrix3d::Zero();
  for (int k = 0; k < 3; ++k)
    if (eig.eigenvalues()(k) >= 0.5) P += eig.eigenvectors().col(k) * eig.eigenvectors().col(k).transpose();
  return P;
}

nlohmann::ordered_json matrix_to_json(const Eigen::Matrix3d& M) {
  nlohmann::ordered_json rows = nlohmann::ordered_json::array();
  for (int r = 0; r < 3; ++r) rows.push_back({M(r, 0), M(r, 1), M(r, 2)});
  return rows;
}

/// A 3x3 matrix as rows; absent: zero (learned along no direction: the full stated error is kept).
Eigen::Matrix3d matrix_from_json(const nlohmann::json& j, const char* key) {
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  if (!j.contains(key)) return M;
  const auto& rows = j.at(key);
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) M(r, c) = rows.at(static_cast<std::size_t>(r)).at(static_cast<std::size_t>(c)).get<double>();
  if (!M.allFinite()) throw std::invalid_argument(std::string(key) + " is not finite");
  return M;
}

}  // namespace

Vec3 CellBias::update(const CutOffset& measured, const config::CompensationSection& settings) {
  const Vec3 before = bias_mm;
  // the measurement is the cell's whole offset (the re-scan against the commanded path, which
  // already had the estimate taken off): the estimate moves towards it along what it observed
  const Vec3 innovation = measured.observed * (measured.offset_mm - bias_mm);
  bias_mm += settings.gain * innovation;
  scatter_mm2 = (1.0 - settings.gain) * scatter_mm2 + settings.gain * innovation * innovation.transpose();
  learned = projector_onto(learned + measured.observed);
  if (const double n = bias_mm.norm(); n > settings.max_offset_mm && n > 0.0) bias_mm *= settings.max_offset_mm / n;
  ++updates;
  return bias_mm - before;
}

double PlacementUncertainty::along_mm(const Vec3& n) const { return std::sqrt(std::max(0.0, n.dot(bound_mm2 * n))); }

std::string PlacementUncertainty::describe() const {
  // sideways: the larger of the two horizontal principal bounds
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> h(bound_mm2.topLeftCorner<2, 2>());
  char buf[96];
  std::snprintf(buf, sizeof buf, "%.2f mm sideways, %.2f mm vertically", std::sqrt(std::max(0.0, h.eigenvalues()(1))),
                along_mm(Vec3::UnitZ()));
  return buf;
}

PlacementUncertainty placement_uncertainty(const config::SafetySection& safety, const CellBias& bias,
                                           const config::CompensationSection& settings) {
  PlacementUncertainty u;
  if (safety.calibration_accuracy_mm <= 0.0 && safety.robot_accuracy_mm <= 0.0 && safety.robot_repeatability_mm <= 0.0)
    return u;  // nothing stated: the regions' allowances alone
  const double systematic2 =
      safety.calibration_accuracy_mm * safety.calibration_accuracy_mm + safety.robot_accuracy_mm * safety.robot_accuracy_mm;
  const Eigen::Matrix3d I = Eigen::Matrix3d::Identity();
  const Eigen::Matrix3d& P = bias.learned;
  const double g = std::clamp(settings.gain, 1e-6, 1.0);
  const double left = std::pow(1.0 - g, static_cast<double>(bias.updates));  // of the stated systematic error
  u.bound_mm2 = systematic2 * (I - P) + left * left * systematic2 * P + g / (2.0 - g) * (P * bias.scatter_mm2 * P) +
                safety.robot_repeatability_mm * safety.robot_repeatability_mm * I;
  return u;
}

RegrindCompensation regrind_compensation(const config::SafetySection& safety, const CellBias& cell,
                                         const CutOffset& measured, const config::CompensationSection& settings) {
  RegrindCompensation out;
  const Eigen::Matrix3d I = Eigen::Matrix3d::Identity(), P = measured.observed, Q = I - P;
  out.bias_mm = P * measured.offset_mm + Q * cell.bias_mm;
  const auto usual = placement_uncertainty(safety, cell, settings);
  if (usual.bound_mm2.isZero()) return out;  // nothing stated: the regions' allowances alone
  const Eigen::Matrix3d scatter = measured.std_mm.cwiseAbs2().asDiagonal();
  const double repeatability2 = safety.robot_repeatability_mm * safety.robot_repeatability_mm;
  out.placement.bound_mm2 = Q * usual.bound_mm2 * Q + P * (repeatability2 * I + scatter) * P;
  return out;
}

std::string CellBias::describe() const {
  return fmt3(bias_mm, 3) + " mm after " + std::to_string(updates) + " cycle" + (updates == 1 ? "" : "s");
}

Result<CellBias> load_cell_bias(const std::filesystem::path& file) {
  std::error_code ec;
  if (!std::filesystem::exists(file, ec)) return CellBias{};
  std::ifstream in(file);
  std::stringstream text;
  text << in.rdbuf();
  try {
    const auto j = nlohmann::json::parse(text.str());
    CellBias b;
    const auto& v = j.at("bias_mm");
    b.bias_mm = Vec3(v.at(0).get<double>(), v.at(1).get<double>(), v.at(2).get<double>());
    if (!b.bias_mm.allFinite()) throw std::invalid_argument("bias_mm is not finite");
    b.updates = j.value("updates", std::size_t{0});
    b.calibration_id = j.value("calibration_id", std::string{});
    b.tools_id = j.value("tools_id", std::string{});
    b.learned = matrix_from_json(j, "learned");
    b.scatter_mm2 = matrix_from_json(j, "scatter_mm2");
    return b;
  } catch (const std::exception& e) {
    return Error{"compensation.state", file.string() + ": not a compensation state file (" + e.what() + ")"};
  }
}

Status save_cell_bias(const std::filesystem::path& file, const CellBias& bias) {
  const nlohmann::ordered_json j = {{"bias_mm", {bias.bias_mm.x(), bias.bias_mm.y(), bias.bias_mm.z()}},
                                    {"updates", bias.updates},
                                    {"calibration_id", bias.calibration_id},
                                    {"tools_id", bias.tools_id},
                                    {"learned", matrix_to_json(bias.learned)},
                                    {"scatter_mm2", matrix_to_json(bias.scatter_mm2)},
                                    {"frame", "base: where the tool cuts minus where it is told to, mm"}};
  return write_file_atomic(file, j.dump(2) + "\n");
}

std::filesystem::path cell_bias_file(const config::CellConfig& cell) {
  return cell.compensation.state_file.empty() ? cell.cell.state_dir / "compensation.json" : cell.compensation.state_file;
}

namespace {
std::string hex_hash(const std::string& text) {
  char buf[24];
  std::snprintf(buf, sizeof buf, "%016zx", std::hash<std::string>{}(text));
  return buf;
}
}  // namespace

std::string tools_identity(const config::PartRecipe& recipe) {
  std::ostringstream s;
  for (const auto& t : recipe.tools)
    s << t.name << ' ' << static_cast<int>(t.shape) << ' ' << t.diameter_mm << ' ' << t.length_mm << ' '
      << t.cone_angle_deg << ' ' << t.tcp_mm[0] << ' ' << t.tcp_mm[1] << ' ' << t.tcp_mm[2] << ';';
  return hex_hash(s.str());
}

}  // namespace fettle::process
