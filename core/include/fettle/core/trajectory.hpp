#pragma once
// A grinding trajectory as the planner hands it to the robot link.
#include <string>
#include <vector>

#include "fettle/core/geometry.hpp"

namespace fettle {

enum class MoveKind { approach, grind, air, retract };

struct TrajectoryPoint {
  Pose T_base_tool;             ///< tool pose in the robot base frame (mm, unit quaternion)
  double speed_mm_s = 0.0;      ///< TCP speed towards this point
  double spindle_rpm = 0.0;     ///< spindle speed at this point (0 = off)
  int segment = 0;              ///< segment / pass id
  MoveKind kind = MoveKind::grind;
};

struct Trajectory {
  std::string part_id;
  std::vector<std::string> segment_regions;  ///< segment id -> region name
  std::vector<TrajectoryPoint> points;

  /// The region `p` belongs to through its segment, or `none` when segment_regions has no entry.
  [[nodiscard]] std::string region_of(const TrajectoryPoint& p, const std::string& none = {}) const {
    return p.segment >= 0 && static_cast<std::size_t>(p.segment) < segment_regions.size()
               ? segment_regions[static_cast<std::size_t>(p.segment)]
               : none;
  }
};

}  // namespace fettle
