// fettle calibrate intrinsics | projector | projector-patterns | hand-eye | show  (docs/calibration.md);
// hand-eye itself is in calibrate_hand_eye.cpp.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <future>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "fettle/cli/cli.hpp"
#include "fettle/config/calibration.hpp"
#include "fettle/config/load.hpp"
#include "fettle/core/error.hpp"
#include "fettle/drivers/camera.hpp"
#include "fettle/drivers/robot_link.hpp"
#include "fettle/vision/calibration/board.hpp"
#include "fettle/vision/calibration/gray_code.hpp"
#include "fettle/vision/calibration/hand_eye.hpp"
#include "fettle/vision/calibration/stereo.hpp"
#include "fettle/vision/cloud.hpp"

#include "calibrate_common.hpp"

namespace fettle::cli::calibrate {

namespace {

std::string default_id(const std::string& date) {
  std::string id = "cal-";
  for (const char c : date)
    if (c != '-' && c != ':') id += c;
  return id;
}

}  // namespace

// ---- input files ------------------------------------------------------------------------

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
        throw UserError(where + "quaternion qw,qx,qy,qz has norm " + fixed(q.norm(), 4) + ", not 1");
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
  if (file.extension() == ".pcd" || file.extension() == ".ply") {  // through Fettle's checked readers
    for (const auto& p : fettle::vision::load_cloud(file).points) pts.emplace_back(p.cast<double>());
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
  std::string board_type = "chessboard";
  std::string dictionary = "DICT_5X5_100";
  double square_mm = 0.0;
  double marker_mm = 0.0;
  std::size_t min_views = 5;
  double max_edge_width_px = 4.0;
  bool k3 = false;
};

cal::BoardSpec board_from(const std::string& type, const std::string& board, double square_mm, double marker_mm,
                          const std::string& dictionary) {
  if (type == "charuco") return cal::parse_charuco_board(board, square_mm, marker_mm, dictionary);
  if (type != "chessboard") throw UserError("--board-type \"" + type + "\": use chessboard or charuco");
  return cal::parse_board(board, square_mm);
}

int run_intrinsics(const IntrinsicsArgs& a) {
  const auto board = board_from(a.board_type, a.board, a.square_mm, a.marker_mm, a.dictionary);
  std::cerr << "board: " << cal::describe(board) << "\n";
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
              << (v.used ? "rms " + fixed(v.rms_px, 3) + " px" : v.skip_reason) << "\n";
  const auto& k = r->intrinsics;
  std::cout << "image " << k.width_px << "x" << k.height_px << " px, " << k.views << " views used\n"
            << "fx " << fixed(k.fx_px, 2) << "  fy " << fixed(k.fy_px, 2) << "  cx " << fixed(k.cx_px, 2) << "  cy "
            << fixed(k.cy_px, 2) << " px\n"
            << "distortion";
  for (const double d : k.distortion) std::cout << " " << fixed(d, 6);
  std::cout << "\nreprojection rms " << fixed(k.rms_px, 4) << " px\n";
  auto file = new_file(a.id, a.note);
  file.intrinsics = k;
  fettle::config::write_calibration(a.out, file);
  std::cout << "wrote " << a.out.string() << " (id " << file.id << ")\n";
  return fettle::exit_code::ok;
}

// ---- camera-projector (Gray code) ----------------------------------------------------------

struct ProjectorArgs {
  fs::path images, camera_intrinsics, out;
  std::string board, projector, id, note;
  std::string board_type = "chessboard";
  std::string dictionary = "DICT_5X5_100";
  double square_mm = 0.0;
  double marker_mm = 0.0;
  double min_contrast_grey = 15.0;
  std::size_t min_views = 3;
};

cal::GrayCodeLayout parse_projector_size(const std::string& text) {
  const auto x = text.find('x');
  int w = 0, h = 0;
  try {
    if (x == std::string::npos) throw std::invalid_argument("no x");
    std::size_t used_w = 0, used_h = 0;
    w = std::stoi(text.substr(0, x), &used_w);
    h = std::stoi(text.substr(x + 1), &used_h);
    if (used_w != x || used_h != text.size() - x - 1) throw std::invalid_argument("trailing");
  } catch (const std::exception&) {
    throw UserError("--projector \"" + text + "\": expected WIDTHxHEIGHT in projector pixels, e.g. 1280x800");
  }
  return cal::GrayCodeLayout::for_projector(w, h);
}

/// The pattern images of one board pose, in GrayCodeLayout order, found by name (any image
/// extension) in `dir`.
std::vector<cal::GrayImage> load_pattern_images(const fs::path& dir, const cal::GrayCodeLayout& layout) {
  std::map<std::string, fs::path> by_stem;
  for (const auto& f : cal::list_images(dir)) by_stem.emplace(f.stem().string(), f);
  std::vector<cal::GrayImage> images;
  for (const auto& name : layout.names()) {
    const auto it = by_stem.find(name);
    if (it == by_stem.end())
      throw UserError(
          dir.string() + ": no image named " + name + " (.png, .bmp, .tif, .pgm, .jpg); a " +
          std::to_string(layout.width_px) + "x" + std::to_string(layout.height_px) + " px projector's sequence has " +
          std::to_string(layout.image_count()) + " images: white, black, col_00, col_00_inv ... " +
          layout.names()[1 + 2 * static_cast<std::size_t>(layout.column_bits)] + ", row_00, row_00_inv ... " +
          layout.names().back() + " (`fettle calibrate projector-patterns` writes them)");
    auto img = cal::load_gray_image(it->second);
    if (!img) throw UserError(img.error().message);
    img->name = it->second.string();
    images.push_back(std::move(*img));
  }
  return images;
}

int run_projector(const ProjectorArgs& a) {
  const auto board = board_from(a.board_type, a.board, a.square_mm, a.marker_mm, a.dictionary);
  const auto layout = parse_projector_size(a.projector);
  const auto base = fettle::config::load_calibration(a.camera_intrinsics);
  if (!base.intrinsics)
    throw UserError(a.camera_intrinsics.string() +
                    ": has no [intrinsics] section; run `fettle calibrate intrinsics` first");
  if (!fs::is_directory(a.images)) throw UserError(a.images.string() + ": not a directory");
  std::vector<fs::path> poses;
  for (const auto& e : fs::directory_iterator(a.images))
    if (e.is_directory()) poses.push_back(e.path());
  std::sort(poses.begin(), poses.end());
  if (poses.empty())
    throw UserError(a.images.string() + ": no sub-directories; put the " + std::to_string(layout.image_count()) +
                    " pattern images of each board pose in a directory of its own (pose01, pose02, ...)");
  std::cerr << "board: " << cal::describe(board) << "; projector " << layout.width_px << "x" << layout.height_px
            << " px, " << layout.image_count() << " images per pose\n";
  cal::StructuredLightOptions o;
  o.decode.min_contrast_grey = a.min_contrast_grey;
  std::vector<cal::StereoView> views;
  std::vector<std::string> skipped;
  for (std::size_t i = 0; i < poses.size(); ++i) {
    std::cerr << "pose " << i + 1 << "/" << poses.size() << ": " << poses[i].string() << "\n";
    const auto images = load_pattern_images(poses[i], layout);
    if (images[0].width_px != base.intrinsics->width_px || images[0].height_px != base.intrinsics->height_px)
      throw UserError(images[0].name + ": " + std::to_string(images[0].width_px) + "x" +
                      std::to_string(images[0].height_px) + " px, but the camera intrinsics in " +
                      a.camera_intrinsics.string() + " are for " + std::to_string(base.intrinsics->width_px) + "x" +
                      std::to_string(base.intrinsics->height_px) + " px images");
    auto v = cal::decode_stereo_view(images, board, layout, o);
    if (!v) {
      // Wrong sizes or counts are the operator's to fix; a pose the decode cannot use is skipped.
      if (v.error().code == "calibration.image_size" || v.error().code == "calibration.pattern_count")
        throw UserError(poses[i].string() + ": " + v.error().message);
      std::cout << "  SKIPPED  " << poses[i].filename().string() << "  " << v.error().message << "\n";
      skipped.push_back(poses[i].filename().string() + ": " + v.error().message);
      continue;
    }
    std::cout << "  used     " << poses[i].filename().string() << "  " << v->corners_decoded << " of "
              << v->corners_total << " corners decoded, " << v->map.valid_pixels << " pixels decoded ("
              << v->map.low_contrast_pixels << " low contrast, " << v->map.undecided_pixels << " undecided)\n";
    views.push_back(std::move(v->view));
  }
  if (views.size() < a.min_views) {
    std::string why;
    for (const auto& s : skipped) why += "\n  " + s;
    throw UserError("only " + std::to_string(views.size()) + " of " + std::to_string(poses.size()) +
                    " board poses usable, need " + std::to_string(a.min_views) + why);
  }
  auto kp = cal::calibrate_projector_intrinsics(views, layout.width_px, layout.height_px);
  if (!kp) throw UserError(kp.error().message);
  std::cout << "projector intrinsics (inverse camera, " << views.size() << " views): fx " << fixed(kp->fx_px, 2)
            << "  fy " << fixed(kp->fy_px, 2) << "  cx " << fixed(kp->cx_px, 2) << "  cy " << fixed(kp->cy_px, 2)
            << " px, distortion";
  for (const double d : kp->distortion) std::cout << " " << fixed(d, 6);
  std::cout << ", rms " << fixed(kp->rms_px, 3) << " px\n";
  cal::StereoOptions so;
  so.min_views = a.min_views;
  auto r = cal::calibrate_camera_projector(views, *base.intrinsics, *kp, so);
  if (!r) throw UserError(r.error().message);
  std::cout << "stereo rms " << fixed(r->rms_px, 3) << " px\n";
  print_transform("T_camera_projector", r->T_camera_projector);
  auto file = new_file(a.id, a.note);
  file.intrinsics = base.intrinsics;
  file.T_base_camera = base.T_base_camera;
  file.T_flange_board = base.T_flange_board;
  file.hand_eye = base.hand_eye;
  file.T_camera_projector = r->T_camera_projector;
  file.stereo_rms_px = r->rms_px;
  fettle::config::write_calibration(a.out, file);
  std::cout << "wrote " << a.out.string() << " (id " << file.id << ")\n";
  return fettle::exit_code::ok;
}

int run_projector_patterns(const std::string& projector, const fs::path& out) {
  const auto layout = parse_projector_size(projector);
  fs::create_directories(out);
  const auto patterns = cal::gray_code_patterns(layout);
  for (const auto& p : patterns) {
    const cv::Mat m(p.height_px, p.width_px, CV_8UC1, const_cast<std::uint8_t*>(p.pixels.data()));  // NOLINT
    const fs::path file = out / (p.name + ".png");
    if (!cv::imwrite(file.string(), m)) throw UserError(file.string() + ": cannot be written");
  }
  std::cout << "wrote " << patterns.size() << " pattern images (" << layout.width_px << "x" << layout.height_px
            << " px) to " << out.string() << "\n";
  return fettle::exit_code::ok;
}

// ---- show -------------------------------------------------------------------------------

int run_show(const fs::path& path) {
  const auto c = fettle::config::load_calibration(path);
  std::cout << path.string() << ": OK\nid " << c.id << ", date " << c.date << (c.note.empty() ? "" : ", " + c.note)
            << "\n";
  if (c.intrinsics)
    std::cout << "intrinsics: " << c.intrinsics->width_px << "x" << c.intrinsics->height_px << " px, fx "
              << fixed(c.intrinsics->fx_px, 2) << ", fy " << fixed(c.intrinsics->fy_px, 2) << ", rms "
              << fixed(c.intrinsics->rms_px, 3) << " px over " << c.intrinsics->views << " views\n";
  if (c.T_base_camera) print_transform("T_base_camera", *c.T_base_camera);
  if (c.T_camera_projector) print_transform("T_camera_projector", *c.T_camera_projector);
  if (c.hand_eye)
    std::cout << "hand-eye (" << c.hand_eye->method << "): " << c.hand_eye->poses << " poses, rms "
              << fixed(c.hand_eye->rms_mm, 3) << " mm / " << fixed(c.hand_eye->rms_deg, 3) << " deg\n";
  return fettle::exit_code::ok;
}

}  // namespace fettle::cli::calibrate

