// fettle-sim spindle: the simulated CiA 402 grinding spindle drive.
//   --listen 127.0.0.1:PORT   serve its CAN bus with socketcand's rawmode protocol (port 0: any free
//                             port; prints "listening ADDRESS:PORT")
//   --can vcan0               or sit on a SocketCAN interface instead
// Commands on stdin, one per line: "fault overcurrent|overtemperature|heartbeat_loss",
// "removal MM3_S" (material removal rate), "heartbeat on|off", "status".
#include <unistd.h>

#include <csignal>
#include <iostream>
#include <memory>
#include <sstream>
#include <string>

#include <boost/asio/io_context.hpp>
#include <boost/asio/posix/stream_descriptor.hpp>
#include <boost/asio/read_until.hpp>
#include <boost/asio/signal_set.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/streambuf.hpp>

#include "fettle/cli/cli.hpp"
#include "fettle/config/load.hpp"
#include "fettle/core/error.hpp"
#include "fettle/drivers/canopen_transport.hpp"
#include "fettle/sim/spindle.hpp"

namespace {

struct Args {
  std::string listen = "127.0.0.1:29536";
  std::string can;
  std::string bus = "can0";
  int node_id = 1;
  double ramp_rpm_s = 20000.0;
  double rated_current_a = 8.0;
  double run_for_s = 0.0;
  std::filesystem::path cell;
  const CLI::Option* listen_given = nullptr;
  const CLI::Option* bus_given = nullptr;
  const CLI::Option* node_id_given = nullptr;
};

std::string apply_command(fettle::sim::SimulatedSpindleDrive& drive, const std::string& line) {
  std::istringstream in(line);
  std::string cmd, arg;
  in >> cmd >> arg;
  if (cmd.empty()) return "";
  if (cmd == "fault") {
    auto f = fettle::sim::parse_spindle_fault(arg);
    if (!f) return "error " + f.error().message;
    drive.inject_fault(*f);
    return "ok fault " + arg;
  }
  if (cmd == "removal") {
    try {
      drive.set_material_removal_rate(std::stod(arg));
    } catch (const std::exception&) {
      return "error removal needs a number (mm3/s)";
    }
    return "ok removal " + arg;
  }
  if (cmd == "heartbeat" && (arg == "on" || arg == "off")) {
    drive.set_heartbeat_enabled(arg == "on");
    return "ok heartbeat " + arg;
  }
  if (cmd == "status") {
    std::ostringstream s;
    s << "status state=\"" << fettle::canopen::to_string(drive.state()) << "\" nmt=\""
      << fettle::canopen::to_string(drive.nmt_state()) << "\" velocity_rpm=" << drive.velocity_rpm()
      << " current_a=" << drive.current_a() << " mode=" << static_cast<int>(drive.mode());
    return s.str();
  }
  return "error unknown command '" + line +
         "' (fault overcurrent|overtemperature|heartbeat_loss, removal MM3_S, heartbeat on|off, status)";
}

int run_spindle(Args a) {
  if (!a.cell.empty()) {
    // The drive fettled expects: [spindle] node_id, on its socketcand address:port and bus; options given win.
    const auto cell = fettle::config::load_cell(a.cell);
    const auto& s = cell.spindle;
    if (a.listen_given->count() == 0) a.listen = s.address + ":" + std::to_string(s.port);
    if (a.bus_given->count() == 0) a.bus = s.interface;
    if (a.node_id_given->count() == 0) a.node_id = s.node_id;
  }
  boost::asio::io_context io;
  fettle::sim::SpindleSimOptions o;
  o.node_id = static_cast<std::uint8_t>(a.node_id);
  o.ramp_rpm_s = a.ramp_rpm_s;
  o.rated_current_a = a.rated_current_a;

  std::shared_ptr<fettle::canopen::InProcessBus> bus;
  std::unique_ptr<fettle::sim::SocketcandServer> server;
  std::shared_ptr<fettle::canopen::CanTransport> transport;
  if (!a.can.empty()) {
    transport = fettle::canopen::open_socketcan(io, a.can);
  } else {
    const auto [address, port] = fettle::cli::parse_address_port(a.listen, "--listen", 0, "127.0.0.1:0");
    bus = fettle::canopen::InProcessBus::create();
    transport = bus->attach(io, "drive");
    server = std::make_unique<fettle::sim::SocketcandServer>(io, bus, address, port, a.bus);
    std::cout << "listening " << address << ":" << server->port() << std::endl;
  }
  fettle::sim::SimulatedSpindleDrive drive(io, transport, o);
  drive.power_on();
  std::cerr << "fettle-sim spindle: node " << a.node_id << (a.can.empty() ? " on socketcand bus " + a.bus : " on " + a.can)
            << "; commands on stdin: fault overcurrent|overtemperature|heartbeat_loss, removal MM3_S, "
               "heartbeat on|off, status\n";

  boost::asio::signal_set signals(io, SIGINT, SIGTERM);
  signals.async_wait([&io](const boost::system::error_code&, int) { io.stop(); });
  boost::asio::steady_timer run_for(io);
  if (a.run_for_s > 0.0) {
    run_for.expires_after(std::chrono::milliseconds(static_cast<long long>(a.run_for_s * 1000.0)));
    run_for.async_wait([&io](const boost::system::error_code& ec) {
      if (!ec) io.stop();
    });
  }

  // stdin commands (when stdin is a pipe or a terminal; /dev/null and files are ignored).
  boost::asio::posix::stream_descriptor input(io);
  boost::asio::streambuf input_buffer;
  std::function<void()> read_line;
  boost::system::error_code ec;
  input.assign(::dup(STDIN_FILENO), ec);
  if (!ec) {
    read_line = [&] {
      boost::asio::async_read_until(input, input_buffer, '\n', [&](const boost::system::error_code& e, std::size_t) {
        if (e) return;  // end of input: keep running until a signal
        std::istream is(&input_buffer);
        std::string line;
        std::getline(is, line);
        if (auto reply = apply_command(drive, line); !reply.empty()) std::cout << reply << std::endl;
        read_line();
      });
    };
    read_line();
  }
  io.run();
  std::cout << "stopped" << std::endl;
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("spindle", [](CLI::App& app, const fettle::cli::Common&) {
  auto args = std::make_shared<Args>();
  auto* cmd = app.add_subcommand("spindle", "Simulated CANopen CiA 402 grinding spindle drive (socketcand or SocketCAN)");
  args->listen_given =
      cmd->add_option("--listen", args->listen,
                      "Serve the drive's CAN bus with the socketcand protocol on ADDRESS:PORT (0: any free port)")
          ->capture_default_str();
  cmd->add_option("--cell", args->cell,
                  "Cell file: the drive [spindle] describes (node_id; socketcand address:port and bus interface); "
                  "options given explicitly win")
      ->check(CLI::ExistingFile);
  cmd->add_option("--can", args->can, "Use this SocketCAN interface (e.g. vcan0) instead of --listen");
  args->bus_given = cmd->add_option("--bus", args->bus, "Bus name clients open over socketcand")->capture_default_str();
  args->node_id_given =
      cmd->add_option("--node-id", args->node_id, "CANopen node id")->check(CLI::Range(1, 127))->capture_default_str();
  cmd->add_option("--ramp-rpm-s", args->ramp_rpm_s, "Acceleration/deceleration in rpm/s")
      ->check(CLI::Range(1.0, 1e6))
      ->capture_default_str();
  cmd->add_option("--rated-current-a", args->rated_current_a, "Motor rated current (0x6075)")
      ->check(CLI::Range(0.1, 1000.0))
      ->capture_default_str();
  cmd->add_option("--run-for-s", args->run_for_s, "Exit after this many seconds (0: until SIGINT/SIGTERM)");
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [args] { return run_spindle(*args); }}};
});

}  // namespace
