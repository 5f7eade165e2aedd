#pragma once
// Fault codes of fettled (docs/faults.md is the table for people; this header must match it).
//
// Every fault has a number (written to the PLC's fault_code register, latched until the PLC
// sends a PackML Reset), a stable id, and a reaction:
//   hold  - recoverable: the cell stops in Held (spindle off, slide home); the operator
//           removes the cause, the PLC sends Reset (clears the latch) and Unhold.
//   abort - safety-relevant: the robot is stopped first, then the spindle; the cell goes to
//           Aborted; recovery is Clear -> Stopped -> Reset -> Idle -> Start.
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "fettle/core/result.hpp"

namespace fettle::daemon {

enum class FaultReaction { hold, abort };
std::string_view to_string(FaultReaction r);

enum class FaultCode : std::uint16_t {
  // PLC and slide (1xx)
  plc_link_lost = 101,         ///< PLC link down while nothing moves
  plc_link_lost_moving = 102,  ///< PLC link down while the robot or spindle moves
  plc_value_out_of_range = 103,
  slide_timeout = 104,
  slide_fault = 105,
  // Camera (2xx)
  camera_timeout = 201,      ///< no frame after the configured retries
  camera_unavailable = 202,  ///< the camera cannot be opened / reconnected
  // Robot (3xx)
  robot_nak = 301,              ///< the robot refused a message (reason code in the message)
  robot_fault = 302,            ///< the robot reported FAULT while running
  robot_link_lost_moving = 303, ///< robot link lost during upload-run (motion possible)
  robot_unavailable = 304,      ///< the robot is not connected when a cycle needs it
  robot_timeout = 305,          ///< no DONE within the run timeout
  // Spindle (4xx)
  spindle_fault = 401,        ///< drive fault (EMCY, fault statusword, heartbeat lost)
  spindle_timeout = 402,      ///< not at speed / not stopped in time
  spindle_unavailable = 403,  ///< the drive cannot be configured
  tool_worn = 404,            ///< a wheel is predicted worn past its [[tools]] max_wear_mm
  // Part, vision, planning (5xx)
  empty_fixture = 501,
  wrong_part = 502,
  unknown_recipe = 503,
  vision_failed = 504,
  plan_failed = 505,
  // Daemon (6xx)
  step_timeout = 601,   ///< a cycle step outlived its timeout
  operator_abort = 602, ///< Abort command from the PLC or the control socket
  internal = 603,       ///< a bug (an exception on the cycle path)
  records_failed = 604, ///< a cycle record could not be written (disk full, permissions)
};

struct FaultInfo {
  FaultCode code;
  std::string_view id;  ///< e.g. "camera.timeout"
  FaultReaction reaction;
  std::string_view meaning;
  std::string_view remedy;
};

/// The table of every fault (in code order).
const std::vector<FaultInfo>& fault_table();
const FaultInfo& info(FaultCode code);
std::optional<FaultCode> fault_from_number(int number);

/// A fault that happened: code plus what/where for people.
struct Fault {
  FaultCode code = FaultCode::internal;
  std::string message;
  std::string step;  ///< cycle step where it happened ("" outside a cycle)

  [[nodiscard]] int number() const { return static_cast<int>(code); }
  [[nodiscard]] FaultReaction reaction() const { return info(code).reaction; }
  [[nodiscard]] std::string_view id() const { return info(code).id; }
  /// "E201 camera.timeout (capture 1): ..."
  [[nodiscard]] std::string describe() const;
};

/// What the cycle called when it got an error.
enum class ErrorSource { plc, camera, robot, spindle, process };

/// The fault for an Error of a device or the pipeline, from its source and its kind (never from
/// its code string), given whether the robot or spindle may be moving. An error whose kind says
/// nothing more for its source is `fallback` (the caller's step knows what failed).
Fault fault_from_error(const Error& error, ErrorSource source, std::string_view step, bool motion, FaultCode fallback);

}  // namespace fettle::daemon