namespace {

using namespace fettle::cli::calibrate;  // NOLINT(google-build-using-namespace): the command's wiring

FETTLE_COMMAND("calibrate", [](CLI::App& app, const fettle::cli::Common&) {
  auto* c = app.add_subcommand("calibrate",
                               "Camera intrinsics, camera-projector, hand-eye calibration (docs/calibration.md)");
  c->require_subcommand(1);

  auto ia = std::make_shared<IntrinsicsArgs>();
  auto* in = c->add_subcommand("intrinsics", "Camera intrinsics (Zhang's method) from chessboard images");
  in->add_option("--images", ia->images, "Directory of chessboard images")->required();
  in->add_option("--board", ia->board, "Chessboard: inner corners COLSxROWS, e.g. 9x6; ChArUco: squares, e.g. 7x5")
      ->required();
  in->add_option("--square-mm", ia->square_mm, "Square size in mm")->required();
  in->add_option("--board-type", ia->board_type, "chessboard or charuco")->capture_default_str();
  in->add_option("--marker-mm", ia->marker_mm, "ChArUco marker size in mm");
  in->add_option("--dictionary", ia->dictionary, "ChArUco marker dictionary (OpenCV name)")->capture_default_str();
  in->add_option("--out", ia->out, "Calibration file to write")->required();
  in->add_option("--id", ia->id, "Calibration id (default: cal-<date>)");
  in->add_option("--note", ia->note, "Free text stored in the file");
  in->add_option("--min-views", ia->min_views, "Fewest usable views accepted")->capture_default_str();
  in->add_option("--max-edge-width-px", ia->max_edge_width_px, "Views with wider (blurred) edges are skipped")
      ->capture_default_str();
  in->add_flag("--k3", ia->k3, "Also estimate the k3 distortion coefficient (wide-angle lenses)");

  auto pa = std::make_shared<ProjectorArgs>();
  auto* pr = c->add_subcommand("projector", "Camera-projector extrinsics (T_camera_projector) from Gray-code images");
  pr->add_option("--images", pa->images,
                 "Directory with one sub-directory per board pose, each holding the pattern images white, black, "
                 "col_00, col_00_inv, ..., row_NN_inv")
      ->required();
  pr->add_option("--board", pa->board, "Chessboard: inner corners COLSxROWS, e.g. 9x6; ChArUco: squares")->required();
  pr->add_option("--square-mm", pa->square_mm, "Square size in mm")->required();
  pr->add_option("--board-type", pa->board_type, "chessboard or charuco")->capture_default_str();
  pr->add_option("--marker-mm", pa->marker_mm, "ChArUco marker size in mm");
  pr->add_option("--dictionary", pa->dictionary, "ChArUco marker dictionary")->capture_default_str();
  pr->add_option("--projector", pa->projector, "Projector resolution WIDTHxHEIGHT, e.g. 1280x800")->required();
  pr->add_option("--camera-intrinsics", pa->camera_intrinsics,
                 "Calibration file with the camera's [intrinsics] (kept in the output with its other sections)")
      ->required();
  pr->add_option("--out", pa->out, "Calibration file to write")->required();
  pr->add_option("--id", pa->id, "Calibration id (default: cal-<date>)");
  pr->add_option("--note", pa->note, "Free text stored in the file");
  pr->add_option("--min-contrast-grey", pa->min_contrast_grey,
                 "Pixels whose white - black difference is smaller are not decoded (shadow, dark spots)")
      ->capture_default_str();
  pr->add_option("--min-views", pa->min_views, "Fewest usable board poses accepted")->capture_default_str();

  auto patterns_size = std::make_shared<std::string>();
  auto patterns_out = std::make_shared<fs::path>();
  auto* pp = c->add_subcommand("projector-patterns", "Write the Gray-code pattern images for the projector");
  pp->add_option("--projector", *patterns_size, "Projector resolution WIDTHxHEIGHT, e.g. 1280x800")->required();
  pp->add_option("--out", *patterns_out, "Directory to write white.png, black.png, col_00.png, ...")->required();

  auto ha = std::make_shared<HandEyeArgs>();
  auto* he = c->add_subcommand("hand-eye", "Eye-to-hand calibration: T_base_camera (board or sphere on the flange)");
  he->add_flag("--live", ha->live,
               "Drive the robot through poses and scan the sphere it holds (sphere method; needs --config)");
  he->add_option("--config", ha->config, "Cell file: robot, camera and nominal calibration (with --live)");
  he->add_option("--poses", ha->poses, "TOML file of [[pose]] position_mm = [x, y, z] TCP poses (with --live)");
  he->add_option("--auto", ha->auto_poses, "Spread N poses over the camera's view (with --live)");
  he->add_option("--speed-mm-s", ha->speed_mm_s, "Robot speed between poses (with --live)")->capture_default_str();
  he->add_option("--settle-ms", ha->settle_ms, "Wait after each move before scanning (with --live)")
      ->capture_default_str();
  he->add_option("--search-radius-mm", ha->search_radius_mm,
                 "Look for the sphere this far around where the nominal calibration puts it (with --live)")
      ->capture_default_str();
  he->add_option("--auto-min-height-mm", ha->auto_min_height_mm,
                 "Lowest sphere height above the base for --auto (default: [safety] safe_height_mm)");
  he->add_option("--auto-max-height-mm", ha->auto_max_height_mm,
                 "Highest sphere height for --auto (default: min + 150)");
  he->add_option("--robot-poses", ha->robot_poses,
                 "CSV name,x_mm,y_mm,z_mm,qw,qx,qy,qz of the flange in the base frame (sphere: TCP x,y,z)");
  he->add_option("--images", ha->images, "Directory with the board image of every pose (named as in the CSV)");
  he->add_option("--board-poses", ha->board_poses, "CSV of board poses in the camera frame (T_camera_board)");
  he->add_option("--clouds", ha->clouds, "Directory with the sphere scan (.xyz, .pcd or .ply) of every pose");
  he->add_option("--calibration", ha->calibration, "Calibration file with the intrinsics (kept in the output)");
  he->add_option("--board", ha->board, "Chessboard inner corners / ChArUco squares COLSxROWS (with --images)");
  he->add_option("--square-mm", ha->square_mm, "Square size in mm (with --images)");
  he->add_option("--board-type", ha->board_type, "chessboard or charuco (with --images)")->capture_default_str();
  he->add_option("--marker-mm", ha->marker_mm, "ChArUco marker size in mm");
  he->add_option("--dictionary", ha->dictionary, "ChArUco marker dictionary")->capture_default_str();
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
      {pr, [pa] { return run_projector(*pa); }},
      {pp, [patterns_size, patterns_out] { return run_projector_patterns(*patterns_size, *patterns_out); }},
      {he, [ha] { return run_hand_eye(*ha); }},
      {show, [file] { return run_show(*file); }}};
});

}  // namespace
