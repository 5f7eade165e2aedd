// The fault table (docs/faults.md) and the mapping from link/pipeline errors to faults.
#include "fettle/daemon/faults.hpp"

#include <algorithm>
#include <cstdio>
#include <stdexcept>

namespace fettle::daemon {

std::string_view to_string(FaultReaction r) { return r == FaultReaction::hold ? "hold" : "abort"; }

const std::vector<FaultInfo>& fault_table() {
  using enum FaultCode;
  using enum FaultReaction;
  static const std::vector<FaultInfo> table{
      {plc_link_lost, "plc.link_lost", hold, "the PLC link is down (no reply, or its heartbeat froze) while nothing moves",
       "check the PLC, the Ethernet cable and [plc] address/port; the link reconnects by itself"},
      {plc_link_lost_moving, "plc.link_lost_moving", abort,
       "the PLC link went down while the robot or the spindle was moving",
       "check the PLC and the network; then Clear, Reset, Start"},
      {plc_value_out_of_range, "plc.value_out_of_range", hold, "a PLC register holds an impossible value",
       "fix the PLC program (docs/plc-interface.md lists the allowed values)"},
      {slide_timeout, "slide.timeout", hold, "the camera slide did not reach its position within [slide] travel_timeout_ms",
       "check the slide axis and its PLC program"},
      {slide_fault, "slide.fault", hold, "the PLC reports a slide fault", "clear the slide fault at the PLC"},
      {camera_timeout, "camera.timeout", hold, "the camera sent no complete frame after [camera] retries",
       "check the camera's power, cable and network (packet size, jumbo frames)"},
      {camera_unavailable, "camera.unavailable", hold, "the camera cannot be opened or reconnected",
       "check [camera] address, the camera's power and network"},
      {robot_nak, "robot.nak", hold, "the robot refused a message (the NAK code says why)",
       "see the NAK code in docs/robot-protocol.md; check [safety] limits against the robot's envelope"},
      {robot_fault, "robot.fault", abort, "the robot reported FAULT during a run",
       "check the robot controller's error log; reset the robot, then Clear, Reset, Start"},
      {robot_link_lost_moving, "robot.link_lost_moving", abort,
       "the robot link was lost during an upload or a run; a protocol error from the robot (a wrong sequence number, "
       "a line that does not parse, a reply that answers nothing) takes the link down too",
       "check the robot controller and the network; a protocol error is in the log with the line "
       "(docs/robot-protocol.md)"},
      {robot_unavailable, "robot.unavailable", hold,
       "the robot is not connected or not ready when the cycle needs it (also a lost link or protocol error while "
       "nothing moves)",
       "start the robot program (it must accept HELLO on [robot] address/port)"},
      {robot_timeout, "robot.timeout", abort, "the robot did not finish the run within [robot] run_timeout_ms",
       "check the robot; the run timeout must exceed the longest trajectory"},
      {spindle_fault, "spindle.fault", abort, "the spindle drive is in fault (EMCY, statusword, heartbeat lost)",
       "read the EMCY code (docs/spindle-canopen.md), fix the drive, then Clear, Reset, Start"},
      {spindle_timeout, "spindle.timeout", abort, "the spindle did not reach or leave its speed in time",
       "check the drive's ramp and [spindle] spin_up_timeout_ms"},
      {spindle_unavailable, "spindle.unavailable", hold, "the spindle drive cannot be reached or configured",
       "check the CAN bus, termination, node id and [spindle] transport"},
      {tool_worn, "tool.worn", hold,
       "a wheel would wear past its [[tools]] max_wear_mm on the next casting, or its wear would be known less well "
       "than its regions' finish needs (the cell's prediction from the iron it removed)",
       "fit a new wheel, run `fettle tool changed NAME` in maintenance mode, then Reset, Start"},
      {empty_fixture, "part.empty_fixture", hold, "no part was found in the fixture",
       "place a part; the PLC must request a cycle only with a part clamped"},
      {wrong_part, "part.wrong_part", hold, "the scanned part does not match the requested recipe's template",
       "check the part and the recipe id the PLC sends"},
      {unknown_recipe, "part.unknown_recipe", hold, "the PLC requested a recipe id that [cell] recipes does not list",
       "add the recipe to [[cell.recipes]] or fix the PLC's recipe id"},
      {vision_failed, "vision.failed", hold, "inspection failed (too few points, no plane, bad views)",
       "check the camera view and the [vision] settings of the recipe"},
      {plan_failed, "planning.failed", hold, "no valid grinding trajectory could be planned",
       "check the recipe's regions, tools and [safety] limits"},
      {step_timeout, "cycle.step_timeout", abort, "a cycle step outlived its timeout", "see the step in the log"},
      {operator_abort, "cycle.operator_abort", abort, "Abort was commanded", "Clear, Reset, Start"},
      {internal, "cycle.internal", abort, "an internal error on the cycle path (a bug)", "report it with the log"},
      {records_failed, "records.failed", hold, "a cycle record could not be written",
       "check free space and permissions of [cell] state_dir"},
  };
  return table;
}

const FaultInfo& info(FaultCode code) {
  for (const auto& f : fault_table())
    if (f.code == code) return f;
  throw std::logic_error("fault code without a table entry: " + std::to_string(static_cast<int>(code)));
}

std::optional<FaultCode> fault_from_number(int number) {
  for (const auto& f : fault_table())
    if (static_cast<int>(f.code) == number) return f.code;
  return std::nullopt;
}

std::string Fault::describe() const {
  char head[16];
  std::snprintf(head, sizeof head, "E%d ", number());
  std::string s = head + std::string(id());
  if (!step.empty()) s += " (" + step + ")";
  return s + ": " + message;
}

namespace {

FaultCode robot_fault_for(ErrorKind kind, bool motion, FaultCode fallback) {
  using enum FaultCode;
  switch (kind) {
    case ErrorKind::refused: return robot_nak;
    case ErrorKind::device_fault: return robot_fault;
    case ErrorKind::timeout: return robot_timeout;
    case ErrorKind::link_lost:
    case ErrorKind::cancelled: return motion ? robot_link_lost_moving : robot_unavailable;
    case ErrorKind::unavailable: return robot_unavailable;
    case ErrorKind::invalid_request: return plan_failed;
    default: return fallback;
  }
}

FaultCode spindle_fault_for(ErrorKind kind, bool motion) {
  using enum FaultCode;
  switch (kind) {
    case ErrorKind::timeout: return spindle_timeout;
    case ErrorKind::unavailable:
    case ErrorKind::refused: return motion ? spindle_fault : spindle_unavailable;  // it may turn: a fault
    default: return spindle_fault;
  }
}

FaultCode process_fault_for(ErrorKind kind, FaultCode fallback) {
  using enum FaultCode;
  switch (kind) {
    case ErrorKind::no_part: return empty_fixture;
    case ErrorKind::wrong_part: return wrong_part;
    case ErrorKind::unplannable:
    case ErrorKind::invalid_request: return plan_failed;
    default: return fallback;
  }
}

}  // namespace

Fault fault_from_error(const Error& error, ErrorSource source, std::string_view step, bool motion, FaultCode fallback) {
  FaultCode code = fallback;
  switch (source) {
    case ErrorSource::robot: code = robot_fault_for(error.kind, motion, fallback); break;
    case ErrorSource::spindle: code = spindle_fault_for(error.kind, motion); break;
    case ErrorSource::camera:
      code = error.kind == ErrorKind::no_data ? FaultCode::camera_timeout : FaultCode::camera_unavailable;
      break;
    case ErrorSource::process: code = process_fault_for(error.kind, fallback); break;
    case ErrorSource::plc: break;
  }
  return Fault{code, error.message.empty() ? error.code : error.code + ": " + error.message, std::string(step)};
}

}  // namespace fettle::daemon
