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
  ToolIndex(std::vector<ToolSolid> poses, std::vector<std::size_t> tools, double cell, double grow)
      : poses_(std::move(poses)), tools_(std::move(tools)), keys_{cell} {
    for (std::size_t i = 0; i < poses_.size(); ++i) {
      const auto l = keys_.coords(poses_[i].box_min(grow)), h = keys_.coords(poses_[i].box_max(grow));
      for (auto z = l[2]; z <= h[2]; ++z)
        for (auto y = l[1]; y <= h[1]; ++y)
          for (auto x = l[0]; x <= h[0]; ++x) cells_[CellKeys::pack(x, y, z)].push_back(i);
    }
  }
  /// The smallest signed distance of q to any pose's tool, with that tool's normal, the share of
  /// the normal across the tool's axis (1 on a ball and a cylinder's side, 0 on its flat end:
  /// how much of a smaller radius shows there) and the tool's index; false when no pose is near.
  bool nearest(const Vec3& q, double& sd, Vec3& normal, double& radial, std::size_t& tool,
               std::size_t* pose = nullptr) const {
    const auto it = cells_.find(keys_.key(q));
    if (it == cells_.end()) return false;
    bool found = false;
    Vec3 n;
    std::size_t best = 0;
    for (auto i : it->second) {
      const double d = poses_[i].distance(q, n);
      if (!found || d < sd) sd = d, normal = n, best = i, found = true;
    }
    if (found) {
      const auto& p = poses_[best];
      radial = p.ball ? 1.0 : std::clamp((normal - normal.dot(p.axis) * p.axis).norm(), 0.0, 1.0);
      tool = tools_[best];
      if (pose != nullptr) *pose = best;
    }
    return found;
  }
  [[nodiscard]] const ToolSolid& pose(std::size_t i) const { return poses_[i]; }
  [[nodiscard]] bool empty() const { return poses_.empty(); }

 private:
  std::vector<ToolSolid> poses_;
  std::vector<std::size_t> tools_;  // per pose: index into the recipe's tools
  CellKeys keys_;
  std::unordered_map<std::int64_t, std::vector<std::size_t>> cells_;
};

/// The commanded tool poses that cut, with the wear they were commanded with: every pose and
/// move sample but the air moves (cone tools are not measured, the header says so).
ToolIndex commanded_tools(const LoadedRecipe& loaded, const std::vector<Trajectory>& ground, const ToolWearMm& wear,
                          double grow) {
  const auto& tools = loaded.recipe.tools;
  std::vector<config::Tool> worn;
  for (const auto& t : tools) worn.push_back(worn_tool(t, wear));
  std::vector<ToolSolid> poses;
  std::vector<std::size_t> index;
  for_each_tool_pose(loaded, ground, false, [&](std::size_t, const config::Tool& tool, const Pose& m) {
    if (tool.shape == config::ToolShape::cone) return;
    const auto k = static_cast<std::size_t>(&tool - tools.data());
    poses.push_back(ToolSolid::of(worn[k], m.to_transform()));
    index.push_back(k);
  });
  return ToolIndex(std::move(poses), std::move(index), 8.0, grow);
}

/// The first scan's surface as seen from above: the highest point of each base-frame x-y cell.
/// Where the re-scan lies clearly below it, material was removed: the tool cut there (it did
/// not only pass by a surface it left as it was).
class HeightColumns {
 public:
  /// From the first scan's points (part frame), those in `roi`'s box only when given.
  HeightColumns(const vision::Inspection& before, double cell, const config::Region* roi = nullptr) : cell_(cell) {
    const Eigen::Isometry3f T = before.whole.T_scene_template.cast<float>();
    Eigen::Vector3f lo = Eigen::Vector3f::Constant(-1e30f), hi = Eigen::Vector3f::Constant(1e30f);
    if (roi != nullptr)
      for (int k = 0; k < 3; ++k) {
        const auto c = static_cast<float>(roi->roi_center_mm[static_cast<std::size_t>(k)]);
        const auto h = static_cast<float>(0.5 * roi->roi_size_mm[static_cast<std::size_t>(k)]);
        lo[k] = c - h, hi[k] = c + h;
      }
    for (const auto& p : before.scene_part.points)
      if ((p.array() >= lo.array()).all() && (p.array() <= hi.array()).all()) add((T * p).cast<double>());
  }
  /// No scan: columns from add().
  HeightColumns(std::nullptr_t, double cell) : cell_(cell) {}
  void add(const Vec3& b) {
    const auto k = key(b.x(), b.y());
    const auto z = static_cast<float>(b.z());
    const auto it = top_.find(k);
    if (it == top_.end()) {
      top_.emplace(k, Top{z, z, b});
    } else {
      if (z > it->second.z) it->second.z = z, it->second.at = b;
      it->second.bottom = std::min(it->second.bottom, z);
    }
  }
  /// Each column's highest point.
  template <class Fn>
  void for_each(Fn&& fn) const {
    for (const auto& [k, t] : top_) fn(t.at);
  }
  /// How far the surface seen over q's column (its highest point) stands above q (nullopt:
  /// nothing seen there).
  [[nodiscard]] std::optional<double> removed_above(const Vec3& q) const {
    const auto it = top_.find(key(q.x(), q.y()));
    if (it == top_.end()) return std::nullopt;
    return static_cast<double>(it->second.z) - q.z();
  }
  /// How far the lowest surface the first scan saw in q's column stood above q: a surface at
  /// q's height in the column (beside a fin, round a riser's foot) may be where the tool only
  /// passed by (nullopt: the first scan saw nothing there).
  [[nodiscard]] std::optional<double> below_all(const Vec3& q) const {
    const auto it = top_.find(key(q.x(), q.y()));
    if (it == top_.end()) return std::nullopt;
    return static_cast<double>(it->second.bottom) - q.z();
  }
  [[nodiscard]] bool empty() const { return top_.empty(); }
  /// The highest point of q's column and its eight neighbours (nullopt: none seen there).
  [[nodiscard]] std::optional<double> top_near(const Vec3& q) const {
    std::optional<double> out;
    for (int dy = -1; dy <= 1; ++dy)
      for (int dx = -1; dx <= 1; ++dx) {
        const auto it = top_.find(key(q.x() + dx * cell_, q.y() + dy * cell_));
        if (it != top_.end() && (!out || it->second.z > *out)) out = it->second.z;
      }
    return out;
  }

