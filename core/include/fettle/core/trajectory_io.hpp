#pragma once
// Trajectory files, one implementation for every program (the planner's records, fettle-sim's
// robot and grinding, the CLI): JSON, as trajectory.json in a cycle record, and CSV, one point
// a line for spreadsheets and robot vendors' importers. Both hold, per point, x, y, z (mm, robot
// base frame), qw, qx, qy, qz (T_base_tool's orientation), speed_mm_s, spindle_rpm, segment and
// kind (approach, grind, air, retract); JSON also part_id and segment_regions.
#include <filesystem>

#include "fettle/core/result.hpp"
#include "fettle/core/trajectory.hpp"

namespace fettle {

/// "approach", "grind", "air" or "retract".
const char* move_kind_name(MoveKind kind);

Status write_trajectory_json(const std::filesystem::path& path, const Trajectory& trajectory);
Status write_trajectory_csv(const std::filesystem::path& path, const Trajectory& trajectory);

/// Reads a JSON (the file starts with '{') or CSV trajectory. Numbers may be written as
/// strings ("nan", "inf"): they are read as such, for the robot controller's validation to
/// refuse by point. Throws UserError naming the file and the line or point, and what is wrong.
Trajectory read_trajectory(const std::filesystem::path& path);

}  // namespace fettle
