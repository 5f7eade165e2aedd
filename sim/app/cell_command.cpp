// fettle-sim cell --config config/cell.sim.toml [--castings 5]: the whole simulated cell in one
// process on loopback (PLC, 3D camera, robot, spindle via socketcand) around one casting on the
// fixture; castings are fed automatically with a cycle request each (fettle/sim/cell.hpp).
//
// While it runs, lines on stdin inject faults or drive it by hand (CellSim::inject), e.g.
// `camera drop 3`, `robot nak TRAJ ENVELOPE`, `spindle fault overcurrent`, `plc drop`,
// `part empty`, `part request`, `auto off`, `quit`.
#include <poll.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <memory>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>

#include <nlohmann/json.hpp>

#include "fettle/config/load.hpp"
#include "fettle/core/atomic_file.hpp"
#include "fettle/cli/cli.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/sim/cell.hpp"
#include "sim_common.hpp"

namespace {

std::atomic<bool> g_stop{false};
extern "C" void on_cell_signal(int /*sig*/) { g_stop = true; }

struct Args {
  std::filesystem::path config;
  int castings = 5;
  std::uint64_t first_seed = 1;
  std::filesystem::path ports_file;
  bool ephemeral = false;
  bool no_camera = false;
  std::string resolution = "1032x772";
  double speedup = 10.0;
  bool manual = false;
  bool exit_when_done = false;
  bool ideal = false;
  fettle::sim::app::ErrorOptions errors;
};

int run_cell(const Args& a) {
  auto log = fettle::log::get("sim.cell");
  fettle::sim::CellSimOptions o;
  o.cell = fettle::config::load_cell(a.config);
  o.castings = a.castings;
  o.first_seed = a.first_seed;
  o.camera = !a.no_camera;
  o.robot_speedup = a.speedup;
  o.auto_start = !a.manual;
  o.noise = !a.ideal;
  o.errors = fettle::sim::app::error_budget(a.errors);
  o.cell_seed = a.errors.cell_seed;
  if (a.ephemeral) o.plc_port = o.robot_port = o.spindle_port = 0;
  std::tie(o.camera_width, o.camera_height) = fettle::sim::app::parse_resolution(a.resolution);
  fettle::sim::CellSim cell(o);
  cell.on_event([](const std::string& line) { std::cout << line << std::endl; });
  cell.start();
  if (!a.ports_file.empty()) {
    const nlohmann::json ports{{"plc", cell.plc_port()}, {"robot", cell.robot_port()}, {"spindle", cell.spindle_port()}};
    if (auto st = fettle::write_file_atomic(a.ports_file, ports.dump() + "\n"); !st)
      throw fettle::UserError("--ports-file: " + st.error().message);
  }
  std::signal(SIGINT, on_cell_signal);
  std::signal(SIGTERM, on_cell_signal);
  std::cout << "ready" << std::endl;
  std::string buffer;
  bool stdin_open = true;
  while (!g_stop) {
    if (a.exit_when_done && cell.done()) {
      std::cout << "all " << a.castings << " castings done" << std::endl;
      break;
    }
    if (!stdin_open) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
      continue;
    }
    pollfd p{STDIN_FILENO, POLLIN, 0};
    if (::poll(&p, 1, 50) <= 0 || (p.revents & (POLLIN | POLLHUP)) == 0) continue;
    char chunk[512];
    const auto n = ::read(STDIN_FILENO, chunk, sizeof chunk);
    if (n <= 0) {
      stdin_open = false;
      continue;
    }
    buffer.append(chunk, static_cast<std::size_t>(n));
    for (auto nl = buffer.find('\n'); nl != std::string::npos; nl = buffer.find('\n')) {
      const std::string line = buffer.substr(0, nl);
      buffer.erase(0, nl + 1);
      if (line == "quit") g_stop = true;
      else if (!line.empty())
        if (auto st = cell.inject(line); !st) std::cout << "error: " << st.error().message << std::endl;
    }
  }
  cell.stop();
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("cell", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* cmd = app.add_subcommand(
      "cell", "The whole simulated cell (PLC, 3D camera, robot, spindle over socketcand) around one casting");
  cmd->add_option("--config", a->config, "Cell file (ports, slide, calibration, safety, recipes)")
      ->required()
      ->check(CLI::ExistingFile);
  cmd->add_option("--castings", a->castings, "Castings fed automatically, one cycle request each (0 = none)")
      ->capture_default_str();
  cmd->add_option("--first-seed", a->first_seed, "Seed of the first casting (then +1 each)")->capture_default_str();
  cmd->add_option("--ports-file", a->ports_file, "Write {\"plc\",\"robot\",\"spindle\"} ports as JSON here");
  cmd->add_flag("--ephemeral", a->ephemeral, "Bind PLC, robot and socketcand to free ports (see --ports-file)");
  cmd->add_flag("--no-camera", a->no_camera, "No GigE Vision camera (UDP 3956 stays free)");
  cmd->add_option("--resolution", a->resolution, "Camera range map WIDTHxHEIGHT")->capture_default_str();
  cmd->add_option("--speedup", a->speedup, "Robot execution speed-up (1 = real time)")->capture_default_str();
  cmd->add_flag("--manual", a->manual, "No automatic Reset/Start from the PLC");
  cmd->add_flag("--exit-when-done", a->exit_when_done, "Exit once every casting got its result");
  cmd->add_flag("--ideal", a->ideal, "No scanner noise");
  fettle::sim::app::add_error_options(cmd, a->errors);
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a] { return run_cell(*a); }}};
});

}  // namespace