 private:
  [[nodiscard]] std::int64_t key(double x, double y) const {
    const auto cx = static_cast<std::int64_t>(std::floor(x / cell_));
    const auto cy = static_cast<std::int64_t>(std::floor(y / cell_));
    return (cx << 32) ^ (cy & 0xFFFFFFFF);
  }
  struct Top {
    float z;       // the highest point's height
    float bottom;  // the lowest point's
    Vec3 at;       // the highest point
  };
  double cell_;
  std::unordered_map<std::int64_t, Top> top_;
};

/// An unknown counts as observed when this share of it lies in the span the fit solved.
constexpr double kObservedShare = 0.9;
/// A wheel's own rate replaces its stated one from this many measurements of its radius on.
constexpr std::size_t kMinWearMeasurements = 3;
/// A tool's radius is fitted apart from the offset when this share of its column's information
/// is left once the offset is fitted (measure_cut_offset()).
constexpr double kSeparableShare = 0.3;

/// The projector onto the span of a symmetric positive semi-definite matrix's eigenvectors
/// whose eigenvalues are at least `least` (a projector's are 0 or 1).
Eigen::Matrix3d projector_onto(const Eigen::Matrix3d& M, double least) {
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(0.5 * (M + M.transpose()));
  Eigen::Matrix3d P = Eigen::Matrix3d::Zero();
  for (int k = 0; k < 3; ++k)
    if (eig.eigenvalues()(k) >= least) P += eig.eigenvectors().col(k) * eig.eigenvectors().col(k).transpose();
  return P;
}

/// The projector onto the directions of b-space a fit's solved span holds whole.
Eigen::Matrix3d observed_part(const Eigen::Matrix3d& solved) { return projector_onto(solved, kObservedShare); }

struct Sample {
  double sd;
  Vec3 n;
  double radial;       // share of n across the tool's axis
  std::size_t tool;    // index into the recipe's tools
  std::size_t region;  // index into the verification's regions
  bool edge = false;   // on a stub's edge (add_stub_edges), not on a cut surface
};

