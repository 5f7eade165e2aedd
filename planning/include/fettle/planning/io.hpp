#pragma once
// Trajectory files, compatible with the simulator's reader (fettle::sim::read_trajectory):
//   trajectory.json {"part_id", "segment_regions": [...], "points": [{"x","y","z","qw","qx","qy",
//                    "qz","speed_mm_s","spindle_rpm","segment","kind"}...]}
//   trajectory.csv  header x,y,z,qw,qx,qy,qz,speed_mm_s,spindle_rpm,segment,kind
// Poses are T_base_tool (TCP), mm. preview.png: top and side views of the part cloud coloured by
// excess height with the tool path drawn.
#include <filesystem>
#include <vector>

#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"
#include "fettle/core/trajectory.hpp"

namespace fettle::planning {

Status write_trajectory_json(const std::filesystem::path& path, const Trajectory& trajectory);
Status write_trajectory_csv(const std::filesystem::path& path, const Trajectory& trajectory);
/// Reads trajectory.json back (throws UserError naming the file and the point on bad input).
Trajectory read_trajectory_json(const std::filesystem::path& path);

struct PreviewPoint {
  Vec3 position_base_mm;
  double excess_mm = 0.0;  ///< height above the template (0 for template points)
};
Status write_preview_png(const std::filesystem::path& path, const std::vector<PreviewPoint>& cloud,
                         const Trajectory& trajectory);

/// Writes trajectory.json, trajectory.csv and preview.png into `dir` (created if needed).
Status write_outputs(const std::filesystem::path& dir, const Trajectory& trajectory,
                     const std::vector<PreviewPoint>& cloud);

}  // namespace fettle::planning
