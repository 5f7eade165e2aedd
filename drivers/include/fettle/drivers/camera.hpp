#pragma once
// The GigE Vision 3D camera through Aravis: one organized cloud per software trigger.
//
//   Camera camera(camera_options(cell.camera));   // opens by address (never discovery), configures
//   Result<CameraCapture> c = camera.capture();   // trigger, receive, decode; retries; reconnects
//
// Setup throws fettle::DeviceError (camera unreachable, missing features); capture() returns
// values: "camera.fault" after `retries` failed attempts (timeouts, missing packets),
// "camera.unsupported_pixel_format", "camera.control_lost" if reconnecting failed.
// When Aravis reports control-lost (the heartbeat found another controller, or the camera
// rebooted), and after a capture that got no complete frame, the next capture() tears down
// and recreates the camera and its stream.
//
// The cycle uses the camera as a device with the cell's common lifecycle (device.hpp):
//   GigECamera cam(camera_options(cell.camera));
//   cam.configure();  cam.activate();  cam.capture();  cam.deactivate();   // errors as values
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "fettle/config/camera.hpp"
#include "fettle/core/cloud.hpp"
#include "fettle/core/result.hpp"
#include "fettle/drivers/camera_decode.hpp"
#include "fettle/drivers/device.hpp"

namespace fettle::drivers {

/// How to reach and set up the camera (from [camera] in the cell file).
struct CameraOptions {
  std::string address;           ///< IPv4; used as is, no discovery
  std::string serial;            ///< or the serial number (found by GigE Vision discovery)
  int frame_timeout_ms = 5000;   ///< wait for one triggered frame
  int retries = 2;               ///< re-triggers after a timeout or missing packets
  double exposure_us = 0.0;      ///< 0 = leave the camera's setting
  std::string pixel_format;      ///< e.g. "Coord3D_C16"; empty = leave the camera's setting
  int packet_size_bytes = 0;     ///< GevSCPSPacketSize; 0 = leave the camera's setting
  int heartbeat_timeout_ms = 0;  ///< GevHeartbeatTimeout; 0 = leave the camera's setting
  std::optional<Intrinsics> intrinsics;  ///< overrides the camera's Scan3d intrinsics (calibration file)
};

/// Options from the cell file's [camera] section (intrinsics are set by the caller if configured).
CameraOptions camera_options(const config::CameraSection& section);

/// What the camera says about itself after setup.
struct CameraInfo {
  std::string vendor;
  std::string model;
  std::string serial;
  std::string address;
  std::uint32_t width = 0;
  std::uint32_t height = 0;
  std::string pixel_format;  ///< the camera's PixelFormat
  std::vector<std::string> pixel_formats;  ///< the formats it offers
  std::uint32_t packet_size_bytes = 0;
  double exposure_us = 0.0;  ///< 0 if the camera has no exposure feature
  std::int64_t heartbeat_timeout_ms = 0;  ///< GevHeartbeatTimeout; 0 if the camera has no such feature
  Scan3dParameters scan3d;
  bool scan3d_from_camera = false;  ///< the camera has Scan3d features
  std::string intrinsics_source;    ///< "camera", "calibration" or "none"

  [[nodiscard]] std::string to_string() const;
};

/// Stream statistics of one capture (differences of Aravis' cumulative counters).
struct CaptureStats {
  int attempts = 0;               ///< triggers sent
  std::uint64_t resent_packets = 0;
  std::uint64_t missing_packets = 0;
  std::uint64_t underruns = 0;    ///< frames dropped because no buffer was free
  std::uint64_t failed_frames = 0;
  double wait_ms = 0.0;           ///< trigger to complete frame (last attempt)
  double decode_ms = 0.0;
  bool reconnected = false;       ///< the camera was recreated before this capture
};

struct CameraCapture {
  OrganizedCloud cloud;  ///< mm, camera frame
  std::uint64_t frame_id = 0;
  std::uint64_t timestamp_ns = 0;  ///< camera clock
  std::uint32_t pixel_format = 0;
  CaptureStats stats;
};

class Camera {
 public:
  /// Opens and configures the camera (TriggerMode On, TriggerSource Software, Continuous
  /// acquisition, exposure, pixel format) and starts acquisition. Throws DeviceError.
  explicit Camera(CameraOptions options);
  ~Camera();
  Camera(const Camera&) = delete;
  Camera& operator=(const Camera&) = delete;

  [[nodiscard]] const CameraInfo& info() const;
  /// One frame per call: trigger, wait up to frame_timeout_ms, retry up to `retries` times.
  Result<CameraCapture> capture();
  /// The same, decoding into `out` (its cloud's storage is reused: no 3.2 MP allocation per
  /// frame on the cycle path). On error `out` holds no valid frame.
  Status capture(CameraCapture& out);
  /// True once Aravis signalled control-lost and the camera was not recreated yet.
  [[nodiscard]] bool control_lost() const;
  /// How many times the camera was torn down and recreated.
  [[nodiscard]] int reconnects() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// The cell's 3D camera as a device (device.hpp): what the cycle uses. One capture at a time,
/// from one thread.
class CameraDevice : public Device {
 public:
  [[nodiscard]] std::string_view kind() const override { return "camera"; }
  /// One organized cloud (mm, camera frame). Not active: the error "camera.inactive".
  virtual Result<CameraCapture> capture() = 0;
  /// What the camera says about itself; empty until it was active.
  [[nodiscard]] virtual CameraInfo info() const = 0;
};

/// The GigE Vision camera (Camera) as a CameraDevice: configure() checks the options,
/// activate() opens the camera (a DeviceError becomes last_error()), deactivate() closes it.
class GigECamera final : public CameraDevice {
 public:
  explicit GigECamera(CameraOptions options);
  ~GigECamera() override;

  Status configure() override;
  Status activate() override;
  void deactivate() override;
  [[nodiscard]] Lifecycle lifecycle() const override { return lifecycle_; }
  [[nodiscard]] const Error& last_error() const override { return last_error_; }
  Result<CameraCapture> capture() override;
  [[nodiscard]] CameraInfo info() const override;

 private:
  Status failed(Error e);
  CameraOptions options_;
  std::unique_ptr<Camera> camera_;
  CameraInfo info_;
  Lifecycle lifecycle_ = Lifecycle::unconfigured;
  Error last_error_;
};

/// A camera answering GigE Vision discovery (for `fettle camera discover` only).
struct DiscoveredCamera {
  std::string id;
  std::string vendor;
  std::string model;
  std::string serial;
  std::string address;
  std::string protocol;
};
/// Broadcast discovery on every interface: for operators commissioning a cell, never used
/// by the cell itself.
std::vector<DiscoveredCamera> discover_cameras();

}  // namespace fettle::drivers
