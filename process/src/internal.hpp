#pragma once
// Helpers shared by the pipeline's translation units (recipe.cpp, process.cpp, verify.cpp); not
// installed: process/include/ has the library's interface.
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include "fettle/core/result.hpp"
#include "fettle/planning/planner.hpp"
#include "fettle/process/pipeline.hpp"

namespace fettle::process {

using Clock = std::chrono::steady_clock;

inline double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

inline void report(const Progress& progress, std::size_t done, std::size_t total, const std::string& step) {
  if (progress) progress(done, total, step);
}

/// The error of a step of the pipeline, named in the message. A planning step's error that
/// says nothing more is of kind unplannable: no path for this part (fettled's fault 505).
inline Error step_error(const std::string& step, const Error& inner) {
  const bool planning = step == "plan" || step == "validate";
  const ErrorKind kind = inner.kind == ErrorKind::unspecified && planning ? ErrorKind::unplannable : inner.kind;
  return Error{inner.code.empty() ? "pipeline." + step : inner.code, "step " + step + ": " + inner.message, kind};
}

/// Integer cells of a uniform grid of `cell` mm, packed into one key (21 bits an axis): the
/// spatial hashing of verify.cpp and compensation.cpp.
struct CellKeys {
  double cell = 1.0;
  [[nodiscard]] std::array<std::int64_t, 3> coords(const Vec3& p) const {
    return {static_cast<std::int64_t>(std::floor(p.x() / cell)), static_cast<std::int64_t>(std::floor(p.y() / cell)),
            static_cast<std::int64_t>(std::floor(p.z() / cell))};
  }
  static std::int64_t pack(std::int64_t x, std::int64_t y, std::int64_t z) {
    return ((x & 0x1FFFFF) << 42) | ((y & 0x1FFFFF) << 21) | (z & 0x1FFFFF);
  }
  [[nodiscard]] std::int64_t key(const Vec3& p) const {
    const auto c = coords(p);
    return pack(c[0], c[1], c[2]);
  }
};

/// Calls fn(region index, its tool, pose) for every pose of the trajectories (base frame) that
/// belongs to a recipe region, and for every sample of the moves between consecutive poses
/// (planning::for_each_move_sample, validate()'s sampling) before it; without `air`, air moves
/// (and the moves into and out of them) are left out.
template <class Fn>
void for_each_tool_pose(const LoadedRecipe& loaded, const std::vector<Trajectory>& ground, bool air, Fn&& fn) {
  const auto& regions = loaded.recipe.regions;
  for (const auto& traj : ground)
    for (std::size_t i = 0; i < traj.points.size(); ++i) {
      const auto& p = traj.points[i];
      if (!air && p.kind == MoveKind::air) continue;
      const std::string name = traj.region_of(p);
      const config::Region* it = loaded.region(name);
      if (it == nullptr) continue;
      const auto region = static_cast<std::size_t>(it - regions.data());
      const auto& tool = loaded.tool_for(*it);
      if (i > 0 && (air || traj.points[i - 1].kind != MoveKind::air))
        planning::for_each_move_sample(traj.points[i - 1].T_base_tool, p.T_base_tool, [&](const Pose& m) {
          fn(region, tool, m);
          return true;
        });
      fn(region, tool, p.T_base_tool);
    }
}

/// The part and its regions located in the views (process.cpp says how).
Result<vision::Inspection> locate(const LoadedRecipe& loaded, const std::vector<View>& views, double jump_edge_mm,
                                  std::vector<StepTiming>& timings, const Progress& progress, std::size_t total);

}  // namespace fettle::process
