// fettle: the operator's and integrator's command-line tool.
#include <filesystem>
#include <iostream>
#include <optional>
#include <string>

#include "fettle/config/load.hpp"
#include "fettle/core/cli.hpp"

namespace {

int config_check(const std::filesystem::path& file, fettle::config::FileKind kind) {
  const auto problems = fettle::config::check_file(file, kind);
  for (const auto& d : problems) std::cerr << d.to_string() << "\n";
  if (!problems.empty()) {
    std::cerr << file.string() << ": " << problems.size() << (problems.size() == 1 ? " problem" : " problems")
              << " found\n";
    return fettle::exit_code::failure;
  }
  std::cout << file.string() << ": OK\n";
  return fettle::exit_code::ok;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"fettle - tools for a Fettle fettling cell (configuration, inspection, calibration)", "fettle"};
  app.require_subcommand(1);
  app.set_version_flag("--version", std::string("fettle ") + FETTLE_VERSION);
  std::optional<std::string> log_level;
  fettle::cli::add_log_level(app, log_level);

  auto* config = app.add_subcommand("config", "Configuration files");
  config->require_subcommand(1);
  auto* check = config->add_subcommand("check", "Validate a cell or part file: exit 0 if valid, 1 with the problems");
  std::filesystem::path file;
  std::string kind = "auto";
  check->add_option("FILE", file, "Cell (.toml) or part recipe file")->required();
  check->add_option("--kind", kind, "File kind (auto: a file with a [part] table is a part recipe)")
      ->check(CLI::IsMember({"auto", "cell", "part"}));

  return fettle::cli::run(app, argc, argv, [&]() -> int {
    fettle::log::Options log_options;
    log_options.program = "fettle";
    log_options.override_level = log_level;
    fettle::log::init(log_options);
    if (check->parsed()) {
      const auto k = kind == "cell"   ? fettle::config::FileKind::cell
                     : kind == "part" ? fettle::config::FileKind::part
                                      : fettle::config::FileKind::automatic;
      return config_check(file, k);
    }
    return fettle::exit_code::usage;
  });
}
