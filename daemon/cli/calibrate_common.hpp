#pragma once
// What `fettle calibrate`'s subcommands share (calibrate_command.cpp: intrinsics, projector,
// show and the command line; calibrate_hand_eye.cpp: hand-eye from files and --live).
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <optional>
#include <string>
#include <vector>

#include "fettle/config/calibration.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/geometry.hpp"
#include "fettle/vision/calibration/board.hpp"
#include "fettle/vision/calibration/hand_eye.hpp"

namespace fettle::cli::calibrate {

namespace fs = std::filesystem;
namespace cal = fettle::vision::calibration;
using fettle::Transform;
using fettle::UserError;
using fettle::Vec3;

/// `v` with `decimals` digits after the point.
inline std::string fixed(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  return buf;
}

inline void print_transform(const char* name, const Transform& T) {
  const fettle::Pose p = fettle::Pose::from_transform(T);
  const Eigen::AngleAxisd aa(T.rotation());
  std::cout << name << ": position [" << fixed(p.position_mm.x(), 3) << ", " << fixed(p.position_mm.y(), 3) << ", "
            << fixed(p.position_mm.z(), 3) << "] mm, rotation " << fixed(fettle::rad_to_deg(aa.angle()), 4)
            << " deg about [" << fixed(aa.axis().x(), 4) << ", " << fixed(aa.axis().y(), 4) << ", "
            << fixed(aa.axis().z(), 4) << "]\n";
}

struct PoseRow {
  std::string name;
  Vec3 position_mm;
  std::optional<fettle::Quat> orientation;
};

/// CSV: name,x_mm,y_mm,z_mm[,qw,qx,qy,qz]; '#' comments, blank lines and a header line
/// starting with "name" are ignored.
std::vector<PoseRow> read_pose_csv(const fs::path& file, bool need_orientation);
Transform to_transform(const PoseRow& r);
/// Points of a PCD, PLY or x y z text file.
std::vector<Vec3> read_cloud(const fs::path& file);
/// The calibration board from --board-type, --board, --square-mm, --marker-mm, --dictionary.
cal::BoardSpec board_from(const std::string& type, const std::string& board, double square_mm, double marker_mm,
                          const std::string& dictionary);
/// A new calibration file dated now; `id` empty: one made from the date.
fettle::config::CalibrationFile new_file(const std::string& id, const std::string& note);

struct HandEyeArgs {
  bool live = false;
  fs::path robot_poses, images, board_poses, clouds, calibration, out;
  fs::path config, poses;  // --live
  int auto_poses = 0;      // --live --auto N
  double speed_mm_s = 50.0;
  int settle_ms = 500;
  double search_radius_mm = 60.0;
  double auto_min_height_mm = 0.0;  // 0 = the cell's safe_height_mm
  double auto_max_height_mm = 0.0;  // 0 = min + 150 mm
  std::string board, id, note;
  std::string board_type = "chessboard";
  std::string dictionary = "DICT_5X5_100";
  double square_mm = 0.0;
  double marker_mm = 0.0;
  double sphere_radius_mm = 0.0;
  std::size_t min_poses = 6;
  double max_edge_width_px = 4.0;
};

int run_hand_eye(const HandEyeArgs& a);
int run_hand_eye_live(const HandEyeArgs& a);

}  // namespace fettle::cli::calibrate
