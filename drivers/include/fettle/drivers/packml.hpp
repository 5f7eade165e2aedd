#pragma once
// PackML (ANSI/ISA-TR88.00.02) state and command codes, as carried in PackTags
// (Status.StateCurrent and Command.CntrlCmd). Shared by the PLC link, the daemon and the
// simulated PLC. Header-only, no dependencies.
#include <cstdint>
#include <optional>
#include <string_view>

namespace fettle::packml {

/// Status.StateCurrent. 0 is "Undefined" in PackTags and is never sent by Fettle.
enum class State : std::uint16_t {
  undefined = 0,
  clearing = 1,
  stopped = 2,
  starting = 3,
  idle = 4,
  suspended = 5,
  execute = 6,
  stopping = 7,
  aborting = 8,
  aborted = 9,
  holding = 10,
  held = 11,
  unholding = 12,
  suspending = 13,
  unsuspending = 14,
  resetting = 15,
  completing = 16,
  complete = 17,
};

/// Command.CntrlCmd. 0 is "Undefined" (no command).
enum class Command : std::uint16_t {
  none = 0,
  reset = 1,
  start = 2,
  stop = 3,
  hold = 4,
  unhold = 5,
  suspend = 6,
  unsuspend = 7,
  abort = 8,
  clear = 9,
};

constexpr std::string_view name(State s) {
  switch (s) {
    case State::undefined: return "Undefined";
    case State::clearing: return "Clearing";
    case State::stopped: return "Stopped";
    case State::starting: return "Starting";
    case State::idle: return "Idle";
    case State::suspended: return "Suspended";
    case State::execute: return "Execute";
    case State::stopping: return "Stopping";
    case State::aborting: return "Aborting";
    case State::aborted: return "Aborted";
    case State::holding: return "Holding";
    case State::held: return "Held";
    case State::unholding: return "Unholding";
    case State::suspending: return "Suspending";
    case State::unsuspending: return "Unsuspending";
    case State::resetting: return "Resetting";
    case State::completing: return "Completing";
    case State::complete: return "Complete";
  }
  return "?";
}

constexpr std::string_view name(Command c) {
  switch (c) {
    case Command::none: return "None";
    case Command::reset: return "Reset";
    case Command::start: return "Start";
    case Command::stop: return "Stop";
    case Command::hold: return "Hold";
    case Command::unhold: return "Unhold";
    case Command::suspend: return "Suspend";
    case Command::unsuspend: return "Unsuspend";
    case Command::abort: return "Abort";
    case Command::clear: return "Clear";
  }
  return "?";
}

/// The state with this code (1..17), or nothing for any other value (0 included).
constexpr std::optional<State> state_from_code(int code) {
  if (code < 1 || code > 17) return std::nullopt;
  return static_cast<State>(code);
}

/// The command with this code (0..9), or nothing for any other value.
constexpr std::optional<Command> command_from_code(int code) {
  if (code < 0 || code > 9) return std::nullopt;
  return static_cast<Command>(code);
}

constexpr int code(State s) { return static_cast<int>(s); }
constexpr int code(Command c) { return static_cast<int>(c); }

}  // namespace fettle::packml
