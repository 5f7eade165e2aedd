// The cell learns its own bias (fettle/process/compensation.hpp, docs/compensation.md): fettled
// keeps the estimate in [compensation] state_file across restarts, commands every path shifted
// by minus it, and moves it after each cycle's first verification. A new calibration (its
// sha256) or other tools start it again from zero. Test: Fettled.D (the estimate in report.json
// and the state file), tests/process/test_compensation.cpp (the measurement).
#include <fmt/format.h>

#include "runtime_impl.hpp"

namespace fettle::daemon {

std::string Runtime::Impl::bias_identity_calibration() const {
  return calibration ? config::calibration_identity(*calibration).sha256 : std::string("none");
}

std::string Runtime::Impl::bias_identity_tools() const {
  std::string ids;
  for (const auto& [id, recipe] : recipes) ids += std::to_string(id) + ":" + process::tools_identity(recipe->recipe) + ";";
  return ids;
}

void Runtime::Impl::load_cell_bias() {
  if (!cell.compensation.enabled) return;
  const auto file = process::cell_bias_file(cell);
  auto loaded = process::load_cell_bias(file);
  if (!loaded) {
    log->warn("compensation: {}; the learned bias starts from zero", loaded.error().message);
    loaded = process::CellBias{};
  }
  cell_bias = *loaded;
  const auto cal = bias_identity_calibration(), tools = bias_identity_tools();
  if (cell_bias.updates > 0 && (cell_bias.calibration_id != cal || cell_bias.tools_id != tools)) {
    log->info("compensation: the {} changed since the bias {} was learned: it starts from zero",
              cell_bias.calibration_id != cal ? "calibration" : "tools", cell_bias.describe());
    cell_bias.reset();
  } else if (cell_bias.updates > 0) {
    log->info("compensation: the cell's learned bias {} ({})", cell_bias.describe(), file.string());
  }
  cell_bias.calibration_id = cal;
  cell_bias.tools_id = tools;
}

void Runtime::Impl::learn_bias(Cycle& c) {
  if (!c.cut_offset) return;
  if (!*c.cut_offset) {
    log->info("cycle {}: compensation: {}; the learned bias stays {}", c.summary.id, c.cut_offset->error().message,
              cell_bias.describe());
    return;
  }
  const auto& m = c.cut_offset->value();
  const Vec3 step = cell_bias.update(m, cell.compensation);
  log->info("cycle {}: compensation: the tool cut {} from where it was told; the learned bias moves by "
            "({:.3f}, {:.3f}, {:.3f}) to {}",
            c.summary.id, m.describe(), step.x(), step.y(), step.z(), cell_bias.describe());
  if (auto st = process::save_cell_bias(process::cell_bias_file(cell), cell_bias); !st)
    c.warnings.push_back("compensation: " + st.error().message);
}

}  // namespace fettle::daemon
