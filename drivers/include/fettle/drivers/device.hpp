#pragma once
// The lifecycle every device of the cell goes through, with the same verbs for each, after
// ros2_control's hardware components:
//
//   unconfigured --configure()--> inactive --activate()--> active
//                                     ^                      |
//                                     +----deactivate()------+
//
// configure() checks the options and prepares, without talking to the device. activate()
// connects (opens the camera, starts a link) and may be called again after a failure or a
// deactivate(). deactivate() stops talking to the device and leaves it safe. A failed
// transition leaves the device where it was, with last_error() saying why and what to check;
// the device's own operations (capture, upload, ...) return their errors as values.
// Interfaces: CameraDevice (camera.hpp), RobotDevice (robot_link.hpp), SpindleDevice
// (spindle.hpp), PlcDevice (plc_link.hpp); each has its real implementation there.
#include <string_view>

#include "fettle/core/result.hpp"

namespace fettle::drivers {

enum class Lifecycle { unconfigured, inactive, active };

[[nodiscard]] std::string_view to_string(Lifecycle state);

class Device {
 public:
  virtual ~Device() = default;
  Device() = default;
  Device(const Device&) = delete;
  Device& operator=(const Device&) = delete;

  /// "camera", "robot", "spindle", "plc": names the device in logs and errors.
  [[nodiscard]] virtual std::string_view kind() const = 0;
  virtual Status configure() = 0;
  virtual Status activate() = 0;
  virtual void deactivate() = 0;
  [[nodiscard]] virtual Lifecycle lifecycle() const = 0;
  /// Why the last transition or operation failed (empty code: none did).
  [[nodiscard]] virtual const Error& last_error() const = 0;
};

}  // namespace fettle::drivers
