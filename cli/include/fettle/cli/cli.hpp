#pragma once
// What the three programs (fettle, fettled, fettle-sim) share on the command line.
//
// Subcommands register themselves: each command file of a program defines
//   FETTLE_COMMAND("config", [](CLI::App& app, const fettle::cli::Common&) { ... });
// (see fettle::cli::Command and daemon/cli/config_command.cpp), so adding a command
// never edits main().
#include <algorithm>
#include <exception>
#include <functional>
#include <iostream>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <CLI/CLI.hpp>

#include "fettle/core/error.hpp"
#include "fettle/core/exit_codes.hpp"
#include "fettle/core/log.hpp"

namespace fettle::cli {

/// "ADDRESS:PORT" given to `option`: the address and the port, `min_port` (0: any free port) to
/// 65535; a UserError naming the option and the text otherwise (`example` shows the form).
inline std::pair<std::string, int> parse_address_port(const std::string& text, const std::string& option, int min_port,
                                                      const std::string& example) {
  const auto colon = text.rfind(':');
  if (colon == std::string::npos)
    throw UserError(option + " '" + text + "': expected ADDRESS:PORT, e.g. " + example);
  int port = -1;
  try {
    std::size_t used = 0;
    port = std::stoi(text.substr(colon + 1), &used);
    if (used != text.size() - colon - 1) port = -1;
  } catch (const std::exception&) {
    port = -1;
  }
  if (port < min_port || port > 65535)
    throw UserError(option + " '" + text + "': port must be " +
                    (min_port == 0 ? std::string("0 (any free port)") : std::to_string(min_port)) + " to 65535");
  return {text.substr(0, colon), port};
}

/// Options every command sees.
struct Common {
  std::optional<std::string> log_level;  ///< --log-level, overrides config levels
};

/// A registered command: `setup` adds its subcommand(s) to the program and returns, for
/// each subcommand it added, the function to run when that subcommand is chosen.
struct Command {
  using Runner = std::function<int()>;
  using Setup = std::function<std::vector<std::pair<CLI::App*, Runner>>(CLI::App& app, const Common& common)>;
  std::string name;
  Setup setup;
};

inline std::vector<Command>& registry() {
  static std::vector<Command> commands;
  return commands;
}

inline bool register_command(std::string name, Command::Setup setup) {
  registry().push_back(Command{std::move(name), std::move(setup)});
  return true;
}

/// Adds --log-level (overrides every component's level from the config).
inline CLI::Option* add_log_level(CLI::App& app, std::optional<std::string>& level) {
  return app
      .add_option_function<std::string>(
          "--log-level", [&level](const std::string& v) { level = v; },
          "Log level for every component: trace, debug, info, warn, error, critical, off")
      ->check(CLI::IsMember(log::level_names()));
}

/// Parses the command line and runs `body`, mapping failures to exit codes:
/// 0 ok, 1 failure the user can fix, 2 usage, 3 device, 4 internal (a bug).
inline int run(CLI::App& app, int argc, char** argv, const std::function<int()>& body) {
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForAllHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForVersion& e) {
    return app.exit(e);
  } catch (const CLI::ParseError& e) {
    (void)app.exit(e);
    return exit_code::usage;
  }
  try {
    return body();
  } catch (const UserError& e) {
    std::cerr << app.get_name() << ": " << e.what() << "\n";
    return exit_code::failure;
  } catch (const DeviceError& e) {
    std::cerr << app.get_name() << ": " << e.what() << "\n";
    return exit_code::device;
  } catch (const std::exception& e) {
    std::cerr << app.get_name() << ": internal error: " << e.what() << " (please report this)\n";
    return exit_code::internal;
  }
}

/// main() of a program made of registered commands.
inline int main_with_commands(const std::string& name, const std::string& description, const std::string& version,
                              int argc, char** argv) {
  CLI::App app{description, name};
  app.require_subcommand(1);
  app.set_version_flag("--version", name + " " + version);
  Common common;
  add_log_level(app, common.log_level);
  auto commands = registry();
  std::sort(commands.begin(), commands.end(), [](const Command& a, const Command& b) { return a.name < b.name; });
  std::vector<std::pair<CLI::App*, Command::Runner>> runners;
  for (const auto& c : commands) {
    auto added = c.setup(app, common);
    runners.insert(runners.end(), added.begin(), added.end());
  }
  return run(app, argc, argv, [&]() -> int {
    log::Options log_options;
    log_options.program = name;
    log_options.override_level = common.log_level;
    log::init(log_options);
    for (const auto& [sub, runner] : runners)
      if (sub->parsed()) return runner();
    std::cerr << name << ": choose a subcommand (see --help)\n";
    return exit_code::usage;
  });
}

}  // namespace fettle::cli

#define FETTLE_CLI_CONCAT_(a, b) a##b
#define FETTLE_CLI_CONCAT(a, b) FETTLE_CLI_CONCAT_(a, b)
/// Registers a command of the program this file is linked into.
#define FETTLE_COMMAND(name, ...)                                           \
  static const bool FETTLE_CLI_CONCAT(fettle_command_registered_, __LINE__) = \
      ::fettle::cli::register_command(name, __VA_ARGS__)
