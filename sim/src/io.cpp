// Files the simulator writes and reads: PLY, PCD, range images, ground truth; the check of a
// trajectory before the simulated robot runs it.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "casting_model.hpp"
#include "fettle/core/atomic_file.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/ply.hpp"

namespace fettle::sim {
namespace {

using nlohmann::ordered_json;

template <class T>
void append(std::string& out, const T& v) {
  char buf[sizeof(T)];
  std::memcpy(buf, &v, sizeof(T));
  out.append(buf, sizeof(T));
}

std::string num(double v) {
  std::ostringstream s;
  s.precision(17);
  s << v;
  return s.str();
}

ordered_json pose_json(const Transform& T) {
  const Pose p = Pose::from_transform(T);
  ordered_json j;
  j["position_mm"] = {p.position_mm.x(), p.position_mm.y(), p.position_mm.z()};
  j["quaternion_wxyz"] = {p.orientation.w(), p.orientation.x(), p.orientation.y(), p.orientation.z()};
  ordered_json m = ordered_json::array();
  for (int r = 0; r < 4; ++r) m.push_back({T.matrix()(r, 0), T.matrix()(r, 1), T.matrix()(r, 2), T.matrix()(r, 3)});
  j["matrix"] = m;
  return j;
}

}  // namespace

Status write_valid_points_ply(const std::filesystem::path& path, const OrganizedCloud& cloud, const Transform& T) {
  std::vector<Eigen::Vector3f> points;
  points.reserve(cloud.count_valid());
  const Eigen::Isometry3f Tf = T.cast<float>();
  for (const auto& p : cloud.points)
    if (p.allFinite()) points.push_back(Tf * p);
  return fettle::write_ply(path, points, {}, {}, "fettle-sim, millimetres");
}

Status write_pcd(const std::filesystem::path& path, const OrganizedCloud& cloud) {
  std::string out = "# .PCD v0.7 - fettle-sim, millimetres, camera frame\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
                    "TYPE F F F\nCOUNT 1 1 1\nWIDTH " +
                    std::to_string(cloud.width) + "\nHEIGHT " + std::to_string(cloud.height) +
                    "\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS " + std::to_string(cloud.points.size()) + "\nDATA binary\n";
  out.reserve(out.size() + cloud.points.size() * 12);
  for (const auto& p : cloud.points) append(out, p.x()), append(out, p.y()), append(out, p.z());
  return write_file_atomic(path, out);
}

Status write_range_images(const std::filesystem::path& dir, const std::string& stem, const Capture& c) {
  const auto& r = c.range16;
  std::string raw;
  raw.reserve(r.data.size() * 2);
  for (auto v : r.data) append(raw, v);
  if (auto s = write_file_atomic(dir / (stem + ".c16"), raw); !s) return s;
  const auto& K = c.truth.intrinsics;
  ordered_json j;
  j["pixel_format"] = "Coord3D_C16";
  j["width"] = r.width;
  j["height"] = r.height;
  j["byte_order"] = "little_endian";
  j["coordinate"] = "Z of the camera frame (mm) = value * scale_mm + offset_mm";
  j["scale_mm"] = r.scale_mm;
  j["offset_mm"] = r.offset_mm;
  j["invalid_value"] = r.invalid_value;
  j["intrinsics"] = {{"fx", K.fx}, {"fy", K.fy}, {"cx", K.cx}, {"cy", K.cy},
                     {"distortion_k1_k2_p1_p2_k3", {K.k1, K.k2, K.p1, K.p2, K.k3}}};
  if (auto s = write_file_atomic(dir / (stem + ".c16.json"), j.dump(2) + "\n"); !s) return s;
  std::string rawf;
  rawf.reserve(c.range.data.size() * 4);
  for (auto v : c.range.data) append(rawf, v);
  if (auto s = write_file_atomic(dir / (stem + ".f32"), rawf); !s) return s;
  ordered_json jf;
  jf["pixel_format"] = "Coord3D_C32f";
  jf["width"] = c.range.width;
  jf["height"] = c.range.height;
  jf["byte_order"] = "little_endian";
  jf["coordinate"] = "Z of the camera frame (mm), NaN = invalid";
  jf["intrinsics"] = j["intrinsics"];
  return write_file_atomic(dir / (stem + ".f32.json"), jf.dump(2) + "\n");
}

std::string ground_truth_json(const GroundTruth& t) {
  ordered_json j;
  j["part_id"] = t.part_id;
  j["seed"] = t.seed;
  j["view"] = t.view;
  j["slide_position_mm"] = t.slide_position_mm;
  j["frames"] = "T_a_b maps points of frame b into frame a; base: table top z = 0, z up; camera: OpenCV";
  j["T_base_camera"] = pose_json(t.T_base_camera);
  j["T_base_part"] = pose_json(t.T_base_part);
  const auto& K = t.intrinsics;
  j["intrinsics"] = {{"width", K.width}, {"height", K.height}, {"fx", K.fx}, {"fy", K.fy}, {"cx", K.cx}, {"cy", K.cy},
                     {"distortion_k1_k2_p1_p2_k3", {K.k1, K.k2, K.p1, K.p2, K.k3}}};
  ordered_json regions = ordered_json::array();
  for (const auto& r : t.regions) {
    ordered_json jr;
    jr["name"] = r.name;
    jr["type"] = config::to_string(r.type);
    jr["volume_mm3"] = r.volume_mm3;
    jr["max_height_mm"] = r.max_height_mm;
    jr["height_measured"] = r.radial ? "radially from the axis (part frame)" : "along part +z";
    if (r.radial) jr["axis_center_mm"] = {r.axis_center_mm.x(), r.axis_center_mm.y()};
    regions.push_back(jr);
  }
  j["regions"] = regions;
  ordered_json gouges = ordered_json::array();
  for (const auto& g : t.gouges)
    gouges.push_back({{"position_mm", {g.position_mm.x(), g.position_mm.y(), g.position_mm.z()}},
                      {"depth_mm", g.depth_mm},
                      {"pose_index", g.pose_index}});
  j["gouges"] = gouges;
  return j.dump(2) + "\n";
}

Status write_height_png(const std::filesystem::path& path, const Capture& c) {
  const auto& cloud = c.cloud;
  const Eigen::Isometry3f T = c.truth.T_base_camera.cast<float>();
  std::vector<float> z(cloud.points.size(), std::numeric_limits<float>::quiet_NaN());
  float lo = 1e9f, hi = -1e9f;
  for (std::size_t k = 0; k < z.size(); ++k) {
    if (!cloud.points[k].allFinite()) continue;
    z[k] = (T * cloud.points[k]).z();
    lo = std::min(lo, z[k]), hi = std::max(hi, z[k]);
  }
  cv::Mat gray(static_cast<int>(cloud.height), static_cast<int>(cloud.width), CV_8UC1, cv::Scalar(0));
  cv::Mat mask(gray.size(), CV_8UC1, cv::Scalar(0));
  for (std::size_t k = 0; k < z.size(); ++k) {
    if (std::isnan(z[k])) continue;
    const int v = static_cast<int>(k / cloud.width), u = static_cast<int>(k % cloud.width);
    gray.at<std::uint8_t>(v, u) = static_cast<std::uint8_t>(std::clamp(255.0f * (z[k] - lo) / std::max(1e-3f, hi - lo), 0.0f, 255.0f));
    mask.at<std::uint8_t>(v, u) = 255;
  }
  cv::Mat color;
  cv::applyColorMap(gray, color, cv::COLORMAP_TURBO);
  color.setTo(cv::Scalar(0, 0, 0), mask == 0);
  std::vector<std::uint8_t> buf;
  if (!cv::imencode(".png", color, buf)) return Error{"sim.png", path.string() + ": PNG encoding failed"};
  return write_file_atomic(path, std::string(buf.begin(), buf.end()));
}

Status write_capture(const std::filesystem::path& dir, const std::string& stem, const Capture& c) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return Error{"sim.out_dir", dir.string() + ": cannot create the directory: " + ec.message()};
  if (auto s = write_valid_points_ply(dir / (stem + ".ply"), c.cloud); !s) return s;
  if (auto s = write_pcd(dir / (stem + ".pcd"), c.cloud); !s) return s;
  if (auto s = write_range_images(dir, stem, c); !s) return s;
  return write_file_atomic(dir / (stem + ".truth.json"), ground_truth_json(c.truth));
}

