#pragma once
// The PackML state machine (ANSI/ISA-TR88.00.02): 17 states, the standard commands and the
// state-complete (SC) transitions of the acting states. Pure logic, no I/O: the runtime
// applies commands, performs each acting state's work and calls state_complete() when done.
// State and command codes are those of fettle::packml (drivers/packml.hpp), mirrored to the PLC.
//
//   Stopped  --Reset-->  Resetting --SC--> Idle --Start--> Starting --SC--> Execute
//   Execute  --SC--> Completing --SC--> Complete --Reset--> Resetting
//   Execute/Suspending/Suspended/Unsuspending --Hold--> Holding --SC--> Held --Unhold--> Unholding --SC--> Execute
//   Execute  --Suspend--> Suspending --SC--> Suspended --Unsuspend--> Unsuspending --SC--> Execute
//   any but Stopped/Stopping/Clearing/Aborting/Aborted --Stop--> Stopping --SC--> Stopped
//   any but Aborting/Aborted --Abort--> Aborting --SC--> Aborted --Clear--> Clearing --SC--> Stopped
#include <string>

#include "fettle/core/result.hpp"
#include "fettle/drivers/packml.hpp"

namespace fettle::daemon {

class PackmlMachine {
 public:
  explicit PackmlMachine(packml::State initial = packml::State::stopped) : state_(initial) {}

  [[nodiscard]] packml::State state() const { return state_; }
  /// Acting states (…ing) end by state_complete(); wait states end only by a command.
  [[nodiscard]] static bool is_acting(packml::State s);
  /// The state `command` leads to from `from`, or an Error (code "packml.not_allowed") naming both.
  [[nodiscard]] static Result<packml::State> target(packml::State from, packml::Command command);
  /// The state an acting state's SC leads to; an Error for wait states.
  [[nodiscard]] static Result<packml::State> completion(packml::State from);

  /// Applies a command: the new state, or an Error (state unchanged).
  Result<packml::State> command(packml::Command command);
  /// The current acting state is complete: the new state, or an Error for wait states.
  Result<packml::State> state_complete();
  /// Counts every transition (for status and tests).
  [[nodiscard]] long long transitions() const { return transitions_; }

 private:
  packml::State state_;
  long long transitions_ = 0;
};

}  // namespace fettle::daemon
