// fettle robot conformance: checks a robot controller program against docs/robot-protocol.md.
//   fettle robot conformance --address 192.168.20.40:30100 --cell-id cell-01
//   fettle robot conformance --config cell.toml --motion     (robot in its offline simulator)
// One line per rule (PASS / FAIL / SKIP, its section of the document, what the robot must do),
// with what was seen under a failure. Exit code 0 when no rule fails, 1 when one does, 3 when
// the robot cannot be reached at all.
#include <filesystem>
#include <iostream>
#include <memory>
#include <string>
#include <tuple>
#include <vector>

#include "fettle/cli/cli.hpp"
#include "fettle/config/load.hpp"
#include "fettle/core/error.hpp"
#include "fettle/drivers/robot_conformance.hpp"

namespace {

namespace robot = fettle::drivers::robot;

struct Args {
  std::filesystem::path config;
  std::string address;  ///< HOST:PORT
  std::string cell_id;
  bool motion = false;
  std::vector<double> point_mm;
  double speed_mm_s = 20.0;
  int timeout_ms = 0;
};

robot::ConformanceOptions options_from(const Args& a) {
  robot::ConformanceOptions o;
  if (!a.config.empty()) {
    const auto cell = fettle::config::load_cell(a.config);
    o.address = cell.robot.address;
    o.port = cell.robot.port;
    if (!cell.robot.cell_id.empty()) o.cell_id = cell.robot.cell_id;
    o.reply_timeout_ms = cell.robot.reply_timeout_ms;
    // Inside the cell's workspace: its centre, at a quarter of its height above the floor.
    const auto& s = cell.safety;
    o.point_mm = fettle::Vec3((s.workspace_min_mm[0] + s.workspace_max_mm[0]) / 2.0,
                              (s.workspace_min_mm[1] + s.workspace_max_mm[1]) / 2.0,
                              s.workspace_min_mm[2] + (s.workspace_max_mm[2] - s.workspace_min_mm[2]) / 4.0);
  }
  if (!a.address.empty())
    std::tie(o.address, o.port) = fettle::cli::parse_address_port(a.address, "--address", 1, "192.168.20.40:30100");
  if (a.config.empty() && a.address.empty())
    throw fettle::UserError("which robot controller? give --address HOST:PORT (or --config CELL.toml)");
  if (!a.cell_id.empty()) o.cell_id = a.cell_id;
  if (!a.point_mm.empty()) o.point_mm = fettle::Vec3(a.point_mm[0], a.point_mm[1], a.point_mm[2]);
  if (a.timeout_ms > 0) o.reply_timeout_ms = a.timeout_ms;
  o.motion = a.motion;
  o.speed_mm_s = a.speed_mm_s;
  return o;
}

int conformance(const Args& a) {
  const auto o = options_from(a);
  std::cout << "robot controller at " << o.address << ":" << o.port << ", cell id " << o.cell_id
            << (o.motion ? ", with motion rules" : ", motion rules skipped (--motion runs them)") << "\n";
  int failed = 0, skipped = 0, unreachable = 0;
  const auto results = robot::run_conformance(o, [&](const robot::ConformanceRule& r) {
    std::cout << robot::name(r.outcome) << "  " << r.id << " (section " << r.section << "): " << r.rule << "\n";
    if (r.outcome == robot::ConformanceRule::Outcome::fail) {
      ++failed;
      std::cout << "      " << r.detail << "\n";
      if (r.detail.starts_with("cannot connect") || r.detail.starts_with("no TCP connection")) ++unreachable;
    }
    if (r.outcome == robot::ConformanceRule::Outcome::skipped) ++skipped;
    std::cout.flush();
  });
  const auto ran = static_cast<int>(results.size()) - skipped;
  std::cout << ran - failed << " of " << ran << " rules pass";
  if (skipped > 0) std::cout << ", " << skipped << " skipped";
  std::cout << " (docs/robot-protocol.md)\n";
  if (ran > 0 && unreachable == ran) return fettle::exit_code::device;
  return failed == 0 ? fettle::exit_code::ok : fettle::exit_code::failure;
}

FETTLE_COMMAND("robot", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* robot_cmd = app.add_subcommand("robot", "The robot controller (commissioning)");
  robot_cmd->require_subcommand(1);
  auto* conf = robot_cmd->add_subcommand(
      "conformance", "Check a robot controller program against docs/robot-protocol.md, rule by rule");
  conf->add_option("--address", a->address, "The controller's HOST:PORT");
  conf->add_option("--config", a->config, "Cell file: its [robot] address, port, cell_id, reply_timeout_ms")
      ->check(CLI::ExistingFile);
  conf->add_option("--cell-id", a->cell_id, "Cell id sent in HELLO (default: the cell file's, else 'conformance')");
  conf->add_flag("--motion", a->motion,
                 "Also run the rules that make the robot move (3 points, 10 mm, spindle off): use the vendor's "
                 "offline simulator or a safe mode");
  conf->add_option("--point-mm", a->point_mm, "Where those points lie, X Y Z in the base frame (mm)")->expected(3);
  conf->add_option("--speed-mm-s", a->speed_mm_s, "Their speed")->check(CLI::Range(0.001, 1000.0))->capture_default_str();
  conf->add_option("--timeout-ms", a->timeout_ms, "Wait for each expected line (default: reply_timeout_ms, 2000)")
      ->check(CLI::PositiveNumber);
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{conf, [a] { return conformance(*a); }}};
});

}  // namespace
