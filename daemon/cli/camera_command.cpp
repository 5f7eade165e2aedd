// fettle camera info|capture|discover: commissioning the GigE Vision 3D camera.
//   fettle camera info --address 192.168.20.30
//   fettle camera capture --address 192.168.20.30 --out scan.ply
//   fettle camera discover          (broadcast discovery: for operators only)
#include <chrono>
#include <filesystem>
#include <iostream>
#include <memory>
#include <string>

#include "fettle/config/calibration.hpp"
#include "fettle/config/load.hpp"
#include "fettle/cli/cli.hpp"
#include "fettle/core/error.hpp"
#include "fettle/drivers/camera.hpp"
#include "fettle/core/ply.hpp"

namespace {

struct Args {
  std::filesystem::path config;
  std::string address;
  std::string serial;
  std::string pixel_format;
  int timeout_ms = 0;
  int retries = -1;
  double exposure_us = 0.0;
  std::filesystem::path out;
};

fettle::drivers::CameraOptions options_from(const Args& a) {
  fettle::drivers::CameraOptions o;
  if (!a.config.empty()) {
    const auto cell = fettle::config::load_cell(a.config);
    o = fettle::drivers::camera_options(cell.camera);
    if (cell.camera.intrinsics == "calibration") {
      if (cell.calibration.file.empty())
        throw fettle::UserError(a.config.string() + ": [camera] intrinsics = \"calibration\" needs [calibration] file");
      const auto cal = fettle::config::load_calibration(cell.calibration.file);
      if (!cal.intrinsics)
        throw fettle::UserError(cell.calibration.file.string() + ": has no camera intrinsics, which [camera] "
                                                                 "intrinsics = \"calibration\" asks for");
      o.intrinsics = fettle::drivers::Intrinsics{cal.intrinsics->fx_px, cal.intrinsics->fy_px, cal.intrinsics->cx_px,
                                                 cal.intrinsics->cy_px};
    }
  }
  if (!a.address.empty()) o.address = a.address, o.serial.clear();
  if (!a.serial.empty()) o.serial = a.serial, o.address.clear();
  if (o.address.empty() && o.serial.empty())
    throw fettle::UserError("which camera? give --address A (or --serial S, or --config CELL.toml)");
  if (!a.pixel_format.empty()) o.pixel_format = a.pixel_format;
  if (a.timeout_ms > 0) o.frame_timeout_ms = a.timeout_ms;
  if (a.retries >= 0) o.retries = a.retries;
  if (a.exposure_us > 0.0) o.exposure_us = a.exposure_us;
  return o;
}

int camera_info(const Args& a) {
  fettle::drivers::Camera camera(options_from(a));
  std::cout << camera.info().to_string();
  return fettle::exit_code::ok;
}

int camera_capture(const Args& a) {
  fettle::drivers::Camera camera(options_from(a));
  auto c = camera.capture();
  if (!c) {
    std::cerr << "fettle: " << c.error().message << "\n";
    return c.error().code == "camera.unsupported_pixel_format" || c.error().code == "camera.no_intrinsics"
               ? fettle::exit_code::failure
               : fettle::exit_code::device;
  }
  if (auto s = fettle::write_ply(a.out, c->cloud); !s) throw fettle::UserError(s.error().message);
  std::cout << a.out.string() << ": " << c->cloud.width << " x " << c->cloud.height << " organized cloud, "
            << c->cloud.count_valid() << " valid points (frame " << c->frame_id << ", "
            << fettle::drivers::pixel_format_name(c->pixel_format) << ", " << c->stats.attempts << " attempt"
            << (c->stats.attempts == 1 ? "" : "s") << ", " << c->stats.wait_ms << " ms, decode " << c->stats.decode_ms
            << " ms)\n";
  return fettle::exit_code::ok;
}

int camera_discover() {
  const auto cameras = fettle::drivers::discover_cameras();
  if (cameras.empty()) {
    std::cout << "no camera answered GigE Vision discovery\n";
    return fettle::exit_code::ok;
  }
  for (const auto& c : cameras)
    std::cout << c.address << "  " << c.vendor << " " << c.model << "  serial " << c.serial << "  (" << c.protocol
              << ", id " << c.id << ")\n";
  return fettle::exit_code::ok;
}

void add_camera_options(CLI::App* cmd, Args& a) {
  cmd->add_option("--config", a.config, "Cell file: use its [camera] section")->check(CLI::ExistingFile);
  cmd->add_option("--address", a.address, "Camera IPv4 address (opened directly, no discovery)");
  cmd->add_option("--serial", a.serial, "Camera serial number (found by discovery)");
  cmd->add_option("--pixel-format", a.pixel_format, "Set PixelFormat first")
      ->check(CLI::IsMember({"Coord3D_C16", "Coord3D_C32f", "Coord3D_ABC32f"}));
  cmd->add_option("--timeout-ms", a.timeout_ms, "Frame timeout, ms")->check(CLI::PositiveNumber);
  cmd->add_option("--retries", a.retries, "Retries after a timeout or missing packets")->check(CLI::Range(0, 100));
  cmd->add_option("--exposure-us", a.exposure_us, "Exposure time, us")->check(CLI::PositiveNumber);
}

FETTLE_COMMAND("camera", [](CLI::App& app, const fettle::cli::Common&) {
  auto a = std::make_shared<Args>();
  auto* camera = app.add_subcommand("camera", "The GigE Vision 3D camera (commissioning)");
  camera->require_subcommand(1);
  auto* info = camera->add_subcommand("info", "Open the camera and show what it says about itself");
  add_camera_options(info, *a);
  auto* capture = camera->add_subcommand("capture", "Trigger one frame and write the organized cloud (mm) as PLY");
  add_camera_options(capture, *a);
  capture->add_option("--out", a->out, "Output file (.ply)")->required();
  auto* discover =
      camera->add_subcommand("discover", "List cameras answering GigE Vision broadcast discovery (operators only)");
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{
      {info, [a] { return camera_info(*a); }},
      {capture, [a] { return camera_capture(*a); }},
      {discover, [] { return camera_discover(); }}};
});

}  // namespace
