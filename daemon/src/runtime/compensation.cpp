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
  cell_bias.add_wear_measurements(m, c.tool_wear_mm);
  const auto predicted = cell_bias.tool_wear(c.recipe->recipe);
  for (const auto& [name, w] : m.tools) {
    const auto cmd = c.tool_wear_mm.find(name);
    const auto now = predicted.find(name);
    log->info("cycle {}: compensation: wheel '{}' cut {:.3f} +- {:.3f} mm inside its commanded radius ({} points; "
              "planned worn {:.3f} mm); its wear is now predicted {:.3f} mm ({:.3f} to {:.3f})",
              c.summary.id, name, w.wear_mm, w.std_mm, w.points, cmd == c.tool_wear_mm.end() ? 0.0 : cmd->second,
              now == predicted.end() ? 0.0 : now->second.expected_mm, now == predicted.end() ? 0.0 : now->second.least_mm,
              now == predicted.end() ? 0.0 : now->second.most_mm);
  }
  if (auto st = process::save_cell_bias(process::cell_bias_file(cell), cell_bias); !st)
    c.warnings.push_back("compensation: " + st.error().message);
}

void Runtime::Impl::count_removal(Cycle& c, const ProcessOutput* planned, bool first_grind) {
  if (!cell.compensation.enabled || !c.recipe) return;
  if (planned != nullptr) {
    const auto more = process::removed_cm3(*c.recipe, *planned);
    for (const auto& [name, cm3] : more) c.removed_seen_cm3[name] += cm3;
  }
  std::map<std::string, double> delta;
  for (const auto& [name, cm3] : c.removed_seen_cm3) {
    delta[name] = std::max(0.0, cm3 - c.removed_counted_cm3[name]);
    c.removed_counted_cm3[name] = std::max(cm3, c.removed_counted_cm3[name]);
  }
  cell_bias.add_removed(delta);
  if (first_grind) last_removed_cm3[c.recipe_id] = delta;
  if (auto st = process::save_cell_bias(process::cell_bias_file(cell), cell_bias); !st)
    c.warnings.push_back("compensation: " + st.error().message);
}

std::optional<Fault> Runtime::Impl::worn_wheels(const Cycle& c) const {
  if (!cell.compensation.enabled || !c.recipe || c.dry) return std::nullopt;
  const auto& recipe = c.recipe->recipe;
  const auto last = last_removed_cm3.find(c.recipe_id);
  const auto worn = cell_bias.worn_out(recipe, last == last_removed_cm3.end() ? std::map<std::string, double>{} : last->second);
  if (worn.empty()) return std::nullopt;
  std::string what;
  for (const auto& w : worn) what += fmt::format("{}wheel '{}' is {}", what.empty() ? "" : ", ", w.tool, w.why);
  return Fault{FaultCode::tool_worn,
               what + ": fit a new wheel and run `fettle tool changed " + worn.front().tool +
                   "` in maintenance mode",
               "tools"};
}

Result<json> Runtime::Impl::tool_changed(const std::string& name) {
  if (cycle) return Error{"fettled.busy", "cycle " + cycle->summary.id + " is running; change the wheel when it ends"};
  bool known = false;
  std::string names;
  for (const auto& [id, r] : recipes)
    for (const auto& t : r->recipe.tools) {
      known = known || t.name == name;
      names += (names.empty() ? "" : ", ") + t.name;
    }
  if (!known) return Error{"fettled.unknown_tool", "no recipe of " + cell.source.string() + " has a tool '" + name + "' (tools: " + names + ")"};
  cell_bias.change_tool(name);
  log->info("compensation: a new wheel '{}' is fitted; its predicted wear starts from zero", name);
  if (auto st = process::save_cell_bias(process::cell_bias_file(cell), cell_bias); !st) return st.error();
  return json{{"tool", name}, {"wear_mm", 0.0}};
}

}  // namespace fettle::daemon
