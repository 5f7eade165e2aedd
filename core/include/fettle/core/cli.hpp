#pragma once
// What the three programs (fettle, fettled, fettle-sim) share on the command line.
#include <exception>
#include <functional>
#include <iostream>
#include <optional>
#include <string>

#include <CLI/CLI.hpp>

#include "fettle/core/error.hpp"
#include "fettle/core/exit_codes.hpp"
#include "fettle/core/log.hpp"

namespace fettle::cli {

/// Adds --log-level (overrides every component's level from the config).
inline CLI::Option* add_log_level(CLI::App& app, std::optional<std::string>& level) {
  return app
      .add_option_function<std::string>(
          "--log-level", [&level](const std::string& v) { level = v; },
          "Log level for every component: trace, debug, info, warn, error, critical, off")
      ->check(CLI::IsMember(log::level_names()));
}

/// Parses the command line and runs the chosen command, mapping failures to exit codes:
/// 0 ok, 1 failure the user can fix, 2 usage, 3 device, 4 internal (a bug).
inline int run(CLI::App& app, int argc, char** argv, const std::function<int()>& body) {
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForAllHelp& e) {
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

}  // namespace fettle::cli
