// fettle calibrate intrinsics | hand-eye | show  (docs/calibration.md)
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include <pcl/io/pcd_io.h>
#include <pcl/point_types.h>

#include "fettle/config/calibration.hpp"
#include "fettle/core/cli.hpp"
#include "fettle/core/error.hpp"
#include "fettle/vision/calibration/board.hpp"
#include "fettle/vision/calibration/hand_eye.hpp"

namespace {

namespace fs = std::filesystem;
namespace cal = fettle::vision::calibration;
using fettle::Transform;
using fettle::UserError;
using fettle::Vec3;

std::string fmt(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  return buf;
}

std::string default_id(const std::string& date) {
  std::string id = "cal-";
  for (const char c : date)
    if (c != '-' && c != ':') id += c;
  return id;
}

void print_transform(const char* name, const Transform& T) {
  const fettle::Pose p = fettle::Pose::from_transform(T);
  const Eigen::AngleAxisd aa(T.rotation());
  std::cout << name << ": position [" << fmt(p.position_mm.x(), 3) << ", " << fmt(p.position_mm.y(), 3) << ", "
            << fmt(p.position_mm.z(), 3) << "] mm, rotation " << fmt(fettle::rad_to_deg(aa.angle()), 4)
            << " deg about [" << fmt(aa.axis().x(), 4) << ", " << fmt(aa.axis().y(), 4) << ", "
            << fmt(aa.axis().z(), 4) << "]\n";
}

// ---- input files ------------------------------------------------------------------------

struct PoseRow {
  std::string name;
  Vec3 position_mm;
  std::optional<fettle::Quat> orientation;
};

/// CSV: name,x_mm,y_mm,z_mm[,qw,qx,qy,qz]; '#' comments, blank lines and a header line
/// starting with "name" are ignored.
std::vector<PoseRow> read_pose_csv(const fs::path& file, bool need_orientation) {
  std::ifstream in(file);
  if (!in) throw UserError(file.string() + ": cannot be opened");
  std::vector<PoseRow> rows;
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    const auto first = line.find_first_not_of(" \t\r");
    if (first == std::string::npos || line[first] == '#' || line.compare(first, 4, "name") == 0) continue;
    std::vector<std::string> f;
    std::stringstream ss(line);
    std::string cell;
    while (std::getline(ss, cell, ',')) f.push_back(cell);
    const std::string where = file.string() + ":" + std::to_string(n) + ": ";
    if (f.size() != 4 && f.size() != 8)
      throw UserError(where + "expected name,x_mm,y_mm,z_mm" + (need_orientation ? ",qw,qx,qy,qz" : "[,qw,qx,qy,qz]") +
                      " (" + std::to_string(f.size()) + " fields found)");
    if (need_orientation && f.size() != 8) throw UserError(where + "an orientation qw,qx,qy,qz is needed");
    std::vector<double> v;
    for (std::size_t i = 1; i < f.size(); ++i) {
      try {
        std::size_t used = 0;
        v.push_back(std::stod(f[i], &used));
        if (f[i].find_first_not_of(" \t\r", used) != std::string::npos) throw std::invalid_argument("trailing");
      } catch (const std::exception&) {
        throw UserError(where + "field " + std::to_string(i + 1) + " \"" + f[i] + "\" is not a number");
      }
    }
    PoseRow r;
    r.name = f[0];
    r.name.erase(0, r.name.find_first_not_of(" \t"));
    r.name.erase(r.name.find_last_not_of(" \t\r") + 1);
    r.position_mm = Vec3(v[0], v[1], v[2]);
    if (v.size() == 7) {
      const fettle::Quat q(v[3], v[4], v[5], v[6]);
      if (std::abs(q.norm() - 1.0) > 1e-3)
        throw UserError(where + "quaternion qw,qx,qy,qz has norm " + fmt(q.norm(), 4) + ", not 1");
      r.orientation = q.normalized();
    }
    rows.push_back(r);
  }
  if (rows.empty()) throw UserError(file.string() + ": no poses in the file");
  return rows;
}

Transform to_transform(const PoseRow& r) {
  return fettle::Pose{r.position_mm, r.orientation.value_or(fettle::Quat::Identity())}.to_transform();
}

std::vector<Vec3> read_cloud(const fs::path& file) {
  std::vector<Vec3> pts;
  if (file.extension() == ".pcd") {
    pcl::PointCloud<pcl::PointXYZ> cloud;
    if (pcl::io::loadPCDFile(file.string(), cloud) != 0) throw UserError(file.string() + ": cannot read the PCD file");
    for (const auto& p : cloud.points)
      if (std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z)) pts.emplace_back(p.x, p.y, p.z);
    return pts;
  }
  std::ifstream in(file);
  if (!in) throw UserError(file.string() + ": cannot be opened");
  std::string line;
  while (std::getline(in, line)) {
    for (char& c : line)
      if (c == ',') c = ' ';
    std::stringstream ss(line);
    double x = 0, y = 0, z = 0;
    if (ss >> x >> y >> z && std::isfinite(x) && std::isfinite(y) && std::isfinite(z)) pts.emplace_back(x, y, z);
  }
  return pts;
}

