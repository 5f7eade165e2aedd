#pragma once
// The simulated GigE Vision 3D camera: Aravis' ArvGvFakeCamera (the real GVCP/GVSP wire
// protocols, in process) with Fettle's own GenICam description (Scan3d features, Coord3D_C16
// range maps), serving range images from an injected renderer for the current slide position.
//
//   SimulatedCamera camera(options, synthetic_range_source(...));   // listens on 127.0.0.1:3956
//   camera.set_slide_position_mm(120.0);                            // the PLC moved the slide
//   camera.drop_frames(1);                                          // fault injection
//
// GigE Vision's control port is fixed (UDP 3956): one camera per address. Tests that start
// one hold the CTest RESOURCE_LOCK "gige".
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "fettle/config/cell.hpp"
#include "fettle/config/part.hpp"

namespace fettle::sim {

/// The range camera's fixed model, published through the Scan3d features.
struct RangeImageModel {
  std::uint32_t width = 2064;   ///< 3.2 MP, as the cell's structured-light camera
  std::uint32_t height = 1544;
  double focal_px = 2400.0;     ///< Scan3dFocalLength (square pixels)
  double cx_px = 1031.5;        ///< Scan3dPrincipalPointU
  double cy_px = 771.5;         ///< Scan3dPrincipalPointV
  double scale_mm = 0.02;       ///< Scan3dCoordinateScale: mm per count (0..1310 mm range)
  double offset_mm = 0.0;       ///< Scan3dCoordinateOffset
  std::uint16_t invalid = 0;    ///< Scan3dInvalidDataValue: "no data"
};

/// Where the simulated camera's range images come from: the model, and a renderer that fills
/// width*height Coord3D_C16 values (row-major, z = raw * scale + offset mm, `invalid` = no data)
/// for a slide position. Called from the camera's thread, once per triggered frame.
struct RangeImageSource {
  RangeImageModel model;
  std::function<void(double slide_mm, std::vector<std::uint16_t>& range)> render;
  std::string description;  ///< for logs, e.g. "synthetic plane and sphere"
};

/// A synthetic scene with exactly known geometry, for tests and as the fallback scene:
/// a plane z = plane_z_mm (camera frame) and a sphere of radius sphere_radius_mm whose centre
/// is at sphere_center_mm, shifted along camera x by -slide_mm (the camera rides the slide).
struct SyntheticScene {
  double plane_z_mm = 800.0;
  double sphere_center_mm[3] = {0.0, 0.0, 700.0};
  double sphere_radius_mm = 60.0;
};
RangeImageSource synthetic_range_source(const RangeImageModel& model, const SyntheticScene& scene);
/// The exact depth of the synthetic scene along the ray through pixel (u, v); NaN if none.
double synthetic_depth_mm(const RangeImageModel& model, const SyntheticScene& scene, double slide_mm, double u,
                          double v);

/// The simulator's scanner (fettle::sim::Scanner, sim.hpp) looking at casting `seed` of `recipe`
/// on the fixture: range images at `model`'s size (rectified: the scanner's lens distortion is
/// set to zero, as a 3D camera outputs rectified range maps), with the scanner's noise model
/// unless `noise` is false. With `cell`, the camera sits where that cell's calibration puts it
/// (ScannerConfig::place_in_cell), as in `fettle-sim cell`; without, at the scanner's default.
RangeImageSource scanner_range_source(const config::PartRecipe& recipe, std::uint64_t seed,
                                      const RangeImageModel& model = {}, bool noise = true,
                                      const config::CellConfig* cell = nullptr);

struct SimulatedCameraOptions {
  std::string address = "127.0.0.1";  ///< listening IPv4 (loopback in tests)
  std::string serial = "FETTLE-SIM-3D";
  std::uint32_t packet_size_bytes = 8192;  ///< initial GevSCPSPacketSize
  double packet_loss = 0.0;               ///< GVSP packet loss ratio on every frame (0..1)
  std::uint64_t seed = 1;                 ///< for packet loss
};

class SimulatedCamera {
 public:
  /// Starts listening; throws fettle::DeviceError if the address cannot be used (e.g. another
  /// camera already holds UDP 3956 there).
  SimulatedCamera(SimulatedCameraOptions options, RangeImageSource source);
  ~SimulatedCamera();
  SimulatedCamera(const SimulatedCamera&) = delete;
  SimulatedCamera& operator=(const SimulatedCamera&) = delete;

  [[nodiscard]] const std::string& address() const;
  [[nodiscard]] const RangeImageModel& model() const;

  /// Renders the range image for this slide position (in the caller's thread; with the
  /// simulator's scanner at 3.2 MP this takes a moment) and serves it from the next frame on.
  void set_slide_position_mm(double slide_mm);
  [[nodiscard]] double slide_position_mm() const;

  // Fault injection (each applies to the next frames the camera sends).
  /// The next `frames` triggered frames are never delivered (every GVSP packet dropped).
  void drop_frames(int frames);
  /// The next `frames` frames lose packets with this ratio (the fake ignores resend requests).
  void lose_packets(int frames, double ratio);
  /// Packet loss on every frame from now on.
  void set_packet_loss(double ratio);
  /// The camera thread stalls this long before sending the next frame (control channel too).
  void stall_next_frame_ms(int ms);
  /// Drops the controller's privilege as a camera reboot would: the driver's heartbeat sees
  /// it and Aravis signals control-lost.
  void revoke_control();
  /// The camera stops acquiring by itself (another program's AcquisitionStop, a firmware reset
  /// that keeps its address and our control): triggers are still acknowledged but no frame
  /// comes, and the driver's heartbeat sees nothing wrong.
  void stop_acquisition();

  /// Frames rendered and sent (including dropped ones).
  [[nodiscard]] std::uint64_t frames_sent() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace fettle::sim
