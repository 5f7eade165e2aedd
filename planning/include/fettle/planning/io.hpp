#pragma once
// The planner's output files: trajectory.json and trajectory.csv (the format is core's,
// fettle/core/trajectory_io.hpp, read back by fettle-sim and the CLI), and preview.png: top and
// side views of the part cloud coloured by excess height with the tool path drawn.
#include <filesystem>
#include <vector>

#include "fettle/core/geometry.hpp"
#include "fettle/core/result.hpp"
#include "fettle/core/trajectory.hpp"
#include "fettle/core/trajectory_io.hpp"

namespace fettle::planning {

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