fettle::config::CalibrationFile new_file(const std::string& id, const std::string& note) {
  fettle::config::CalibrationFile c;
  c.date = fettle::config::utc_now_iso8601();
  c.id = id.empty() ? default_id(c.date) : id;
  c.note = note;
  return c;
}

// ---- intrinsics -------------------------------------------------------------------------

struct IntrinsicsArgs {
  fs::path images, out;
  std::string board, id, note;
  double square_mm = 0.0;
  std::size_t min_views = 5;
  double max_edge_width_px = 4.0;
  bool k3 = false;
};

int run_intrinsics(const IntrinsicsArgs& a) {
  const auto board = cal::parse_board(a.board, a.square_mm);
  if (!fs::is_directory(a.images)) throw UserError(a.images.string() + ": not a directory of images");
  const auto files = cal::list_images(a.images);
  if (files.empty()) throw UserError(a.images.string() + ": no images (png, jpg, bmp, tif, pgm) in it");
  std::vector<cal::GrayImage> images;
  for (std::size_t i = 0; i < files.size(); ++i) {
    std::cerr << "reading " << i + 1 << "/" << files.size() << ": " << files[i].filename().string() << "\n";
    auto img = cal::load_gray_image(files[i]);
    if (!img) throw UserError(img.error().message);
    images.push_back(std::move(*img));
  }
  cal::IntrinsicsOptions o;
  o.min_views = a.min_views;
  o.detect.max_edge_width_px = a.max_edge_width_px;
  o.fix_k3 = !a.k3;
  auto r = cal::calibrate_intrinsics(images, board, o);
  if (!r) throw UserError(r.error().message);
  for (const auto& v : r->views)
    std::cout << (v.used ? "  used     " : "  SKIPPED  ") << v.name << "  "
              << (v.used ? "rms " + fmt(v.rms_px, 3) + " px" : v.skip_reason) << "\n";
  const auto& k = r->intrinsics;
  std::cout << "image " << k.width_px << "x" << k.height_px << " px, " << k.views << " views used\n"
            << "fx " << fmt(k.fx_px, 2) << "  fy " << fmt(k.fy_px, 2) << "  cx " << fmt(k.cx_px, 2) << "  cy "
            << fmt(k.cy_px, 2) << " px\n"
            << "distortion";
  for (const double d : k.distortion) std::cout << " " << fmt(d, 6);
  std::cout << "\nreprojection rms " << fmt(k.rms_px, 4) << " px\n";
  auto file = new_file(a.id, a.note);
  file.intrinsics = k;
  fettle::config::write_calibration(a.out, file);
  std::cout << "wrote " << a.out.string() << " (id " << file.id << ")\n";
  return fettle::exit_code::ok;
}

// ---- hand-eye ---------------------------------------------------------------------------

struct HandEyeArgs {
  bool live = false;
  fs::path robot_poses, images, board_poses, clouds, calibration, out;
  std::string board, id, note;
  double square_mm = 0.0;
  double sphere_radius_mm = 0.0;
  std::size_t min_poses = 6;
  double max_edge_width_px = 4.0;
};

void print_residuals(const fettle::config::HandEyeResiduals& r) {
  for (const auto& p : r.per_pose)
    std::cout << (p.outlier ? "  OUTLIER  " : "  ok       ") << p.name << "  " << fmt(p.translation_mm, 3) << " mm"
              << (r.method == "board" ? "  " + fmt(p.rotation_deg, 3) + " deg" : std::string()) << "\n";
  std::cout << r.poses << " poses used; residual rms " << fmt(r.rms_mm, 3) << " mm (max " << fmt(r.max_mm, 3) << ")";
  if (r.method == "board") std::cout << ", " << fmt(r.rms_deg, 3) << " deg (max " << fmt(r.max_deg, 3) << ")";
  std::cout << "\n";
}

