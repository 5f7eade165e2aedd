// fettle-sim plc --listen 127.0.0.1:PORT: the simulated cell PLC on Modbus TCP.
#include <poll.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <csignal>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <sstream>
#include <string>
#include <tuple>
#include <thread>

#include "fettle/config/load.hpp"
#include "fettle/cli/cli.hpp"
#include "fettle/core/error.hpp"
#include "fettle/sim/plc.hpp"

namespace {

std::atomic<bool> g_stop{false};
extern "C" void on_signal(int /*sig*/) { g_stop = true; }

struct Args {
  std::string listen = "127.0.0.1:0";
  std::filesystem::path config;
  int register_base = -1;
  std::vector<double> positions_mm;
  double slide_speed_mm_s = 500.0;
  int heartbeat_period_ms = 100;
  int part_every_ms = 0;
  int recipe_id = 1;
  std::filesystem::path script;
  double run_for_s = 0.0;
  const CLI::Option* listen_given = nullptr;
};

/// Reads whatever full lines stdin has, without blocking; false at end of input.
bool read_stdin_lines(std::string& buffer, std::vector<std::string>& lines) {
  pollfd p{STDIN_FILENO, POLLIN, 0};
  if (::poll(&p, 1, 0) <= 0 || (p.revents & (POLLIN | POLLHUP)) == 0) return true;
  char chunk[512];
  const auto n = ::read(STDIN_FILENO, chunk, sizeof chunk);
  if (n <= 0) return false;
  buffer.append(chunk, static_cast<std::size_t>(n));
  for (auto nl = buffer.find('\n'); nl != std::string::npos; nl = buffer.find('\n')) {
    lines.push_back(buffer.substr(0, nl));
    buffer.erase(0, nl + 1);
  }
  return true;
}

int run_plc(Args a) {
  fettle::sim::PlcSimOptions o;
  if (!a.config.empty()) {
    const auto cell = fettle::config::load_cell(a.config);
    if (a.listen_given->count() == 0) a.listen = cell.plc.address + ":" + std::to_string(cell.plc.port);
    o.register_base = cell.plc.register_base;
    o.photo_positions_mm = cell.slide.photo_positions_mm;
    o.home_mm = cell.slide.home_mm;
  }
  std::tie(o.address, o.port) = fettle::cli::parse_address_port(a.listen, "--listen", 0, "127.0.0.1:0");
  if (a.register_base >= 0) o.register_base = a.register_base;
  if (!a.positions_mm.empty()) o.photo_positions_mm = a.positions_mm;
  o.slide_speed_mm_s = a.slide_speed_mm_s;
  o.heartbeat_period_ms = a.heartbeat_period_ms;
  o.part_every_ms = a.part_every_ms;
  o.part_recipe_id = a.recipe_id;

  std::vector<fettle::sim::PlcScriptStep> script;
  if (!a.script.empty()) {
    std::ifstream f(a.script);
    if (!f) throw fettle::UserError("--script " + a.script.string() + ": cannot read the file");
    std::stringstream text;
    text << f.rdbuf();
    auto parsed = fettle::sim::parse_plc_script(text.str());
    if (!parsed) throw fettle::UserError(a.script.string() + ": " + parsed.error().message);
    script = std::move(parsed.value());
  }

  fettle::sim::PlcSimulator plc(o);
  plc.start();
  std::cout << "listening " << o.address << ":" << plc.port() << std::endl;
  if (!script.empty()) plc.run_script(std::move(script));

  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  const auto started = std::chrono::steady_clock::now();
  std::string buffer;
  bool stdin_open = true;
  while (!g_stop) {
    if (a.run_for_s > 0.0 && std::chrono::steady_clock::now() - started >= std::chrono::duration<double>(a.run_for_s))
      break;
    std::vector<std::string> lines;
    if (stdin_open) stdin_open = read_stdin_lines(buffer, lines);
    for (const auto& line : lines)
      if (auto st = plc.apply(line); !st.ok()) std::cout << "error " << st.error().message << std::endl;
    for (const auto& e : plc.take_log()) std::cout << e << "\n";
    std::cout.flush();
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  plc.stop();
  for (const auto& e : plc.take_log()) std::cout << e << "\n";
  std::cout << "stopped" << std::endl;
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("plc", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* cmd = app.add_subcommand(
      "plc",
      "Simulated cell PLC on Modbus TCP (register map: docs/plc-interface.md). Prints 'listening ADDRESS:PORT', "
      "then what happens; reads commands on stdin: part ID, reset, start, stop, hold, unhold, abort, clear, drop, "
      "freeze on|off, slide-fault on|off, results-ack on|off, force OFFSET VALUE, release OFFSET|all, delay MS");
  a->listen_given =
      cmd->add_option("--listen", a->listen, "ADDRESS:PORT to listen on (port 0 = any free port)")->capture_default_str();
  cmd->add_option("--cell,--config", a->config,
                  "Cell file: listen on its [plc] address:port (unless --listen), take its register_base and [slide] "
                  "photo_positions_mm, home_mm")
      ->check(CLI::ExistingFile);
  cmd->add_option("--register-base", a->register_base, "Holding-register address of the map's first register")
      ->check(CLI::Range(0, 65535 - 26));
  cmd->add_option("--positions-mm", a->positions_mm, "Slide photo positions in mm (1 to 16)")->delimiter(',');
  cmd->add_option("--slide-speed-mm-s", a->slide_speed_mm_s, "Slide travel speed")
      ->check(CLI::Range(0.001, 100000.0))
      ->capture_default_str();
  cmd->add_option("--heartbeat-period-ms", a->heartbeat_period_ms, "PLC heartbeat increment period")
      ->check(CLI::Range(1, 60000))
      ->capture_default_str();
  cmd->add_option("--parts-every-ms", a->part_every_ms, "A part arrives this often (0 = only on command/script)")
      ->check(CLI::Range(0, 3600000));
  cmd->add_option("--recipe-id", a->recipe_id, "Recipe id of parts arriving at a rate")->check(CLI::Range(1, 65535));
  cmd->add_option("--script", a->script, "Script of timed commands: lines '[at SECONDS] COMMAND'")
      ->check(CLI::ExistingFile);
  cmd->add_option("--run-for-s", a->run_for_s, "Stop after this many seconds (0 = until SIGINT/SIGTERM)")
      ->check(CLI::Range(0.0, 1e9));
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a] { return run_plc(*a); }}};
});

}  // namespace
