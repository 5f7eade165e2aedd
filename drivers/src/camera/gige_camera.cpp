// The GigE Vision camera as a CameraDevice (camera.hpp).
#include <string>
#include <utility>

#include "fettle/core/error.hpp"
#include "fettle/drivers/camera.hpp"

namespace fettle::drivers {

GigECamera::GigECamera(CameraOptions options) : options_(std::move(options)) {}
GigECamera::~GigECamera() = default;

Status GigECamera::failed(Error e) {
  last_error_ = e;
  return e;
}

Status GigECamera::configure() {
  if (lifecycle_ != Lifecycle::unconfigured) return {};
  const std::string which = "[camera] ";
  if (options_.address.empty() && options_.serial.empty())
    return failed(Error{"camera.config", which + "gives neither address nor serial: set address (IPv4)", ErrorKind::config});
  if (options_.frame_timeout_ms <= 0)
    return failed(Error{"camera.config",
                        which + "frame_timeout_ms " + std::to_string(options_.frame_timeout_ms) + " must be above 0", ErrorKind::config});
  if (options_.retries < 0)
    return failed(Error{"camera.config", which + "retries " + std::to_string(options_.retries) + " must be 0 or more", ErrorKind::config});
  lifecycle_ = Lifecycle::inactive;
  last_error_ = {};
  return {};
}

Status GigECamera::activate() {
  if (lifecycle_ == Lifecycle::active) return {};
  if (lifecycle_ == Lifecycle::unconfigured)
    return failed(Error{"camera.lifecycle", "camera " + options_.address + ": activate() before configure()", ErrorKind::unavailable});
  try {
    camera_ = std::make_unique<Camera>(options_);
  } catch (const Exception& e) {
    return failed(Error{"camera.unavailable", e.what(), ErrorKind::unavailable});
  }
  info_ = camera_->info();
  lifecycle_ = Lifecycle::active;
  last_error_ = {};
  return {};
}

void GigECamera::deactivate() {
  camera_.reset();  // stops acquisition and gives up the control channel
  if (lifecycle_ == Lifecycle::active) lifecycle_ = Lifecycle::inactive;
}

Result<CameraCapture> GigECamera::capture() {
  if (lifecycle_ != Lifecycle::active || !camera_)
    return Error{"camera.inactive", "camera " + options_.address + " is " + std::string(to_string(lifecycle_)) +
                                        (last_error_.message.empty() ? "" : " (" + last_error_.message + ")"), ErrorKind::unavailable};
  auto c = camera_->capture();
  if (!c) last_error_ = c.error();
  return c;
}

CameraInfo GigECamera::info() const { return info_; }

}  // namespace fettle::drivers
