// fettle tool changed NAME [--socket PATH | --config FILE]: tells fettled a new wheel is fitted.
// fettled predicts each wheel's wear from the iron it removed and stops with tool.worn before
// a casting that would wear it past its [[tools]] max_wear_mm (docs/compensation.md); after the
// change this starts the wheel's wear from zero (the wheel kind's learned rate is kept).
#include <filesystem>
#include <iostream>
#include <memory>
#include <optional>
#include <string>

#include "fettle/cli/cli.hpp"
#include "fettle/daemon/control.hpp"

namespace {

using fettle::daemon::control::json;

struct Args {
  std::string tool;
  std::optional<std::filesystem::path> socket;
  std::optional<std::filesystem::path> config;
  int timeout_ms = 5000;
};

/// Changing a wheel is maintenance: the command switches maintenance mode on for it when it is
/// off (fettled refuses that during a production cycle) and off again afterwards.
int changed(const Args& a) {
  namespace control = fettle::daemon::control;
  const auto socket = control::socket_for_cli(a.socket, a.config);
  const std::chrono::milliseconds timeout{a.timeout_ms};
  const bool was_on = control::cli_request(socket, json{{"cmd", "maintenance"}}, timeout).value("maintenance", false);
  if (!was_on) (void)control::cli_request(socket, json{{"cmd", "maintenance"}, {"on", true}}, timeout);
  try {
    (void)control::cli_request(socket, json{{"cmd", "tool_changed"}, {"tool", a.tool}}, timeout);
  } catch (...) {
    if (!was_on) (void)control::cli_request(socket, json{{"cmd", "maintenance"}, {"on", false}}, timeout);
    throw;
  }
  if (!was_on) (void)control::cli_request(socket, json{{"cmd", "maintenance"}, {"on", false}}, timeout);
  std::cout << "fettled: a new wheel '" << a.tool << "' is fitted; its predicted wear starts from zero\n";
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("tool", [](CLI::App& app, const fettle::cli::Common&) {
  auto args = std::make_shared<Args>();
  auto* tool = app.add_subcommand("tool", "The grinding wheels (wear, changes)");
  tool->require_subcommand(1);
  auto* cmd = tool->add_subcommand(
      "changed", "Tell fettled a new wheel is fitted (after a tool.worn fault; in maintenance mode for the change)");
  cmd->add_option("name", args->tool, "The tool's name in the recipe's [[tools]]")->required();
  auto* socket = cmd->add_option("--socket", args->socket, "Control socket (default: /run/fettle/fettled.sock)");
  cmd->add_option("--config", args->config, "Cell file whose [control] socket to use")->excludes(socket);
  cmd->add_option("--timeout-ms", args->timeout_ms, "Give up after this long")->check(CLI::Range(1, 600000));
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [args] { return changed(*args); }}};
});

}  // namespace
