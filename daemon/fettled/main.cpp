// fettled: the cell controller daemon (docs/daemon.md). One event loop; see fettle/daemon/runtime.hpp.
//
//   fettled --config /etc/fettle/cell.toml [--allow-root] [--log-level debug] [--max-cycles N]
#include <csignal>
#include <filesystem>
#include <iostream>
#include <optional>
#include <string>

#include <CLI/CLI.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>

#include "fettle/config/load.hpp"
#include "fettle/cli/cli.hpp"
#include "fettle/core/log.hpp"
#include "fettle/daemon/control.hpp"
#include "fettle/daemon/runtime.hpp"
#include "fettle/daemon/service.hpp"

namespace {

struct Args {
  std::filesystem::path config = "/etc/fettle/cell.toml";
  bool allow_root = false;
  std::optional<std::string> log_level;
  int max_cycles = 0;
  bool maintenance = false;
  bool no_captures = false;
};

int run(const Args& a) {
  using namespace fettle;
  if (auto st = daemon::service::check_user(a.allow_root); !st) {
    std::cerr << "fettled: " << st.error().message << "\n";
    return exit_code::failure;
  }
  auto cell = config::load_cell(a.config);
  log::Options lo;
  lo.program = "fettled";
  lo.default_level = cell.logging.level;
  lo.component_levels = cell.logging.components;
  lo.override_level = a.log_level;
  log::init(lo);
  auto logger = log::get("fettled");

  boost::asio::io_context io;
  daemon::RuntimeOptions ro;
  ro.max_cycles = a.max_cycles;
  ro.keep_captures = !a.no_captures;
  ro.on_state = [](packml::State, const std::string& line) { daemon::service::notify_status(line); };
  daemon::Runtime runtime(io, cell, ro);
  runtime.start();

  daemon::control::ServerOptions so;
  so.socket_path = cell.control.socket;
  so.maintenance = a.maintenance;
  daemon::control::Server server(io, runtime, so);
  if (auto st = server.start(); !st) {
    logger->error("control socket: {}", st.error().message);
    std::cerr << "fettled: control socket: " << st.error().message << "\n";
    return exit_code::failure;
  }
  bool stopping = false;
  daemon::service::Signals signals(io, [&](int sig) {
    if (stopping) return;
    stopping = true;
    logger->info("signal {}: stopping (robot first, then spindle)", sig);
    daemon::service::notify_stopping("stopping");
    server.stop();
    runtime.shutdown([&io] { io.stop(); });
  });
  daemon::service::Watchdog watchdog(io);
  watchdog.start();
  logger->info("fettled {} ready: cell '{}', control socket {}, records in {}", FETTLE_VERSION, cell.cell.name,
               cell.control.socket.string(), cell.cell.state_dir.string());
  daemon::service::notify_ready(std::string(packml::name(runtime.state())));
  io.run();
  logger->info("fettled stopped");
  return exit_code::ok;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"fettled - the Fettle cell controller daemon (PackML cycle, records, control socket)", "fettled"};
  app.set_version_flag("--version", std::string("fettled ") + FETTLE_VERSION);
  Args a;
  app.add_option("--config,-c", a.config, "Cell configuration file")->capture_default_str();
  app.add_flag("--allow-root", a.allow_root, "Run even as root (not recommended; the unit runs as user fettle)");
  fettle::cli::add_log_level(app, a.log_level);
  app.add_option("--max-cycles", a.max_cycles, "Complete Execute after this many cycles (0 = never)");
  app.add_flag("--maintenance", a.maintenance, "Start in maintenance mode (control socket reset/hold/dry cycle)");
  app.add_flag("--no-captures", a.no_captures, "Do not keep raw captures in the cycle records");
  return fettle::cli::run(app, argc, argv, [&] { return run(a); });
}
