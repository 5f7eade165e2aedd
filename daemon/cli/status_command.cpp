// fettle status [--socket PATH | --config FILE] [--json]: asks fettled over its control socket.
#include <cmath>
#include <filesystem>
#include <iostream>
#include <memory>
#include <optional>
#include <sstream>
#include <string>

#include "fettle/cli/cli.hpp"
#include "fettle/daemon/control.hpp"

namespace {

using fettle::daemon::control::json;

std::string text(const json& v) { return fettle::daemon::control::display_text(v); }

std::string duration_text(double s) {
  if (!std::isfinite(s) || s < 0) return "-";
  const auto total = static_cast<long long>(s);
  std::ostringstream o;
  if (total >= 86400) o << total / 86400 << " d ";
  if (total >= 3600) o << (total % 86400) / 3600 << " h ";
  if (total >= 60) o << (total % 3600) / 60 << " min ";
  o << total % 60 << " s";
  return o.str();
}

void print_status(const json& r, const std::filesystem::path& socket) {
  auto row = [](const std::string& key, const std::string& value) {
    std::cout << key << std::string(key.size() < 14 ? 14 - key.size() : 1, ' ') << value << "\n";
  };
  std::string state = r.contains("state") ? text(r["state"]) : "?";
  if (r.contains("state_code")) state += " (code " + text(r["state_code"]) + ")";
  row("state", state);
  row("maintenance", r.value("maintenance", false) ? "on" : "off");
  if (r.contains("fault")) {
    const json& f = r["fault"];
    if (f.is_object() && f.contains("id"))
      row("fault", text(f["id"]) + " (code " + text(f.value("code", json{})) + "): " + text(f.value("message", json{})));
    else if (f.is_object())
      row("fault", text(f.value("code", json{})) + ": " + text(f.value("message", json{})));
    else
      row("fault", f.is_null() ? "none" : text(f));
  }
  if (r.contains("cycle_id")) row("cycle", text(r["cycle_id"]));
  if (r.contains("cycles_total")) row("cycles", text(r["cycles_total"]));
  if (r.contains("last_result")) row("last result", text(r["last_result"]));
  if (r.contains("uptime_s") && r["uptime_s"].is_number()) row("uptime", duration_text(r["uptime_s"].get<double>()));
  if (r.contains("version")) row("version", text(r["version"]));
  for (const auto& [k, v] : r.items()) {
    if (k == "ok" || k == "id" || k == "state" || k == "state_code" || k == "maintenance" || k == "fault" ||
        k == "cycle_id" || k == "cycles_total" || k == "last_result" || k == "uptime_s" || k == "version")
      continue;
    row(k, text(v));
  }
  row("socket", socket.string());
}

struct Args {
  std::optional<std::filesystem::path> socket;
  std::optional<std::filesystem::path> config;
  bool json_output = false;
  int timeout_ms = 5000;
};

int status(const Args& a) {
  const auto socket = fettle::daemon::control::socket_for_cli(a.socket, a.config);
  const json r = fettle::daemon::control::cli_request(socket, json{{"cmd", "status"}},
                                                      std::chrono::milliseconds{a.timeout_ms});
  if (a.json_output)
    std::cout << r.dump() << "\n";
  else
    print_status(r, socket);
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("status", [](CLI::App& app, const fettle::cli::Common&) {
  auto args = std::make_shared<Args>();
  auto* cmd = app.add_subcommand(
      "status", "Show fettled's state (PackML state, maintenance mode, fault, cycles) from its control socket");
  auto* socket = cmd->add_option("--socket", args->socket, "Control socket (default: /run/fettle/fettled.sock)");
  cmd->add_option("--config", args->config, "Cell file whose [control] socket to use")->excludes(socket);
  cmd->add_flag("--json", args->json_output, "Print the daemon's reply as one JSON object (for scripts)");
  cmd->add_option("--timeout-ms", args->timeout_ms, "Give up after this long")->check(CLI::Range(1, 600000));
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [args] { return status(*args); }}};
});

}  // namespace