/// The edge a wheel's side left in a surface it cut part of: re-scan points (base frame) of a
/// surface that still stands as the first scan saw it, beside a wheel's side, where the same
/// surface went on further into the tool in the first scan and is gone in the re-scan. There the
/// real wheel stopped: such a point lies on the real tool's surface, sd = n . b - w like a cut
/// surface's (fettle/process/compensation.hpp), inside the commanded tool or outside it. A
/// ring's fin ground by a disc's side leaves such a stub round the flange: the wall it is
/// measured against stands edge-on to the camera and shows nothing, the stub's top does
/// (docs/compensation.md, "A wheel's radius from its stub").
/// Per bin of stub_bin_mm over the nearest pose's tip, the stub's outer edge is its deepest
/// point into the tool (a robust one: the fifth deepest in a hundred); the points within
/// stub_edge_mm of it are the samples. Points nearer the wall than that, and the tool's flat end
/// over an untouched face, are left out. Test Compensation.AWornDiscShowsItsRadiusInTheStubItLeaves.
void add_stub_edges(const VerificationResult& after, const ToolIndex& tools, const HeightColumns& first_scan,
                    const CutOffsetSettings& settings, std::vector<Sample>& samples) {
  HeightColumns rescan(nullptr, settings.stub_column_mm);
  for (const auto& r : after.regions)
    for (const auto& p : r.roi_points_part) rescan.add(r.T_base_region * p.cast<double>());
  const CellKeys bins{settings.stub_bin_mm};
  std::map<std::pair<std::size_t, std::int64_t>, std::vector<Sample>> by_bin;
  for (const auto& r : after.regions) {
    const Eigen::Isometry3d T = r.T_base_region;
    for (const auto& p : r.roi_points_part) {
      const Vec3 q = T * p.cast<double>();
      // a surface the first scan saw at this height: not removed
      const auto removed = first_scan.removed_above(q);
      if (!removed || std::abs(*removed) >= settings.removed_min_mm) continue;
      Sample s{};
      s.edge = true;
      s.region = static_cast<std::size_t>(&r - after.regions.data());
      std::size_t pose = 0;
      if (!tools.nearest(q, s.sd, s.n, s.radial, s.tool, &pose) || s.sd > settings.band_mm ||
          s.sd < -settings.stub_band_mm || s.radial < 0.5)
        continue;
      // one step further into the tool across its axis: the first scan's surface went on at this
      // height, the re-scan's is gone or stub_drop_mm lower (cut through, not a face's shallow cut)
      Vec3 in(-s.n.x(), -s.n.y(), 0.0);
      if (in.norm() < 0.5) continue;
      const Vec3 beyond = q + settings.column_mm * in.normalized();  // at q's height
      const auto was = first_scan.removed_above(beyond), now = rescan.removed_above(beyond);
      if (!was || std::abs(*was) >= 2.0 * settings.removed_min_mm || (now && *now > -settings.stub_drop_mm)) continue;
      by_bin[{s.region, bins.key(tools.pose(pose).a)}].push_back(s);
    }
  }
  for (auto& [bin, edge] : by_bin) {
    if (edge.size() < 3) continue;
    std::sort(edge.begin(), edge.end(), [](const Sample& a, const Sample& b) { return a.sd < b.sd; });
    const double deepest = edge[edge.size() / 20].sd;
    for (const auto& s : edge)
      if (s.sd >= deepest && s.sd <= deepest + settings.stub_edge_mm) samples.push_back(s);
  }
}

/// A robust least-squares fit sd_i = a_i . x over samples (rows a_i from `row`): points off the
/// fit by more than a shrinking gate are left out (material the tool did not reach, a
/// neighbouring surface it passed by), the rest weighted by Huber's rule. Only the directions
/// of x the samples fix with at least min_points' weight are solved for.
struct RobustFit {
  Eigen::VectorXd x;
  Eigen::MatrixXd solved;  // projector onto the solved directions
  Eigen::MatrixXd cov;     // of x
  double sigma = 0.0;
  std::size_t used = 0;
  std::vector<std::size_t> tool_points;  // used points on a tool's radius (radial > 0.5), per tool
};

