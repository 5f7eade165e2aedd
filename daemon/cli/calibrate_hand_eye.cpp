// fettle calibrate hand-eye: from recorded poses with images, board poses or clouds, and --live
// against the robot controller and the camera (docs/calibration.md).
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

// ---- hand-eye ---------------------------------------------------------------------------

void print_residuals(const fettle::config::HandEyeResiduals& r) {
  for (const auto& p : r.per_pose)
    std::cout << (p.outlier ? "  OUTLIER  " : "  ok       ") << p.name << "  " << fixed(p.translation_mm, 3) << " mm"
              << (r.method == "board" ? "  " + fixed(p.rotation_deg, 3) + " deg" : std::string()) << "\n";
  std::cout << r.poses << " poses used; residual rms " << fixed(r.rms_mm, 3) << " mm (max " << fixed(r.max_mm, 3)
            << ")";
  if (r.method == "board") std::cout << ", " << fixed(r.rms_deg, 3) << " deg (max " << fixed(r.max_deg, 3) << ")";
  std::cout << "\n";
}

int run_hand_eye(const HandEyeArgs& a) {
  if (a.live) return run_hand_eye_live(a);
  if (a.robot_poses.empty()) throw UserError("--robot-poses FILE is required (or --live --config CELL)");
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
      std::cerr << "  centre [" << fixed(fit->center_mm.x(), 3) << ", " << fixed(fit->center_mm.y(), 3) << ", "
                << fixed(fit->center_mm.z(), 3) << "] mm, radius " << fixed(fit->radius_mm, 3) << " mm, "
                << fit->inliers << " points, rms " << fixed(fit->rms_mm, 3) << " mm\n";
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
        throw UserError(
            "--images needs the camera intrinsics: give --calibration FILE (from `fettle calibrate "
            "intrinsics`)");
      const auto board = board_from(a.board_type, a.board, a.square_mm, a.marker_mm, a.dictionary);
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
                  << fixed(pose->T_camera_board.translation().norm(), 1) << " mm, reprojection rms "
                  << fixed(pose->rms_px, 3) << " px\n";
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

// ---- hand-eye --live ----------------------------------------------------------------------

/// The robot link on its own io thread, with blocking calls for the calibration sequence.
class LiveRobot {
 public:
  explicit LiveRobot(fettle::drivers::RobotLinkOptions o)
      : options_(std::move(o)), work_(boost::asio::make_work_guard(io_)), link_(io_, options_) {
    boost::asio::post(io_, [this] { link_.start(); });
    thread_ = std::thread([this] { io_.run(); });
  }
  ~LiveRobot() {
    boost::asio::post(io_, [this] { link_.shutdown(); });
    work_.reset();
    io_.stop();
    thread_.join();
  }
  LiveRobot(const LiveRobot&) = delete;
  LiveRobot& operator=(const LiveRobot&) = delete;

  /// Waits until the link is ready; throws DeviceError naming the robot's address.
  void wait_ready() {
    const auto until = std::chrono::steady_clock::now() + std::chrono::milliseconds(options_.connect_timeout_ms + 1000);
    while (std::chrono::steady_clock::now() < until) {
      if (on_io([this] { return link_.state(); }) == fettle::drivers::RobotState::ready) return;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    const auto err = on_io([this] { return link_.last_error(); });
    throw fettle::DeviceError("robot controller at " + where() + " is not ready (" +
                              std::string(fettle::drivers::to_string(on_io([this] { return link_.state(); }))) +
                              (err.message.empty() ? "" : ": " + err.message) +
                              "); check [robot] address/port in the cell file and that the robot program runs");
  }

  /// Moves the tool to `target` in a straight line at `speed_mm_s`; returns at DONE.
  fettle::Status move_to(const fettle::Pose& target, double speed_mm_s) {
    fettle::Trajectory t;
    t.part_id = "hand-eye calibration";
    t.segment_regions = {"calibration"};
    t.points.push_back(fettle::TrajectoryPoint{target, speed_mm_s, 0.0, 0, fettle::MoveKind::air});
    if (auto s = call([this, t](fettle::drivers::RobotLink::Handler h) { link_.upload(t, std::move(h)); },
                      options_.reply_timeout_ms * 4);
        !s)
      return s;
    return call([this](fettle::drivers::RobotLink::Handler h) { link_.run(std::move(h)); },
                options_.run_timeout_ms + 2000);
  }

  [[nodiscard]] std::string where() const { return options_.address + ":" + std::to_string(options_.port); }

 private:
  template <class F>
  auto on_io(F f) -> decltype(f()) {
    std::promise<decltype(f())> p;
    auto fut = p.get_future();
    boost::asio::post(io_, [&] { p.set_value(f()); });
    return fut.get();
  }

  template <class F>
  fettle::Status call(F start, int timeout_ms) {
    auto p = std::make_shared<std::promise<fettle::Status>>();
    auto fut = p->get_future();
    boost::asio::post(io_, [start, p] { start([p](fettle::Status s) { p->set_value(std::move(s)); }); });
    if (fut.wait_for(std::chrono::milliseconds(timeout_ms)) != std::future_status::ready)
      return fettle::Error{"robot.timeout",
                           "no answer from the robot at " + where() + " within " + std::to_string(timeout_ms) + " ms"};
    return fut.get();
  }

  fettle::drivers::RobotLinkOptions options_;
  boost::asio::io_context io_;
  boost::asio::executor_work_guard<boost::asio::io_context::executor_type> work_;
  fettle::drivers::RobotLink link_;
  std::thread thread_;
};

/// The van der Corput radical inverse (a low-discrepancy sequence for spreading poses).
double radical_inverse(int i, int base) {
  double f = 1.0, r = 0.0;
  for (; i > 0; i /= base) {
    f /= base;
    r += f * (i % base);
  }
  return r;
}

/// `n` sphere positions spread over the camera's view: image points of a Halton sequence in the
/// middle 70 % of the image, on 3 heights above the table, tool pointing down.
std::vector<fettle::config::CalibrationPose> auto_poses(int n, const Transform& T_base_camera,
                                                        const fettle::drivers::CameraInfo& cam, double min_h,
                                                        double max_h) {
  const auto& in = cam.scan3d.intrinsics;
  if (!in) throw UserError("--auto needs the camera's intrinsics (Scan3d features or [camera] intrinsics)");
  std::vector<fettle::config::CalibrationPose> poses;
  const Vec3 origin = T_base_camera.translation();
  for (int i = 0; i < n; ++i) {
    const double u = cam.width * (0.15 + 0.7 * radical_inverse(i + 1, 2));
    const double v = cam.height * (0.15 + 0.7 * radical_inverse(i + 1, 3));
    const double h = min_h + (max_h - min_h) * 0.5 * (i % 3);
    const Vec3 ray = T_base_camera.rotation() * Vec3((u - in->cx_px) / in->fx_px, (v - in->cy_px) / in->fy_px, 1.0);
    if (ray.z() > -1e-6) throw UserError("--auto: the nominal camera does not look down at the table");
    const double s = (h - origin.z()) / ray.z();
    fettle::config::CalibrationPose p;
    p.name = "auto" + std::to_string(i + 1);
    p.T_base_tool = fettle::Pose{origin + s * ray, fettle::Quat(0.0, 1.0, 0.0, 0.0)};
    poses.push_back(p);
  }
  return poses;
}

int run_hand_eye_live(const HandEyeArgs& a) {
  if (a.config.empty()) throw UserError("--live needs --config CELL.toml (the robot and camera to use)");
  if (a.out.empty()) throw UserError("--out FILE is required");
  if ((a.auto_poses > 0) == !a.poses.empty()) throw UserError("--live needs exactly one of --poses FILE or --auto N");
  if (!a.images.empty() || !a.board_poses.empty() || !a.clouds.empty() || !a.robot_poses.empty())
    throw UserError(
        "--live records its own poses and scans: leave out --robot-poses, --images, --board-poses, "
        "--clouds");
  if (!a.board.empty())
    throw UserError(
        "--live uses the sphere method: the cell's 3D camera delivers range maps, in which a board "
        "cannot be found. Hold a sphere in the tool (--sphere-radius-mm), or record board images "
        "yourself and use --robot-poses with --images");
  if (!(a.sphere_radius_mm > 0.0)) throw UserError("--live needs --sphere-radius-mm R (the sphere held by the robot)");
  if (!(a.speed_mm_s > 0.0)) throw UserError("--speed-mm-s must be above 0");

  const auto cell = fettle::config::load_cell(a.config);
  if (cell.calibration.file.empty())
    throw UserError(a.config.string() +
                    ": [calibration] file is needed: --live finds the sphere near where a nominal "
                    "T_base_camera (e.g. from the cell drawing) puts it");
  const auto nominal = fettle::config::load_calibration(cell.calibration.file);
  if (!nominal.T_base_camera)
    throw UserError(cell.calibration.file.string() +
                    ": has no [T_base_camera]; --live needs a nominal one (from the "
                    "cell drawing, within --search-radius-mm of the truth)");
  const Transform T_nominal = *nominal.T_base_camera;
  if (a.speed_mm_s > cell.safety.max_speed_mm_s)
    throw UserError("--speed-mm-s " + fixed(a.speed_mm_s, 1) + " exceeds the cell's [safety] max_speed_mm_s " +
                    fixed(cell.safety.max_speed_mm_s, 1));

  auto cam_options = fettle::drivers::camera_options(cell.camera);
  if (cell.camera.intrinsics == "calibration" && nominal.intrinsics)
    cam_options.intrinsics = fettle::drivers::Intrinsics{nominal.intrinsics->fx_px, nominal.intrinsics->fy_px,
                                                         nominal.intrinsics->cx_px, nominal.intrinsics->cy_px};
  std::cerr << "camera: connecting to " << cam_options.address << "\n";
  fettle::drivers::Camera camera(cam_options);
  std::cerr << "robot: connecting to " << cell.robot.address << ":" << cell.robot.port << "\n";
  LiveRobot robot(fettle::drivers::RobotLinkOptions::from_config(cell.robot));
  robot.wait_ready();

  std::vector<fettle::config::CalibrationPose> poses;
  if (!a.poses.empty()) {
    poses = fettle::config::load_calibration_poses(a.poses);
  } else {
    const double lo = a.auto_min_height_mm > 0.0 ? a.auto_min_height_mm : cell.safety.safe_height_mm;
    const double hi = a.auto_max_height_mm > 0.0 ? a.auto_max_height_mm : lo + 150.0;
    if (!(hi > lo)) throw UserError("--auto-max-height-mm must be above --auto-min-height-mm");
    poses = auto_poses(a.auto_poses, T_nominal, camera.info(), lo, hi);
  }
  for (const auto& p : poses)
    for (int k = 0; k < 3; ++k)
      if (p.T_base_tool.position_mm[k] < cell.safety.workspace_min_mm[static_cast<std::size_t>(k)] ||
          p.T_base_tool.position_mm[k] > cell.safety.workspace_max_mm[static_cast<std::size_t>(k)])
        throw UserError("pose \"" + p.name + "\" at [" + fixed(p.T_base_tool.position_mm.x(), 1) + ", " +
                        fixed(p.T_base_tool.position_mm.y(), 1) + ", " + fixed(p.T_base_tool.position_mm.z(), 1) +
                        "] mm lies outside the cell's [safety] workspace; nothing was moved");

  cal::SphereFitOptions fo;
  fo.radius_mm = a.sphere_radius_mm;
  std::vector<cal::SphereSample> samples;
  const Transform T_camera_base_nominal = T_nominal.inverse();
  for (std::size_t i = 0; i < poses.size(); ++i) {
    const auto& p = poses[i];
    const Vec3& tcp = p.T_base_tool.position_mm;
    std::cerr << "pose " << i + 1 << "/" << poses.size() << " " << p.name << ": moving to [" << fixed(tcp.x(), 1)
              << ", " << fixed(tcp.y(), 1) << ", " << fixed(tcp.z(), 1) << "] mm\n";
    if (auto s = robot.move_to(p.T_base_tool, a.speed_mm_s); !s)
      throw fettle::DeviceError("robot at " + robot.where() + ": moving to pose \"" + p.name +
                                "\" failed: " + s.error().message + " (" + s.error().code + ")");
    std::this_thread::sleep_for(std::chrono::milliseconds(a.settle_ms));
    auto c = camera.capture();
    if (!c)
      throw fettle::DeviceError("camera at " + cam_options.address + ": capture at pose \"" + p.name +
                                "\" failed: " + c.error().message);
    // Only points near where the nominal calibration puts the sphere: the table and the rest
    // of the scene would drown it.
    const Vec3 expected = T_camera_base_nominal * tcp;
    std::vector<Vec3> near;
    for (const auto& q : c->cloud.points)
      if (q.allFinite() && (q.cast<double>() - expected).norm() < a.search_radius_mm + a.sphere_radius_mm)
        near.push_back(q.cast<double>());
    auto fit = cal::fit_sphere(near, fo);
    if (!fit) {
      std::cout << "  SKIPPED  " << p.name << "  " << fit.error().message << " (searched within "
                << fixed(a.search_radius_mm, 0) << " mm of where the nominal calibration puts it)\n";
      continue;
    }
    std::cerr << "  sphere at [" << fixed(fit->center_mm.x(), 3) << ", " << fixed(fit->center_mm.y(), 3) << ", "
              << fixed(fit->center_mm.z(), 3) << "] mm (camera), " << fit->inliers << " points, rms "
              << fixed(fit->rms_mm, 3) << " mm, " << fixed((fit->center_mm - expected).norm(), 1)
              << " mm from the nominal\n";
    samples.push_back(cal::SphereSample{p.name, tcp, fit->center_mm});
  }
  cal::HandEyeOptions o;
  o.min_poses = a.min_poses;
  auto r = cal::calibrate_hand_eye_sphere(samples, o);
  if (!r) throw UserError(r.error().message);
  print_residuals(r->residuals);
  auto file = new_file(a.id, a.note);
  file.intrinsics = nominal.intrinsics;
  file.T_camera_projector = nominal.T_camera_projector;
  file.stereo_rms_px = nominal.stereo_rms_px;
  file.T_base_camera = r->T_base_camera;
  file.hand_eye = r->residuals;
  print_transform("T_base_camera", *file.T_base_camera);
  const Transform d = T_nominal.inverse() * r->T_base_camera;
  std::cout << "differs from the nominal by " << fixed(d.translation().norm(), 3) << " mm and "
            << fixed(fettle::rad_to_deg(fettle::rotation_angle_rad(d)), 4) << " deg\n";
  fettle::config::write_calibration(a.out, file);
  std::cout << "wrote " << a.out.string() << " (id " << file.id << ")\n";
  return fettle::exit_code::ok;
}

}  // namespace fettle::cli::calibrate
