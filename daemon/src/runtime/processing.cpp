// The default Processing (processing.hpp): fettle::process's pipeline.
#include "fettle/daemon/processing.hpp"

namespace fettle::daemon {

Processing Processing::pipeline() {
  Processing p;
  p.load_recipe = [](const std::filesystem::path& part_file) {
    return std::make_shared<const process::LoadedRecipe>(process::load_recipe(part_file));
  };
  p.process = [](const process::LoadedRecipe& recipe, const config::CellConfig& cell,
                 const std::vector<process::View>& views, const process::ProcessOptions& options) {
    return process::process(recipe, cell, views, options);
  };
  p.verify = [](const process::LoadedRecipe& recipe, const config::CellConfig& cell,
                const std::vector<process::View>& rescan, const std::vector<Trajectory>& ground,
                const process::VerifyOptions& options) { return process::verify(recipe, cell, rescan, ground, options);
  };
  return p;
}

}  // namespace fettle::daemon
