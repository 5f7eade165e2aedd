#include "fettle/daemon/packml_machine.hpp"

#include <string>

namespace fettle::daemon {

using packml::Command;
using packml::State;

bool PackmlMachine::is_acting(State s) {
  switch (s) {
    case State::resetting:
    case State::starting:
    case State::completing:
    case State::holding:
    case State::unholding:
    case State::suspending:
    case State::unsuspending:
    case State::stopping:
    case State::aborting:
    case State::clearing:
    case State::execute:  // Execute ends with SC too (→ Completing)
      return true;
    default:
      return false;
  }
}

Result<State> PackmlMachine::target(State from, Command c) {
  auto refuse = [&] {
    return Error{"packml.not_allowed", "PackML command " + std::string(packml::name(c)) + " is not allowed in state " +
                                           std::string(packml::name(from))};
  };
  switch (c) {
    case Command::none:
      return refuse();
    case Command::abort:
      if (from == State::aborting || from == State::aborted) return refuse();
      return State::aborting;
    case Command::stop:
      if (from == State::stopped || from == State::stopping || from == State::clearing || from == State::aborting ||
          from == State::aborted)
        return refuse();
      return State::stopping;
    case Command::reset:
      if (from == State::stopped || from == State::complete) return State::resetting;
      return refuse();
    case Command::start:
      if (from == State::idle) return State::starting;
      return refuse();
    case Command::hold:
      if (from == State::execute || from == State::suspending || from == State::suspended ||
          from == State::unsuspending)
        return State::holding;
      return refuse();
    case Command::unhold:
      if (from == State::held) return State::unholding;
      return refuse();
    case Command::suspend:
      if (from == State::execute) return State::suspending;
      return refuse();
    case Command::unsuspend:
      if (from == State::suspended) return State::unsuspending;
      return refuse();
    case Command::clear:
      if (from == State::aborted) return State::clearing;
      return refuse();
  }
  return refuse();
}

Result<State> PackmlMachine::completion(State from) {
  switch (from) {
    case State::resetting: return State::idle;
    case State::starting: return State::execute;
    case State::execute: return State::completing;
    case State::completing: return State::complete;
    case State::holding: return State::held;
    case State::unholding: return State::execute;
    case State::suspending: return State::suspended;
    case State::unsuspending: return State::execute;
    case State::stopping: return State::stopped;
    case State::aborting: return State::aborted;
    case State::clearing: return State::stopped;
    default:
      return Error{"packml.not_acting",
                   "state " + std::string(packml::name(from)) + " is a wait state: only a command leaves it"};
  }
}

Result<State> PackmlMachine::command(Command c) {
  auto t = target(state_, c);
  if (t) {
    state_ = *t;
    ++transitions_;
  }
  return t;
}

Result<State> PackmlMachine::state_complete() {
  auto t = completion(state_);
  if (t) {
    state_ = *t;
    ++transitions_;
  }
  return t;
}

}  // namespace fettle::daemon