template <class Row>
RobustFit robust_fit(const std::vector<Sample>& samples, const Row& row, int n, Eigen::VectorXd x0,
                     const std::vector<double>& gates, std::size_t tools, std::size_t min_points) {
  constexpr double kHuberMm = 0.05;
  RobustFit f;
  f.x = std::move(x0);
  f.solved = Eigen::MatrixXd::Zero(n, n);
  f.cov = Eigen::MatrixXd::Zero(n, n);
  f.tool_points.assign(tools, 0);
  for (const double gate : gates) {
    Eigen::MatrixXd N = Eigen::MatrixXd::Zero(n, n);
    Eigen::VectorXd g = Eigen::VectorXd::Zero(n);
    double e2 = 0.0, wsum = 0.0;
    f.used = 0;
    std::fill(f.tool_points.begin(), f.tool_points.end(), 0);
    for (const auto& s : samples) {
      const Eigen::VectorXd a = row(s);
      const double e = s.sd - a.dot(f.x);
      if (std::abs(e) > gate) continue;
      const double w = std::abs(e) <= kHuberMm ? 1.0 : kHuberMm / std::abs(e);
      N.noalias() += w * a * a.transpose();
      g += w * s.sd * a;
      e2 += w * e * e;
      wsum += w;
      ++f.used;
      if (s.radial > 0.5) ++f.tool_points[s.tool];
    }
    if (f.used < min_points) break;
    f.sigma = std::sqrt(e2 / wsum);
    const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(N);
    f.x.setZero();
    f.solved.setZero();
    f.cov.setZero();
    for (int k = 0; k < n; ++k) {
      const double lambda = eig.eigenvalues()(k);
      if (!(lambda >= static_cast<double>(min_points))) continue;
      const Eigen::VectorXd v = eig.eigenvectors().col(k);
      f.x += (v.dot(g) / lambda) * v;
      f.solved += v * v.transpose();
      f.cov += (f.sigma * f.sigma / lambda) * v * v.transpose();
    }
  }
  return f;
}

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
                                     const ToolWearMm& wear, const CutOffsetSettings& settings) {
  const ToolIndex tools = commanded_tools(loaded, ground, wear, settings.band_mm);
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
      const auto removed = first_scan.below_all(q);
      if (!removed || *removed < settings.removed_min_mm) continue;
      Sample s{};
      s.region = static_cast<std::size_t>(&r - after.regions.data());
      if (!tools.nearest(q, s.sd, s.n, s.radial, s.tool) || std::abs(s.sd) > settings.band_mm) continue;
      samples.push_back(s);
    }
  }
  add_stub_edges(after, tools, first_scan, settings, samples);
  if (samples.size() < settings.min_points)
    return Error{"compensation.no_cut", "no cut to measure: " + std::to_string(samples.size()) +
                                            " re-scanned points near the commanded tool surface where material was "
                                            "removed (at least " + std::to_string(settings.min_points) + ")"};
  // Each wheel's radius loss w_t, fitted with an offset of its own on its own cut surfaces:
  // sd_i = n_i . b_t - c_i w_t. Another tool's surfaces elsewhere do not tell it apart: the
  // offset there is not the offset here (a hand-eye rotation of 0.05 deg moves the cut 0.09 mm
  // over the part's 100 mm, and one offset for both gates the disc's stub out as outliers). The
  // column is fitted when what is left of its information once b_t is fitted is at least
  // kSeparableShare of it: a groove's bottom, cut by a ball, looks up, and its radius and the
  // offset's height move it alike (the offset takes it); a disc's side round a ring shows its
  // radius.
  const auto& recipe_tools = loaded.recipe.tools;
  const std::vector<double> gates{settings.band_mm, 0.5 * settings.band_mm, 0.3, 0.2, 0.15, 0.15};
  std::vector<std::optional<double>> wear_of(recipe_tools.size());  // measured radius loss per tool
  CutOffset out;
  for (std::size_t t = 0; t < recipe_tools.size(); ++t) {
    std::vector<Sample> own;
    double radial_weight = 0.0;
    Eigen::Matrix4d N = Eigen::Matrix4d::Zero();  // (b_t, w_t)
    for (const auto& s : samples) {
      if (s.tool != t) continue;
      own.push_back(s);
      radial_weight += s.radial * s.radial;
      Eigen::Vector4d a;
      a << s.n, -s.radial;
      N.noalias() += a * a.transpose();
    }
    if (radial_weight < static_cast<double>(settings.min_points)) continue;
    const double ridge = 1e-6 * std::max(1.0, N.trace() / 4.0);
    const Eigen::Matrix4d inv = (N + ridge * Eigen::Matrix4d::Identity()).inverse();
    if (1.0 / inv(3, 3) < kSeparableShare * N(3, 3)) continue;
    const RobustFit tf = robust_fit(
        own,
        [](const Sample& s) {
          Eigen::VectorXd a(4);
          a << s.n, -s.radial;  // a smaller wheel cuts less far out
          return a;
        },
        4, Eigen::VectorXd::Zero(4), gates, recipe_tools.size(), settings.min_points);
    // observed when it lies in the span the fit solved
    if (tf.used < settings.min_points || tf.solved(3, 3) < kObservedShare) continue;
    wear_of[t] = tf.x(3);
    out.tools[recipe_tools[t].name] =
        ToolWearMeasured{tf.x(3), std::sqrt(std::max(0.0, tf.cov(3, 3))), tf.tool_points[t]};
  }
  // The whole cut's offset: b on every sample, each as if its wheel were as commanded. A stub's
  // edge whose wheel's radius is not measured is left out: it stands that radius inside the
  // commanded tool, and where the edges cover part of the ring only, the offset would take it.
  std::erase_if(samples, [&](const Sample& s) { return s.edge && !wear_of[s.tool]; });
  for (auto& s : samples) s.sd += s.radial * wear_of[s.tool].value_or(0.0);
  const RobustFit fit = robust_fit(
      samples, [](const Sample& s) { return Eigen::VectorXd(s.n); }, 3, Eigen::VectorXd::Zero(3), gates,
      recipe_tools.size(), settings.min_points);
  // the offset's observed directions: those of b-space the solved span holds whole
  const Eigen::Matrix3d P = observed_part(fit.solved);
  if (fit.used < settings.min_points || P.trace() < 0.5)
    return Error{"compensation.no_cut", "no cut to measure: " + std::to_string(fit.used) +
                                            " re-scanned points lie on the commanded tool surface (at least " +
                                            std::to_string(settings.min_points) + " along one direction)"};
  const Vec3 b = fit.x;
  out.offset_mm = P * b;
  out.observed = P;
  out.std_mm = (P * Eigen::Matrix3d(fit.cov) * P).diagonal().cwiseMax(0.0).cwiseSqrt();
  out.points = fit.used;
  out.rms_mm = fit.sigma;
  // Each region's own offset: b alone on its samples (corrected for the wheels' measured radii,
  // as above), started from the whole cut's offset.
  for (std::size_t r = 0; r < after.regions.size(); ++r) {
    std::vector<Sample> own;
    for (const auto& s : samples)
      if (s.region == r) own.push_back(s);
    if (own.size() < settings.min_points) continue;
    const RobustFit rf = robust_fit(
        own, [](const Sample& s) { return Eigen::VectorXd(s.n); }, 3, Eigen::VectorXd(b),
        {0.5 * settings.band_mm, 0.3, 0.2, 0.15, 0.15}, recipe_tools.size(), settings.min_points);
    if (rf.used < settings.min_points) continue;
    const Eigen::Matrix3d Pr = observed_part(rf.solved);
    if (Pr.trace() < 0.5) continue;
    RegionCutOffset ro;
    if (const auto* region = loaded.region(after.regions[r].name); region != nullptr) ro.tool = region->tool;
    ro.offset_mm = Pr * Vec3(rf.x);
    ro.observed = Pr;
    ro.std_mm = (Pr * Eigen::Matrix3d(rf.cov) * Pr).diagonal().cwiseMax(0.0).cwiseSqrt();
    ro.points = rf.used;
    ro.rms_mm = rf.sigma;
    out.regions[after.regions[r].name] = ro;
  }
  return out;
}

