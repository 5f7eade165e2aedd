// The PackML state machine: every state, command and state-complete transition of ISA-TR88.
#include <gtest/gtest.h>

#include <set>

#include "fettle/daemon/packml_machine.hpp"

using fettle::daemon::PackmlMachine;
using fettle::packml::Command;
using fettle::packml::State;

namespace {

const std::vector<State> kAll{State::clearing, State::stopped,   State::starting,  State::idle,
                              State::suspended, State::execute,  State::stopping,  State::aborting,
                              State::aborted,  State::holding,   State::held,      State::unholding,
                              State::suspending, State::unsuspending, State::resetting, State::completing,
                              State::complete};

State after(State from, Command c) {
  auto r = PackmlMachine::target(from, c);
  return r ? *r : State::undefined;
}

}  // namespace

TEST(PackML, SeventeenStatesWithTheirTr88Codes) {
  ASSERT_EQ(kAll.size(), 17U);
  std::set<int> codes;
  for (auto s : kAll) codes.insert(fettle::packml::code(s));
  EXPECT_EQ(codes.size(), 17U);
  EXPECT_EQ(*codes.begin(), 1);
  EXPECT_EQ(*codes.rbegin(), 17);
  EXPECT_EQ(fettle::packml::code(State::execute), 6);
  EXPECT_EQ(fettle::packml::code(State::aborted), 9);
  EXPECT_EQ(fettle::packml::code(State::held), 11);
}

TEST(PackML, ProductionPathFromStoppedToExecuteAndComplete) {
  PackmlMachine m;
  EXPECT_EQ(m.state(), State::stopped);
  EXPECT_EQ(*m.command(Command::reset), State::resetting);
  EXPECT_EQ(*m.state_complete(), State::idle);
  EXPECT_EQ(*m.command(Command::start), State::starting);
  EXPECT_EQ(*m.state_complete(), State::execute);
  EXPECT_EQ(*m.state_complete(), State::completing);
  EXPECT_EQ(*m.state_complete(), State::complete);
  EXPECT_EQ(*m.command(Command::reset), State::resetting);
  EXPECT_EQ(m.transitions(), 7);
}

TEST(PackML, HoldSuspendStopAbortClear) {
  EXPECT_EQ(after(State::execute, Command::hold), State::holding);
  EXPECT_EQ(*PackmlMachine::completion(State::holding), State::held);
  EXPECT_EQ(after(State::held, Command::unhold), State::unholding);
  EXPECT_EQ(*PackmlMachine::completion(State::unholding), State::execute);
  EXPECT_EQ(after(State::execute, Command::suspend), State::suspending);
  EXPECT_EQ(*PackmlMachine::completion(State::suspending), State::suspended);
  EXPECT_EQ(after(State::suspended, Command::unsuspend), State::unsuspending);
  EXPECT_EQ(*PackmlMachine::completion(State::unsuspending), State::execute);
  EXPECT_EQ(after(State::suspended, Command::hold), State::holding);
  EXPECT_EQ(*PackmlMachine::completion(State::stopping), State::stopped);
  EXPECT_EQ(*PackmlMachine::completion(State::aborting), State::aborted);
  EXPECT_EQ(after(State::aborted, Command::clear), State::clearing);
  EXPECT_EQ(*PackmlMachine::completion(State::clearing), State::stopped);
}

TEST(PackML, AbortFromEveryStateButAbortingAndAborted) {
  for (auto s : kAll) {
    const bool allowed = s != State::aborting && s != State::aborted;
    EXPECT_EQ(after(s, Command::abort) == State::aborting, allowed) << fettle::packml::name(s);
  }
}

TEST(PackML, StopFromEveryStateButTheStoppedAndAbortBranch) {
  for (auto s : kAll) {
    const bool allowed = s != State::stopped && s != State::stopping && s != State::clearing &&
                         s != State::aborting && s != State::aborted;
    EXPECT_EQ(after(s, Command::stop) == State::stopping, allowed) << fettle::packml::name(s);
  }
}

TEST(PackML, RefusedCommandsLeaveTheStateAndSayWhy) {
  PackmlMachine m(State::held);
  auto r = m.command(Command::start);
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().code, "packml.not_allowed");
  EXPECT_NE(r.error().message.find("Start"), std::string::npos);
  EXPECT_NE(r.error().message.find("Held"), std::string::npos);
  EXPECT_EQ(m.state(), State::held);
  EXPECT_FALSE(m.command(Command::reset));  // Reset only from Stopped / Complete
  EXPECT_FALSE(m.command(Command::none));
  EXPECT_FALSE(m.state_complete());  // a wait state
  EXPECT_EQ(m.transitions(), 0);
}

TEST(PackML, WaitStatesHaveNoStateComplete) {
  for (auto s : {State::stopped, State::idle, State::held, State::suspended, State::complete, State::aborted})
    EXPECT_FALSE(PackmlMachine::completion(s)) << fettle::packml::name(s);
  for (auto s : kAll)
    EXPECT_EQ(PackmlMachine::is_acting(s), static_cast<bool>(PackmlMachine::completion(s))) << fettle::packml::name(s);
}
