// fettle config check FILE
#include <filesystem>
#include <iostream>
#include <memory>
#include <string>

#include "fettle/config/load.hpp"
#include "fettle/cli/cli.hpp"

namespace {

int config_check(const std::filesystem::path& file, const std::string& kind) {
  const auto k = kind == "cell"   ? fettle::config::FileKind::cell
                 : kind == "part" ? fettle::config::FileKind::part
                                  : fettle::config::FileKind::automatic;
  const auto problems = fettle::config::check_file(file, k);
  for (const auto& d : problems) std::cerr << d.to_string() << "\n";
  if (!problems.empty()) {
    std::cerr << file.string() << ": " << problems.size() << (problems.size() == 1 ? " problem" : " problems")
              << " found\n";
    return fettle::exit_code::failure;
  }
  std::cout << file.string() << ": OK\n";
  return fettle::exit_code::ok;
}

struct Args {
  std::filesystem::path file;
  std::string kind = "auto";
};

FETTLE_COMMAND("config", [](CLI::App& app, const fettle::cli::Common&) {
  auto args = std::make_shared<Args>();
  auto* config = app.add_subcommand("config", "Configuration files");
  config->require_subcommand(1);
  auto* check = config->add_subcommand("check", "Validate a cell or part file: exit 0 if valid, 1 with the problems");
  check->add_option("FILE", args->file, "Cell (.toml) or part recipe file")->required();
  check->add_option("--kind", args->kind, "File kind (auto: a file with a [part] table is a part recipe)")
      ->check(CLI::IsMember({"auto", "cell", "part"}));
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{
      {check, [args] { return config_check(args->file, args->kind); }}};
});

}  // namespace