// ---------------------------------------------------------------------------------------------
// Trajectories (the file format is core's: fettle/core/trajectory_io.hpp)

Status validate_trajectory(const Trajectory& t, const CellLimits& lim) {
  if (t.points.empty()) return Error{"sim.trajectory_empty", "the trajectory has no points"};
  for (std::size_t i = 0; i < t.points.size(); ++i) {
    const auto& p = t.points[i];
    const auto& x = p.T_base_tool.position_mm;
    const auto& q = p.T_base_tool.orientation;
    const std::string at = "trajectory point " + std::to_string(i) + ": ";
    if (!x.allFinite() || !q.coeffs().allFinite() || !std::isfinite(p.speed_mm_s) || !std::isfinite(p.spindle_rpm))
      return Error{"sim.trajectory_nan", at + "a value is NaN or infinite; nothing was executed"};
    if (std::abs(q.norm() - 1.0) > 1e-3)
      return Error{"sim.trajectory_quaternion", at + "quaternion norm " + num(q.norm()) + " is not 1; nothing was executed"};
    for (int a = 0; a < 3; ++a)
      if (x[a] < lim.workspace_min_mm[a] || x[a] > lim.workspace_max_mm[a])
        return Error{"sim.trajectory_outside",
                     at + "position (" + num(x.x()) + ", " + num(x.y()) + ", " + num(x.z()) +
                         ") mm is outside the cell workspace (" + num(lim.workspace_min_mm.x()) + ".." +
                         num(lim.workspace_max_mm.x()) + ", " + num(lim.workspace_min_mm.y()) + ".." +
                         num(lim.workspace_max_mm.y()) + ", " + num(lim.workspace_min_mm.z()) + ".." +
                         num(lim.workspace_max_mm.z()) + "); nothing was executed"};
    if (p.speed_mm_s < 0 || p.speed_mm_s > lim.max_speed_mm_s)
      return Error{"sim.trajectory_speed", at + "speed " + num(p.speed_mm_s) + " mm/s is outside 0.." +
                                               num(lim.max_speed_mm_s) + "; nothing was executed"};
    if (p.spindle_rpm < 0 || p.spindle_rpm > lim.max_spindle_rpm)
      return Error{"sim.trajectory_spindle", at + "spindle " + num(p.spindle_rpm) + " rpm is outside 0.." +
                                                 num(lim.max_spindle_rpm) + "; nothing was executed"};
  }
  return {};
}

}  // namespace fettle::sim
