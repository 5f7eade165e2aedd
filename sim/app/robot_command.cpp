// fettle-sim robot --listen ADDRESS:PORT: the simulated robot controller (docs/robot-protocol.md).
#include <csignal>
#include <exception>
#include <tuple>
#include <utility>
#include <iostream>
#include <memory>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>
#include <boost/asio/signal_set.hpp>

#include "fettle/cli/cli.hpp"
#include "fettle/config/load.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/sim/robot.hpp"

namespace {

struct Args {
  std::string listen = "127.0.0.1:30100";
  fettle::sim::RobotSimOptions options;
  std::string nak;    // VERB:CODE
  std::string fault;  // POINT[:CODE]
  std::vector<double> envelope_min, envelope_max;
  std::filesystem::path cell;
  const CLI::Option* listen_given = nullptr;
  const CLI::Option* cell_id_given = nullptr;
  const CLI::Option* max_speed_given = nullptr;
};

int run_robot(Args& a) {
  auto& o = a.options;
  if (!a.cell.empty()) {
    // Where fettled looks for the robot and what its [safety] allows; options given win.
    const auto cell = fettle::config::load_cell(a.cell);
    if (a.listen_given->count() == 0) a.listen = cell.robot.address + ":" + std::to_string(cell.robot.port);
    if (a.cell_id_given->count() == 0) o.expected_cell_id = cell.robot.cell_id;
    if (a.max_speed_given->count() == 0) o.envelope.max_speed_mm_s = cell.safety.max_speed_mm_s;
    const auto& s = cell.safety;
    if (a.envelope_min.empty()) a.envelope_min.assign(s.workspace_min_mm.begin(), s.workspace_min_mm.end());
    if (a.envelope_max.empty()) a.envelope_max.assign(s.workspace_max_mm.begin(), s.workspace_max_mm.end());
  }
  std::tie(o.address, o.port) = fettle::cli::parse_address_port(a.listen, "--listen", 0, "127.0.0.1:0");
  if (!a.nak.empty()) {
    const auto colon = a.nak.find(':');
    if (colon == std::string::npos) throw fettle::UserError("--nak '" + a.nak + "': expected VERB:CODE, e.g. END:CRC");
    o.faults.nak_verb = a.nak.substr(0, colon);
    o.faults.nak_code = a.nak.substr(colon + 1);
  }
  if (!a.fault.empty()) {
    const auto colon = a.fault.find(':');
    try {
      o.faults.fault_at_point = std::stoi(a.fault.substr(0, colon));
    } catch (const std::exception&) {
      throw fettle::UserError("--fault-at '" + a.fault + "': expected POINT[:CODE], e.g. 40:COLLISION");
    }
    if (colon != std::string::npos) o.faults.fault_code = a.fault.substr(colon + 1);
  }
  if (!a.envelope_min.empty()) o.envelope.min_mm = {a.envelope_min[0], a.envelope_min[1], a.envelope_min[2]};
  if (!a.envelope_max.empty()) o.envelope.max_mm = {a.envelope_max[0], a.envelope_max[1], a.envelope_max[2]};
  for (std::size_t i = 0; i < 3; ++i)
    if (o.envelope.min_mm[i] >= o.envelope.max_mm[i])
      throw fettle::UserError("--envelope-max must be greater than --envelope-min on every axis");

  boost::asio::io_context io;
  fettle::sim::RobotSim robot(io, o);
  auto log = fettle::log::get("sim.robot");
  robot.on_executed([log](const fettle::Trajectory& t) {
    log->info("executed {} ({} points)", t.part_id, t.points.size());
  });
  robot.start();
  // A parseable line for scripts and tests: the bound port.
  std::cout << "fettle-sim robot listening on " << o.address << ":" << robot.port() << std::endl;
  boost::asio::signal_set signals(io, SIGINT, SIGTERM);
  signals.async_wait([&](const boost::system::error_code&, int sig) {
    log->info("signal {}: shutting down", sig);
    robot.close();
    io.stop();
  });
  io.run();
  const auto& s = robot.stats();
  std::cout << "fettle-sim robot: " << s.connections << " connections, " << s.trajectories_received
            << " trajectories received, " << s.trajectories_executed << " executed, " << s.naks << " NAKs, "
            << s.closed_for_garbage << " closed for bad input" << std::endl;
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("robot", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* cmd = app.add_subcommand("robot", "Simulated robot controller speaking the line protocol (docs/robot-protocol.md)");
  a->listen_given =
      cmd->add_option("--listen", a->listen, "ADDRESS:PORT to listen on; port 0 picks a free port (printed on stdout)")
          ->capture_default_str();
  cmd->add_option("--cell", a->cell,
                  "Cell file: listen on its [robot] address:port, accept its cell_id, limit to its [safety] workspace "
                  "and max_speed_mm_s (options given explicitly win)")
      ->check(CLI::ExistingFile);
  cmd->add_option("--robot-id", a->options.robot_id, "Robot id sent in the HELLO ACK")->capture_default_str();
  a->cell_id_given = cmd->add_option("--cell-id", a->options.expected_cell_id, "Cell id to accept in HELLO (default: any)");
  cmd->add_option("--speedup", a->options.speedup, "Execution time scale: 1 real time, 100 100x faster, 0 instant")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 1e6));
  cmd->add_option("--envelope-min", a->envelope_min, "Reachable box, lower corner X Y Z (mm)")->expected(3);
  cmd->add_option("--envelope-max", a->envelope_max, "Reachable box, upper corner X Y Z (mm)")->expected(3);
  a->max_speed_given =
      cmd->add_option("--max-speed", a->options.envelope.max_speed_mm_s, "Speed limit (mm/s); faster points are NAKed")
          ->capture_default_str();
  cmd->add_option("--nak", a->nak, "Fault: NAK the first line with VERB with CODE, e.g. END:CRC, TRAJ:BUSY");
  cmd->add_option("--disconnect-at-chunk", a->options.faults.disconnect_at_chunk,
                  "Fault: close the connection when upload chunk K begins (once)");
  cmd->add_option("--fault-at", a->fault, "Fault: FAULT when execution reaches POINT (once), e.g. 40:COLLISION");
  cmd->add_option("--reply-delay-ms", a->options.faults.reply_delay_ms, "Fault: delay every reply by this much");
  cmd->add_flag("--garbage-reply", a->options.faults.garbage_reply, "Fault: send binary garbage as the first reply");
  cmd->add_flag("--ignore-pings", a->options.faults.ignore_pings, "Fault: never answer PING");
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a] { return run_robot(*a); }}};
});

}  // namespace
