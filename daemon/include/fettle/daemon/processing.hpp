#pragma once
// What the cycle computes, apart from the devices: loading a recipe, processing the views
// (vision and planning) and verifying the re-scan. The runtime calls these through
// RuntimeOptions::processing; the default is fettle::process's pipeline, and tests give
// scripted results so the cycle's fault handling runs in-process in milliseconds
// (tests/daemon/test_cycle_faults.cpp).
#include <filesystem>
#include <functional>
#include <memory>
#include <vector>

#include "fettle/config/cell.hpp"
#include "fettle/core/result.hpp"
#include "fettle/core/trajectory.hpp"
#include "fettle/process/pipeline.hpp"

namespace fettle::daemon {

struct Processing {
  /// Reads a part file and builds its templates. Throws UserError (setup only).
  std::function<std::shared_ptr<const process::LoadedRecipe>(const std::filesystem::path& part_file)> load_recipe;
  /// Vision and planning of one cycle's views (worker pool). Errors as values: vision.* and
  /// planning.* are about the part, others about the cell.
  std::function<Result<process::ProcessOutput>(const process::LoadedRecipe&, const config::CellConfig&,
                                               const std::vector<process::View>&, const process::ProcessOptions&)>
      process;
  /// The verification scan against the template, looking for gouges wherever `ground` went;
  /// judged against the casting's own faces the cycle's first scan found (options.before).
  std::function<Result<process::VerificationResult>(const process::LoadedRecipe&, const config::CellConfig&,
                                                    const std::vector<process::View>& rescan,
                                                    const std::vector<Trajectory>& ground,
                                                    const process::VerifyOptions& options)>
      verify;

  /// fettle::process: process::load_recipe, process::process, process::verify.
  static Processing pipeline();
};

}  // namespace fettle::daemon
