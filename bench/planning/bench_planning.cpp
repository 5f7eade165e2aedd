// Planning time for all regions of a pump-body-sized input (target: <= 100 ms).
// The input is the synthetic part of tests/planning/synthetic_part.hpp: ring flash, riser,
// boss circle flash and straight flash sampled at 0.5 mm (the vision voxel size), about
// as many excess points as the simulator's pump body yields. Prints a table; exit 1 if the
// median total exceeds the target. `bench_planning OUT_DIR` also writes trajectory.json,
// trajectory.csv and preview.png of the plan into OUT_DIR.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <vector>

#include "fettle/planning/io.hpp"

#include "synthetic_part.hpp"

namespace {

double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  using namespace fettle::planning;
  auto scene = testing::make_scene(0.5);
  const PlannerSettings settings;
  constexpr int runs = 15;
  std::size_t total_points = 0;
  std::printf("%-20s %10s %10s %12s\n", "region", "points", "poses", "median_ms");
  for (const auto& in : scene.inputs) {
    std::vector<double> t;
    std::size_t poses = 0;
    for (int r = 0; r < runs; ++r) {
      const auto t0 = std::chrono::steady_clock::now();
      auto plan = plan_region(in, settings);
      t.push_back(ms_since(t0));
      if (!plan) {
        std::fprintf(stderr, "planning failed: %s\n", plan.error().message.c_str());
        return 2;
      }
      poses = plan->points.size();
    }
    total_points += in.excess_points_part.size();
    std::printf("%-20s %10zu %10zu %12.2f\n", in.region->name.c_str(), in.excess_points_part.size(), poses, median(t));
  }
  std::vector<double> t;
  std::size_t poses = 0;
  for (int r = 0; r < runs; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    auto traj = plan_part("pump-body", scene.inputs, settings);
    t.push_back(ms_since(t0));
    if (!traj) {
      std::fprintf(stderr, "planning failed: %s\n", traj.error().message.c_str());
      return 2;
    }
    poses = traj->points.size();
    if (r == 0 && argc > 1) {
      std::vector<PreviewPoint> cloud;
      for (const auto& in : scene.inputs)
        for (const auto& x : in.excess_points_part) cloud.push_back({in.T_base_part * x, in.template_sdf(x)});
      if (auto st = write_outputs(argv[1], *traj, cloud); !st) {
        std::fprintf(stderr, "%s\n", st.error().message.c_str());
        return 2;
      }
    }
  }
  const double total = median(t);
  std::printf("%-20s %10zu %10zu %12.2f   (plan + order + validate, target <= 100 ms)\n", "all regions", total_points,
              poses, total);
  return total <= 100.0 ? 0 : 1;
}