namespace {


nlohmann::ordered_json matrix_to_json(const Eigen::Matrix3d& M) {
  nlohmann::ordered_json rows = nlohmann::ordered_json::array();
  for (int r = 0; r < 3; ++r) rows.push_back({M(r, 0), M(r, 1), M(r, 2)});
  return rows;
}

/// A finite [x, y, z] (`what` names it in the error).
Vec3 vec3_from_json(const nlohmann::json& v, const std::string& what) {
  const Vec3 out(v.at(0).get<double>(), v.at(1).get<double>(), v.at(2).get<double>());
  if (!out.allFinite()) throw std::invalid_argument(what + " is not finite");
  return out;
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
  std::map<std::string, Vec3> region_before;  // each measured region's, as it was commanded
  for (const auto& [name, m] : measured.regions) region_before[name] = region_bias_mm(name);
  // the measurement is the cell's whole offset (the re-scan against the commanded path, which
  // already had the estimate taken off): the estimate moves towards it along what it observed
  const Vec3 innovation = measured.observed * (measured.offset_mm - bias_mm);
  bias_mm += settings.gain * innovation;
  scatter_mm2 = (1.0 - settings.gain) * scatter_mm2 + settings.gain * innovation * innovation.transpose();
  learned = projector_onto(learned + measured.observed, 0.5);  // half a projector's 1
  if (const double n = bias_mm.norm(); n > settings.max_offset_mm && n > 0.0) bias_mm *= settings.max_offset_mm / n;
  ++updates;
  for (const auto& [name, m] : measured.regions) {
    const Vec3 from = region_before.at(name);
    auto& r = regions[name];
    Vec3 own = from + settings.gain * (m.observed * (m.offset_mm - from));
    if (const double n = own.norm(); n > settings.max_offset_mm && n > 0.0) own *= settings.max_offset_mm / n;
    r.learned = projector_onto(r.learned + m.observed, 0.5);
    r.bias_mm = r.learned * own;
    r.tool = m.tool;
    ++r.updates;
  }
  return bias_mm - before;
}

Vec3 CellBias::region_bias_mm(const std::string& region) const {
  const auto it = regions.find(region);
  if (it == regions.end()) return bias_mm;
  return it->second.learned * it->second.bias_mm + (Eigen::Matrix3d::Identity() - it->second.learned) * bias_mm;
}

std::map<std::string, RegionPlacement> CellBias::region_placement(const Eigen::Matrix3d& bound_mm2) const {
  std::map<std::string, RegionPlacement> out;
  for (const auto& [name, r] : regions) out[name] = RegionPlacement{region_bias_mm(name), bound_mm2};
  return out;
}

std::map<std::string, double> removed_cm3(const LoadedRecipe& loaded, const ProcessOutput& processed) {
  std::map<std::string, double> out;
  for (const auto& plan : processed.plans) {
    if (plan.points.empty()) continue;
    const config::Region* r = loaded.region(plan.region);
    const auto m = std::find_if(processed.regions.begin(), processed.regions.end(),
                                [&](const RegionMetrics& x) { return x.name == plan.region; });
    if (r == nullptr || m == processed.regions.end()) continue;
    out[r->tool] += m->excess_volume_mm3 / 1000.0;
  }
  return out;
}

std::map<std::string, double> measure_removed_cm3(const LoadedRecipe& loaded, const vision::Inspection& before,
                                                  const VerificationResult& after, const CutOffsetSettings& settings) {
  std::map<std::string, double> out;
  const double area = settings.column_mm * settings.column_mm;
  for (const auto& r : after.regions) {
    const config::Region* region = loaded.region(r.name);
    if (region == nullptr) continue;
    // the first scan within the same ROI: a feature above the ROI's box is not iron removed
    const HeightColumns first_scan(before, settings.column_mm, region);
    if (first_scan.empty()) continue;
    // the re-scan's surface over each column: its highest point there
    HeightColumns rescan(nullptr, settings.column_mm);
    const Eigen::Isometry3d T = r.T_base_region;
    for (const auto& p : r.roi_points_part) rescan.add(T * p.cast<double>());
    // against the re-scan's highest point over the column and its neighbours: beside a wall a
    // column may hold the wall's top in one scan and not in the other, which is no iron removed
    double mm3 = 0.0;
    rescan.for_each([&](const Vec3& top) {
      const auto near = rescan.top_near(top);
      const auto removed = first_scan.removed_above(Vec3(top.x(), top.y(), near.value_or(top.z())));
      if (removed && *removed >= settings.removed_min_mm) mm3 += *removed * area;
    });
    // at most the excess the first inspection found along the template's normals: a fin that
    // stands out from a wall overhangs air, which a column seen from above counts as iron
    const auto first = std::find_if(before.regions.begin(), before.regions.end(),
                                    [&](const vision::RegionResult& x) { return x.name == r.name; });
    if (first != before.regions.end()) mm3 = std::min(mm3, first->excess.volume_mm3);
    out[region->tool] += mm3 / 1000.0;
  }
  return out;
}

bool ToolWear::rate_measured() const { return measurements >= kMinWearMeasurements && sum_vv > 0.0; }

double ToolWear::rate_mm_per_cm3(const config::Tool& tool) const {
  return rate_measured() ? std::max(0.0, sum_wv / sum_vv) : tool.wear_mm_per_cm3;
}

double ToolWear::rate_tolerance(const config::Tool& tool) const {
  const double stated = std::clamp(tool.wear_tolerance_pct / 100.0, 0.0, 1.0);
  const double rate = rate_mm_per_cm3(tool);
  if (!rate_measured() || rate <= 0.0) return stated;
  // the fit w = r V through the origin: its residuals' variance over the removal's spread
  const double r = sum_wv / sum_vv;
  const double residual2 = std::max(0.0, sum_ww - 2.0 * r * sum_wv + r * r * sum_vv);
  const double sigma_r = std::sqrt(residual2 / static_cast<double>(measurements - 1) / sum_vv);
  return std::min(1.0, 2.0 * sigma_r / rate);
}

WearRange ToolWear::wear(const config::Tool& tool, double more_cm3) const {
  const double v = removed_cm3 + std::max(0.0, more_cm3);
  const double r = rate_mm_per_cm3(tool), tol = rate_tolerance(tool);
  // The least is what the wheel surely lost, and only a measured rate says so: a stated one
  // may not hold for this wheel at all (one that wears less than its maker says, planned
  // smaller than it is, is moved into the wall: test Trial.TheCellLearnsAPathBias*).
  return WearRange{rate_measured() ? std::max(0.0, (1.0 - tol) * r * v) : 0.0, r * v, (1.0 + tol) * r * v};
}

std::map<std::string, WearRange> CellBias::tool_wear(const config::PartRecipe& recipe) const {
  std::map<std::string, WearRange> out;
  for (const auto& t : recipe.tools) {
    const auto it = tools.find(t.name);
    out[t.name] = it == tools.end() ? WearRange{} : it->second.wear(t);
  }
  return out;
}

ToolWearMm CellBias::tool_wear_mm(const config::PartRecipe& recipe) const {
  ToolWearMm out;
  for (const auto& [name, w] : tool_wear(recipe)) out[name] = w.least_mm;
  return out;
}

ToolWearMm CellBias::tool_wear_most_mm(const config::PartRecipe& recipe) const {
  ToolWearMm out;
  for (const auto& [name, w] : tool_wear(recipe)) out[name] = w.most_mm;
  return out;
}

void CellBias::add_removed(const std::map<std::string, double>& removed_cm3) {
  for (const auto& [name, cm3] : removed_cm3) tools[name].removed_cm3 += std::max(0.0, cm3);
}

void CellBias::add_wear_measurements(const CutOffset& measured, const ToolWearMm& commanded) {
  for (const auto& [name, m] : measured.tools) {
    auto& tw = tools[name];
    if (tw.removed_cm3 <= 0.0) continue;
    const auto c = commanded.find(name);
    const double wear = (c == commanded.end() ? 0.0 : c->second) + m.wear_mm;
    tw.sum_wv += wear * tw.removed_cm3;
    tw.sum_vv += tw.removed_cm3 * tw.removed_cm3;
    tw.sum_ww += wear * wear;
    ++tw.measurements;
  }
}

std::optional<double> wear_slack_mm(const config::PartRecipe& recipe, const config::Tool& tool) {
  std::optional<double> out;
  for (const auto& r : recipe.regions) {
    if (r.tool != tool.name || tool.shape == config::ToolShape::cone) continue;
    // a cylinder's flat end grinds a riser's face: its radius leaves nothing there
    if (r.type == config::RegionType::riser && tool.shape == config::ToolShape::cylinder) continue;
    const double slack = config::VerificationSettings::kShareLevelMm - r.allowance_mm;
    if (!out || slack < *out) out = slack;
  }
  return out;
}

std::vector<WornWheel> CellBias::worn_out(const config::PartRecipe& recipe,
                                          const std::map<std::string, double>& next_cm3) const {
  std::vector<WornWheel> out;
  for (const auto& t : recipe.tools) {
    const auto it = tools.find(t.name);
    if (it == tools.end()) continue;
    const auto nx = next_cm3.find(t.name);
    const auto w = it->second.wear(t, nx == next_cm3.end() ? 0.0 : nx->second);
    char why[200];
    if (t.max_wear_mm > 0.0 && w.most_mm > t.max_wear_mm) {
      std::snprintf(why, sizeof why, "worn %.2f mm (up to %.2f; its life: %.2f mm)", w.expected_mm, w.most_mm,
                    t.max_wear_mm);
      out.push_back({t.name, why});
    } else if (const auto slack = wear_slack_mm(recipe, t); slack && w.most_mm - w.least_mm > *slack) {
      std::snprintf(why, sizeof why,
                    "worn %.2f-%.2f mm: known less well than its regions' finish needs (%.2f mm; until its cut "
                    "shows its radius, only a new wheel's is known)",
                    w.least_mm, w.most_mm, *slack);
      out.push_back({t.name, why});
    }
  }
  return out;
}

void CellBias::change_tool(const std::string& name) {
  auto& tw = tools[name];
  tw.removed_cm3 = 0.0;
  ++tw.changes;
  std::erase_if(regions, [&](const auto& r) { return r.second.tool == name; });
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

double largest_tool_tilt_deg(const config::PartRecipe& recipe) {
  double tilt = 0.0;
  for (const auto& r : recipe.regions) {
    const bool flash = r.type == config::RegionType::ring_flash || r.type == config::RegionType::circle_flash;
    // a chamfering tool's axis leans chamfer_deg from the parting plane (planning's chamfer pose)
    if (flash && r.contact == config::FlashContact::chamfer) tilt = std::max(tilt, 90.0 - r.chamfer_deg);
  }
  return std::clamp(tilt, 0.0, 90.0);
}

bool states_accuracy(const config::SafetySection& safety) {
  return safety.calibration_accuracy_mm > 0.0 || safety.robot_accuracy_mm > 0.0 || safety.tcp_accuracy_mm > 0.0 ||
         safety.robot_repeatability_mm > 0.0;
}

PlacementUncertainty placement_uncertainty(const config::SafetySection& safety, const config::PartRecipe& recipe,
                                           const CellBias& bias, const config::CompensationSection& settings) {
  PlacementUncertainty u;
  if (!states_accuracy(safety)) return u;  // nothing stated: the regions' allowances alone
  // The systematic errors are independent: their root sum of squares, the TCP's along the tools'
  // axes only: all of it vertically (a tool straight down, or nearly), sideways as much as the
  // recipe's most leaning tool turns it. The repeatability adds
  // to it: a wheel keeps the deepest of the many noisy poses that sweep over a point, so the
  // path's noise deepens the whole cut by most of its 3 sigma, one-sided, rather than scattering it.
  const double tilt = deg_to_rad(largest_tool_tilt_deg(recipe));
  const double any2 = safety.calibration_accuracy_mm * safety.calibration_accuracy_mm +
                      safety.robot_accuracy_mm * safety.robot_accuracy_mm;
  const double tcp2 = safety.tcp_accuracy_mm * safety.tcp_accuracy_mm;
  const double repeatability = safety.robot_repeatability_mm;
  const double sideways = std::sqrt(any2 + tcp2 * std::sin(tilt) * std::sin(tilt)) + repeatability;
  const double vertically = std::sqrt(any2 + tcp2) + repeatability;
  const Eigen::Matrix3d I = Eigen::Matrix3d::Identity();
  const Eigen::Matrix3d Z = Vec3::UnitZ() * Vec3::UnitZ().transpose();
  const Eigen::Matrix3d unlearned = sideways * sideways * (I - Z) + vertically * vertically * Z;
  const Eigen::Matrix3d& P = bias.learned;
  const Eigen::Matrix3d Q = I - P;
  const double g = std::clamp(settings.gain, 1e-6, 1.0);
  const double left = std::pow(1.0 - g, static_cast<double>(bias.updates));  // of the stated systematic error
  // Along a learned direction the estimate holds all but `left` of the sum, the envelope's depth
  // included; the noise itself stays (the repeatability, as a scatter about that depth), and so
  // does the estimate's own spread.
  u.bound_mm2 = Q * unlearned * Q + P * (left * left * unlearned + repeatability * repeatability * I) * P +
                g / (2.0 - g) * (P * bias.scatter_mm2 * P);
  return u;
}

RegrindCompensation regrind_compensation(const config::SafetySection& safety, const config::PartRecipe& recipe,
                                         const CellBias& cell, const CutOffset& measured,
                                         const config::CompensationSection& settings) {
  RegrindCompensation out;
  const Eigen::Matrix3d I = Eigen::Matrix3d::Identity();
  // along what `offset` observed: it, bounded by the repeatability and its own scatter; along
  // the rest as `bias` and `bound` have it
  const auto take = [&](const Vec3& bias, const Eigen::Matrix3d& bound, const Eigen::Matrix3d& P, const Vec3& offset,
                        const Vec3& std_mm) {
    const Eigen::Matrix3d Q = I - P;
    RegionPlacement p;
    p.bias_mm = P * offset + Q * bias;
    if (bound.isZero()) return p;  // nothing stated: the regions' allowances alone
    const Eigen::Matrix3d scatter = std_mm.cwiseAbs2().asDiagonal();
    const double repeatability2 = safety.robot_repeatability_mm * safety.robot_repeatability_mm;
    p.bound_mm2 = Q * bound * Q + P * (repeatability2 * I + scatter) * P;
    return p;
  };
  const Eigen::Matrix3d usual = placement_uncertainty(safety, recipe, cell, settings).bound_mm2;
  const auto whole = take(cell.bias_mm, usual, measured.observed, measured.offset_mm, measured.std_mm);
  out.bias_mm = whole.bias_mm;
  out.placement.bound_mm2 = whole.bound_mm2;
  for (const auto& [name, r] : measured.regions)
    out.regions[name] = take(whole.bias_mm, whole.bound_mm2, r.observed, r.offset_mm, r.std_mm);
  // a region not measured this time keeps what the cell learned of it
  for (const auto& [name, p] : cell.region_placement(usual))
    out.regions.emplace(name, p);
  return out;
}

ToolWearMm regrind_tool_wear(const ToolWearMm& cell_least, const CutOffset& measured, const ToolWearMm& commanded) {
  ToolWearMm out = cell_least;
  for (const auto& [name, m] : measured.tools) {
    const auto c = commanded.find(name);
    const double least = (c == commanded.end() ? 0.0 : c->second) + m.wear_mm - 2.0 * m.std_mm;
    out[name] = std::max(out[name], least);
  }
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
    b.bias_mm = vec3_from_json(j.at("bias_mm"), "bias_mm");
    b.updates = j.value("updates", std::size_t{0});
    b.calibration_id = j.value("calibration_id", std::string{});
    b.tools_id = j.value("tools_id", std::string{});
    b.learned = matrix_from_json(j, "learned");
    b.scatter_mm2 = matrix_from_json(j, "scatter_mm2");
    if (j.contains("tools"))
      for (const auto& [name, t] : j.at("tools").items()) {
        ToolWear w;
        w.removed_cm3 = t.value("removed_cm3", 0.0);
        w.sum_wv = t.value("sum_wear_x_removed", 0.0);
        w.sum_vv = t.value("sum_removed_squared", 0.0);
        w.sum_ww = t.value("sum_wear_squared", 0.0);
        w.measurements = t.value("measurements", std::size_t{0});
        w.changes = t.value("changes", std::size_t{0});
        if (!std::isfinite(w.removed_cm3) || !std::isfinite(w.sum_wv) || !std::isfinite(w.sum_vv))
          throw std::invalid_argument("tools." + name + " is not finite");
        b.tools[name] = w;
      }
    if (j.contains("regions"))
      for (const auto& [name, r] : j.at("regions").items()) {
        RegionBias rb;
        rb.bias_mm = vec3_from_json(r.at("bias_mm"), "regions." + name + ".bias_mm");
        rb.learned = matrix_from_json(r, "learned");
        rb.tool = r.value("tool", std::string{});
        rb.updates = r.value("updates", std::size_t{0});
        b.regions[name] = rb;
      }
    return b;
  } catch (const std::exception& e) {
    return Error{"compensation.state", file.string() + ": not a compensation state file (" + e.what() + ")"};
  }
}

Status save_cell_bias(const std::filesystem::path& file, const CellBias& bias) {
  nlohmann::ordered_json tools = nlohmann::ordered_json::object();
  for (const auto& [name, w] : bias.tools)
    tools[name] = {{"removed_cm3", w.removed_cm3},
                   {"sum_wear_x_removed", w.sum_wv},
                   {"sum_removed_squared", w.sum_vv},
                   {"sum_wear_squared", w.sum_ww},
                   {"measurements", w.measurements},
                   {"changes", w.changes}};
  nlohmann::ordered_json regions = nlohmann::ordered_json::object();
  for (const auto& [name, r] : bias.regions)
    regions[name] = {{"bias_mm", {r.bias_mm.x(), r.bias_mm.y(), r.bias_mm.z()}},
                     {"learned", matrix_to_json(r.learned)},
                     {"tool", r.tool},
                     {"updates", r.updates}};
  const nlohmann::ordered_json j = {{"bias_mm", {bias.bias_mm.x(), bias.bias_mm.y(), bias.bias_mm.z()}},
                                    {"updates", bias.updates},
                                    {"calibration_id", bias.calibration_id},
                                    {"tools_id", bias.tools_id},
                                    {"learned", matrix_to_json(bias.learned)},
                                    {"scatter_mm2", matrix_to_json(bias.scatter_mm2)},
                                    {"tools", tools},
                                    {"regions", regions},
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