int run_hand_eye(const HandEyeArgs& a) {
  if (a.live)
    throw UserError(
        "--live is not available yet: it needs the robot and camera links, which are not built yet. Record the "
        "poses by hand and run `fettle calibrate hand-eye --robot-poses FILE` with --images, --board-poses or "
        "--clouds (docs/calibration.md)");
  if (a.robot_poses.empty()) throw UserError("--robot-poses FILE is required (or --live, once available)");
  if (a.out.empty()) throw UserError("--out FILE is required");
  const int sources = (a.images.empty() ? 0 : 1) + (a.board_poses.empty() ? 0 : 1) + (a.clouds.empty() ? 0 : 1);
  if (sources != 1) throw UserError("give exactly one of --images DIR, --board-poses FILE or --clouds DIR");

  std::optional<fettle::config::CalibrationFile> base;
  if (!a.calibration.empty()) base = fettle::config::load_calibration(a.calibration);
  auto file = new_file(a.id, a.note);
  if (base) {
    file.intrinsics = base->intrinsics;
    file.T_camera_projector = base->T_camera_projector;
    file.stereo_rms_px = base->stereo_rms_px;
  }
  cal::HandEyeOptions o;
  o.min_poses = a.min_poses;

  if (!a.clouds.empty()) {
    const auto rows = read_pose_csv(a.robot_poses, false);
    cal::SphereFitOptions fo;
    fo.radius_mm = a.sphere_radius_mm;
    std::vector<cal::SphereSample> samples;
    for (std::size_t i = 0; i < rows.size(); ++i) {
      const fs::path cloud_file = a.clouds / rows[i].name;
      std::cerr << "sphere " << i + 1 << "/" << rows.size() << ": " << cloud_file.string() << "\n";
      if (!fs::is_regular_file(cloud_file))
        throw UserError(a.robot_poses.string() + ": pose \"" + rows[i].name + "\" has no cloud file " +
                        cloud_file.string());
      const auto fit = cal::fit_sphere(read_cloud(cloud_file), fo);
      if (!fit) throw UserError(cloud_file.string() + ": " + fit.error().message);
      std::cerr << "  centre [" << fmt(fit->center_mm.x(), 3) << ", " << fmt(fit->center_mm.y(), 3) << ", "
                << fmt(fit->center_mm.z(), 3) << "] mm, radius " << fmt(fit->radius_mm, 3) << " mm, "
                << fit->inliers << " points, rms " << fmt(fit->rms_mm, 3) << " mm\n";
      samples.push_back(cal::SphereSample{rows[i].name, rows[i].position_mm, fit->center_mm});
    }
    auto r = cal::calibrate_hand_eye_sphere(samples, o);
    if (!r) throw UserError(r.error().message);
    print_residuals(r->residuals);
    file.T_base_camera = r->T_base_camera;
    file.hand_eye = r->residuals;
  } else {
    const auto rows = read_pose_csv(a.robot_poses, true);
    std::vector<cal::HandEyeSample> samples;
    if (!a.board_poses.empty()) {
      std::map<std::string, Transform> seen;
      for (const auto& b : read_pose_csv(a.board_poses, true)) seen[b.name] = to_transform(b);
      for (const auto& r : rows) {
        const auto it = seen.find(r.name);
        if (it == seen.end())
          throw UserError(a.board_poses.string() + ": no board pose named \"" + r.name + "\" (named in " +
                          a.robot_poses.string() + ")");
        samples.push_back(cal::HandEyeSample{r.name, to_transform(r), it->second});
      }
    } else {
      if (!file.intrinsics)
        throw UserError("--images needs the camera intrinsics: give --calibration FILE (from `fettle calibrate "
                        "intrinsics`)");
      const auto board = cal::parse_board(a.board, a.square_mm);
      cal::DetectOptions d;
      d.max_edge_width_px = a.max_edge_width_px;
      for (std::size_t i = 0; i < rows.size(); ++i) {
        const fs::path img_file = a.images / rows[i].name;
        auto img = cal::load_gray_image(img_file);
        if (!img) throw UserError(img.error().message + " (pose \"" + rows[i].name + "\")");
        auto obs = cal::detect_board(*img, board, d);
        if (!obs) {
          std::cout << "  SKIPPED  " << rows[i].name << "  " << obs.error().message << "\n";
          continue;
        }
        auto pose = cal::board_pose(*obs, board, *file.intrinsics);
        if (!pose) {
          std::cout << "  SKIPPED  " << rows[i].name << "  " << pose.error().message << "\n";
          continue;
        }
        std::cerr << "image " << i + 1 << "/" << rows.size() << ": " << rows[i].name << " board at "
                  << fmt(pose->T_camera_board.translation().norm(), 1) << " mm, reprojection rms "
                  << fmt(pose->rms_px, 3) << " px\n";
        samples.push_back(cal::HandEyeSample{rows[i].name, to_transform(rows[i]), pose->T_camera_board});
      }
    }
    auto r = cal::calibrate_hand_eye_board(samples, o);
    if (!r) throw UserError(r.error().message);
    print_residuals(r->residuals);
    file.T_base_camera = r->T_base_camera;
    file.T_flange_board = r->T_flange_board;
    file.hand_eye = r->residuals;
    print_transform("T_flange_board", r->T_flange_board);
  }
  print_transform("T_base_camera", *file.T_base_camera);
  fettle::config::write_calibration(a.out, file);
  std::cout << "wrote " << a.out.string() << " (id " << file.id << ")\n";
  return fettle::exit_code::ok;
}

