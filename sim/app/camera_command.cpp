// fettle-sim camera --address 127.0.0.1 [--cell cell.toml] [--part part.toml] [--seed N] [--slide-mm X]:
// the simulated GigE Vision 3D camera (Aravis' fake GigE Vision camera with Fettle's GenICam
// description), serving range images of the casting (--part, the simulator's scanner) or of
// a synthetic plane and sphere (no --part) for the current slide position. With --cell the
// camera sits where that cell's calibration file says (as in `fettle-sim cell`), so a cell
// assembled from the separate simulators sees the part where fettled expects it.
//
// While it runs, lines on stdin change it: `slide MM`, `drop N` (the next N frames are never
// delivered), `loss N RATIO` (the next N frames lose packets), `stall MS`, `revoke` (control
// lost, as after a camera reboot), `quit`.
#include <poll.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <csignal>
#include <filesystem>
#include <iostream>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "fettle/config/load.hpp"
#include "fettle/cli/cli.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/sim/camera.hpp"

namespace {

std::atomic<bool> g_stop{false};
extern "C" void on_camera_signal(int /*sig*/) { g_stop = true; }

struct Args {
  std::string address;  ///< empty: the cell's [camera] address, else 127.0.0.1
  std::filesystem::path cell;
  std::filesystem::path part;
  std::uint64_t seed = 1;
  double slide_mm = 0.0;
  double packet_loss = 0.0;
  std::string serial = "FETTLE-SIM-3D";
  std::string resolution = "2064x1544";
  int packet_size_bytes = 8192;
  double run_for_s = 0.0;
  bool ideal = false;
};

fettle::sim::RangeImageModel model_for(const std::string& resolution) {
  fettle::sim::RangeImageModel m;
  unsigned w = 0, h = 0;
  char x = 0;
  std::istringstream in(resolution);
  if (!(in >> w >> x >> h) || x != 'x' || w < 16 || h < 16 || w > 8192 || h > 8192)
    throw fettle::UserError("--resolution '" + resolution + "': expected WIDTHxHEIGHT, e.g. 2064x1544 (16..8192)");
  m.width = w;
  m.height = h;
  // Same field of view at any resolution: focal length scales with the width.
  m.focal_px = 2400.0 * w / 2064.0;
  m.cx_px = (w - 1) / 2.0;
  m.cy_px = (h - 1) / 2.0;
  return m;
}

/// Applies one stdin command; false for `quit`.
bool apply(fettle::sim::SimulatedCamera& camera, const std::string& line) {
  std::istringstream in(line);
  std::string verb;
  in >> verb;
  if (verb.empty()) return true;
  auto log = fettle::log::get("sim.camera");
  if (verb == "quit") return false;
  if (verb == "slide") {
    double mm = 0.0;
    if (in >> mm) camera.set_slide_position_mm(mm), log->info("slide at {} mm", mm);
  } else if (verb == "drop") {
    int n = 1;
    in >> n;
    camera.drop_frames(n);
  } else if (verb == "loss") {
    int n = 1;
    double r = 0.05;
    in >> n >> r;
    camera.lose_packets(n, r);
  } else if (verb == "stall") {
    int ms = 1000;
    in >> ms;
    camera.stall_next_frame_ms(ms);
  } else if (verb == "revoke") {
    camera.revoke_control();
  } else {
    log->warn("unknown command '{}' (slide MM, drop N, loss N RATIO, stall MS, revoke, quit)", line);
  }
  return true;
}

int run_camera(const Args& a) {
  auto log = fettle::log::get("sim.camera");
  const auto model = model_for(a.resolution);
  fettle::sim::RangeImageSource source;
  std::optional<fettle::config::CellConfig> cell;
  if (!a.cell.empty()) cell = fettle::config::load_cell(a.cell);
  std::string address = a.address;
  if (address.empty()) address = cell && !cell->camera.address.empty() ? cell->camera.address : "127.0.0.1";
  if (!a.part.empty()) {
    const auto recipe = fettle::config::load_part(a.part);
    log->info("building casting {} of {} for the simulated camera", a.seed, a.part.string());
    source = fettle::sim::scanner_range_source(recipe, a.seed, model, !a.ideal, cell ? &*cell : nullptr);
    log->info("serving {}", source.description);
  } else {
    if (cell) log->warn("--cell places the camera over a casting; without --part the synthetic scene is served");
    log->info("no --part given: serving the synthetic plane-and-sphere scene");
    source = fettle::sim::synthetic_range_source(model, fettle::sim::SyntheticScene{});
  }
  fettle::sim::SimulatedCameraOptions o;
  o.address = address;
  o.serial = a.serial;
  o.seed = a.seed;
  o.packet_loss = a.packet_loss;
  o.packet_size_bytes = static_cast<std::uint32_t>(a.packet_size_bytes);
  fettle::sim::SimulatedCamera camera(o, source);
  if (a.slide_mm != 0.0) camera.set_slide_position_mm(a.slide_mm);
  std::signal(SIGINT, on_camera_signal);
  std::signal(SIGTERM, on_camera_signal);
  std::cout << "ready: GigE Vision camera " << a.serial << " on " << address << " (UDP 3956)" << std::endl;
  const auto t0 = std::chrono::steady_clock::now();
  std::string buffer;
  bool stdin_open = true;
  while (!g_stop) {
    if (a.run_for_s > 0.0 &&
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() >= a.run_for_s)
      break;
    if (stdin_open) {
      pollfd p{STDIN_FILENO, POLLIN, 0};
      if (::poll(&p, 1, 50) > 0 && (p.revents & (POLLIN | POLLHUP)) != 0) {
        char chunk[256];
        const auto n = ::read(STDIN_FILENO, chunk, sizeof chunk);
        if (n <= 0) {
          stdin_open = false;
        } else {
          buffer.append(chunk, static_cast<std::size_t>(n));
          for (auto nl = buffer.find('\n'); nl != std::string::npos; nl = buffer.find('\n')) {
            const std::string line = buffer.substr(0, nl);
            buffer.erase(0, nl + 1);
            if (!apply(camera, line)) g_stop = true;
          }
        }
      }
    } else {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
  }
  log->info("simulated camera stopping after {} frames", camera.frames_sent());
  return fettle::exit_code::ok;
}

FETTLE_COMMAND("camera", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* cmd = app.add_subcommand("camera", "Simulated GigE Vision 3D camera (Scan3d, Coord3D_C16) on UDP 3956");
  cmd->add_option("--address", a->address,
                  "Listening IPv4 address (one camera per address; default: the --cell's [camera] address, else "
                  "127.0.0.1)");
  cmd->add_option("--cell", a->cell,
                  "Cell file: the camera sits where its calibration puts it, as fettled expects (default: the "
                  "simulator's own pose, docs/simulator.md)")
      ->check(CLI::ExistingFile);
  cmd->add_option("--part", a->part, "Part recipe of the casting in the fixture")->check(CLI::ExistingFile);
  cmd->add_option("--seed", a->seed, "Seed (casting variation, packet loss)")->capture_default_str();
  cmd->add_option("--slide-mm", a->slide_mm, "Initial slide position, mm")->capture_default_str();
  cmd->add_option("--packet-loss", a->packet_loss, "GVSP packet loss ratio on every frame")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  cmd->add_option("--serial", a->serial, "Serial number")->capture_default_str();
  cmd->add_option("--resolution", a->resolution, "Range map size WIDTHxHEIGHT")->capture_default_str();
  cmd->add_option("--packet-size", a->packet_size_bytes, "Initial GevSCPSPacketSize, bytes")
      ->check(CLI::Range(576, 16384))
      ->capture_default_str();
  cmd->add_flag("--ideal", a->ideal, "No measurement noise (with --part)");
  cmd->add_option("--run-for-s", a->run_for_s, "Stop after this many seconds (0 = until SIGINT/SIGTERM or `quit`)");
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a] { return run_camera(*a); }}};
});

}  // namespace
