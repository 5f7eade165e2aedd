// fettle cycles [--limit N | --last] [--socket PATH | --config FILE] [--json]:
// the newest cycles fettled knows, from its control socket.
#include <algorithm>
#include <filesystem>
#include <iostream>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "fettle/cli/cli.hpp"
#include "fettle/daemon/control.hpp"

namespace {

using fettle::daemon::control::display_text;
using fettle::daemon::control::json;

/// Columns: these first when present, then every other scalar field in order of appearance.
std::vector<std::string> columns_of(const json& cycles) {
  static const std::vector<std::string> preferred{"id", "cycle_id", "started", "part", "result", "duration_s", "fault"};
  std::vector<std::string> cols;
  auto add = [&](const std::string& k) {
    if (std::find(cols.begin(), cols.end(), k) == cols.end()) cols.push_back(k);
  };
  for (const auto& p : preferred)
    for (const auto& c : cycles)
      if (c.is_object() && c.contains(p)) {
        add(p);
        break;
      }
  for (const auto& c : cycles)
    if (c.is_object())
      for (const auto& [k, v] : c.items())
        if (!v.is_structured() || k == "fault") add(k);
  return cols;
}

std::string cell(const json& c, const std::string& key) {
  if (!c.is_object() || !c.contains(key)) return "-";
  const json& v = c[key];
  if (key == "fault" && v.is_object()) return display_text(v.value("code", json{}));
  return display_text(v);
}

void print_table(const json& cycles) {
  if (!cycles.is_array() || cycles.empty()) {
    std::cout << "no cycles recorded yet\n";
    return;
  }
  const auto cols = columns_of(cycles);
  std::vector<std::size_t> width(cols.size());
  for (std::size_t i = 0; i < cols.size(); ++i) {
    width[i] = cols[i].size();
    for (const auto& c : cycles) width[i] = std::max(width[i], cell(c, cols[i]).size());
  }
  auto print_row = [&](const std::vector<std::string>& cells) {
    std::string line;
    for (std::size_t i = 0; i < cells.size(); ++i) {
      line += cells[i];
      if (i + 1 < cells.size()) line += std::string(width[i] - cells[i].size() + 2, ' ');
    }
    std::cout << line << "\n";
  };
  print_row(cols);
  for (const auto& c : cycles) {
    std::vector<std::string> cells;
    for (const auto& k : cols) cells.push_back(cell(c, k));
    print_row(cells);
  }
}

void print_one(const json& cycle) {
  if (cycle.is_null()) {
    std::cout << "no cycle finished yet\n";
    return;
  }
  for (const auto& [k, v] : cycle.items()) {
    std::cout << k << std::string(k.size() < 14 ? 14 - k.size() : 1, ' ')
              << (v.is_structured() ? v.dump() : display_text(v)) << "\n";
  }
}

struct Args {
  std::optional<std::filesystem::path> socket;
  std::optional<std::filesystem::path> config;
  bool json_output = false;
  bool last = false;
  int limit = 20;
  int timeout_ms = 5000;
};

int cycles(const Args& a) {
  namespace control = fettle::daemon::control;
  const auto socket = control::socket_for_cli(a.socket, a.config);
  const json request = a.last ? json{{"cmd", "last_cycle"}} : json{{"cmd", "cycles"}, {"limit", a.limit}};
  const json r = control::cli_request(socket, request, std::chrono::milliseconds{a.timeout_ms});
  const char* key = a.last ? "cycle" : "cycles";
  const json& body = r.contains(key) ? r[key] : json{};
  if (a.json_output)
    std::cout << body.dump() << "\n";
  else if (a.last)
    print_one(body);
  else
    print_table(body);
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("cycles", [](CLI::App& app, const fettle::cli::Common&) {
  auto args = std::make_shared<Args>();
  auto* cmd = app.add_subcommand("cycles", "List the newest cycles (id, result, duration) from fettled's control socket");
  auto* socket = cmd->add_option("--socket", args->socket, "Control socket (default: /run/fettle/fettled.sock)");
  cmd->add_option("--config", args->config, "Cell file whose [control] socket to use")->excludes(socket);
  auto* limit = cmd->add_option("--limit,-n", args->limit, "How many cycles, newest first")->check(CLI::Range(1, 10000));
  cmd->add_flag("--last", args->last, "Only the last finished cycle, with all its fields")->excludes(limit);
  cmd->add_flag("--json", args->json_output, "Print the cycles as JSON (an array; an object or null with --last)");
  cmd->add_option("--timeout-ms", args->timeout_ms, "Give up after this long")->check(CLI::Range(1, 600000));
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [args] { return cycles(*args); }}};
});

}  // namespace