// ---- show -------------------------------------------------------------------------------

int run_show(const fs::path& path) {
  const auto c = fettle::config::load_calibration(path);
  std::cout << path.string() << ": OK\nid " << c.id << ", date " << c.date << (c.note.empty() ? "" : ", " + c.note)
            << "\n";
  if (c.intrinsics)
    std::cout << "intrinsics: " << c.intrinsics->width_px << "x" << c.intrinsics->height_px << " px, fx "
              << fmt(c.intrinsics->fx_px, 2) << ", fy " << fmt(c.intrinsics->fy_px, 2) << ", rms "
              << fmt(c.intrinsics->rms_px, 3) << " px over " << c.intrinsics->views << " views\n";
  if (c.T_base_camera) print_transform("T_base_camera", *c.T_base_camera);
  if (c.T_camera_projector) print_transform("T_camera_projector", *c.T_camera_projector);
  if (c.hand_eye)
    std::cout << "hand-eye (" << c.hand_eye->method << "): " << c.hand_eye->poses << " poses, rms "
              << fmt(c.hand_eye->rms_mm, 3) << " mm / " << fmt(c.hand_eye->rms_deg, 3) << " deg\n";
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("calibrate", [](CLI::App& app, const fettle::cli::Common&) {
  auto* c = app.add_subcommand("calibrate", "Camera intrinsics, hand-eye calibration (docs/calibration.md)");
  c->require_subcommand(1);

  auto ia = std::make_shared<IntrinsicsArgs>();
  auto* in = c->add_subcommand("intrinsics", "Camera intrinsics (Zhang's method) from chessboard images");
  in->add_option("--images", ia->images, "Directory of chessboard images")->required();
  in->add_option("--board", ia->board, "Inner corners COLSxROWS, e.g. 9x6")->required();
  in->add_option("--square-mm", ia->square_mm, "Square size in mm")->required();
  in->add_option("--out", ia->out, "Calibration file to write")->required();
  in->add_option("--id", ia->id, "Calibration id (default: cal-<date>)");
  in->add_option("--note", ia->note, "Free text stored in the file");
  in->add_option("--min-views", ia->min_views, "Fewest usable views accepted")->capture_default_str();
  in->add_option("--max-edge-width-px", ia->max_edge_width_px, "Views with wider (blurred) edges are skipped")
      ->capture_default_str();
  in->add_flag("--k3", ia->k3, "Also estimate the k3 distortion coefficient (wide-angle lenses)");

  auto ha = std::make_shared<HandEyeArgs>();
  auto* he = c->add_subcommand("hand-eye", "Eye-to-hand calibration: T_base_camera (board or sphere on the flange)");
  he->add_flag("--live", ha->live, "Drive the robot and capture through the camera link (not available yet)");
  he->add_option("--robot-poses", ha->robot_poses,
                 "CSV name,x_mm,y_mm,z_mm,qw,qx,qy,qz of the flange in the base frame (sphere: TCP x,y,z)");
  he->add_option("--images", ha->images, "Directory with the board image of every pose (named as in the CSV)");
  he->add_option("--board-poses", ha->board_poses, "CSV of board poses in the camera frame (T_camera_board)");
  he->add_option("--clouds", ha->clouds, "Directory with the sphere scan (.xyz or .pcd) of every pose");
  he->add_option("--calibration", ha->calibration, "Calibration file with the intrinsics (kept in the output)");
  he->add_option("--board", ha->board, "Inner corners COLSxROWS (with --images)");
  he->add_option("--square-mm", ha->square_mm, "Square size in mm (with --images)");
  he->add_option("--sphere-radius-mm", ha->sphere_radius_mm, "Sphere radius (with --clouds; 0 = fit it)");
  he->add_option("--min-poses", ha->min_poses, "Fewest poses accepted")->capture_default_str();
  he->add_option("--max-edge-width-px", ha->max_edge_width_px, "Blurred images are skipped")->capture_default_str();
  he->add_option("--out", ha->out, "Calibration file to write");
  he->add_option("--id", ha->id, "Calibration id (default: cal-<date>)");
  he->add_option("--note", ha->note, "Free text stored in the file");

  auto file = std::make_shared<fs::path>();
  auto* show = c->add_subcommand("show", "Check a calibration file and print what it holds");
  show->add_option("FILE", *file, "Calibration file")->required();

  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{
      {in, [ia] { return run_intrinsics(*ia); }},
      {he, [ha] { return run_hand_eye(*ha); }},
      {show, [file] { return run_show(*file); }}};
});

}  // namespace
