// Plans every region of simulated castings (fettle::sim::Casting) of a part recipe and prints,
// per seed and region, the planning time or the planner's error. Excess points are the
// casting's top surface sampled every 0.5 mm inside each region's ROI where it stands more
// than the region's excess_threshold_mm above the golden template (a stand-in for the vision
// stage); the template is the casting's golden signed distance.
//   bench_planning_sim [part.toml] [seeds]
#include <chrono>
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "fettle/config/load.hpp"
#include "fettle/planning/planner.hpp"
#include "fettle/sim/sim.hpp"

int main(int argc, char** argv) {
  using namespace fettle;
  const std::string part = argc > 1 ? argv[1] : std::string(FETTLE_SOURCE_DIR) + "/config/parts/pump-body.toml";
  const int seeds = argc > 2 ? std::stoi(argv[2]) : 3;
  const auto recipe = config::load_part(part);
  const planning::PlannerSettings settings;
  std::printf("%-6s %-20s %8s %8s %10s  %s\n", "seed", "region", "points", "poses", "ms", "result");
  int failures = 0;
  for (int seed = 1; seed <= seeds; ++seed) {
    const auto casting = sim::Casting::make(recipe, static_cast<std::uint64_t>(seed));
    std::vector<planning::RegionInput> inputs;
    for (const auto& region : recipe.regions) {
      planning::RegionInput in;
      in.region = &region;
      in.tool = &sim::find_tool(recipe, region.tool);
      in.T_base_part = casting.T_base_part();
      in.template_sdf = [&casting](const Vec3& p) { return casting.golden_sdf_mm(p); };
      const Vec3 c(region.roi_center_mm[0], region.roi_center_mm[1], region.roi_center_mm[2]);
      const Vec3 h = 0.5 * Vec3(region.roi_size_mm[0], region.roi_size_mm[1], region.roi_size_mm[2]);
      for (double x = c.x() - h.x(); x <= c.x() + h.x(); x += 0.5)
        for (double y = c.y() - h.y(); y <= c.y() + h.y(); y += 0.5) {
          const double z = casting.surface_z_mm(x, y);
          if (!std::isfinite(z) || z < c.z() - h.z() || z > c.z() + h.z()) continue;
          const Vec3 p(x, y, z);
          if (casting.golden_sdf_mm(p) > region.excess_threshold_mm) in.excess_points_part.push_back(p);
        }
      inputs.push_back(std::move(in));
    }
    for (const auto& in : inputs) {
      const auto t0 = std::chrono::steady_clock::now();
      const auto plan = planning::plan_region(in, settings);
      const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
      std::printf("%-6d %-20s %8zu %8zu %10.1f  %s\n", seed, in.region->name.c_str(), in.excess_points_part.size(),
                  plan ? plan->points.size() : 0U, ms, plan ? "ok" : plan.error().message.c_str());
      failures += plan ? 0 : 1;
    }
    const auto t0 = std::chrono::steady_clock::now();
    const auto traj = planning::plan_part(recipe.id, inputs, settings);
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    std::printf("%-6d %-20s %8s %8zu %10.1f  %s\n", seed, "all (validated)", "", traj ? traj->points.size() : 0U, ms,
                traj ? "ok" : traj.error().message.c_str());
  }
  return failures == 0 ? 0 : 1;
}
