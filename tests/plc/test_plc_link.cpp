// The PLC link against the simulated PLC, over Modbus TCP on 127.0.0.1 (ephemeral ports):
// one test per message and per fault; after each fault the link must recover.
#include <gtest/gtest.h>

#include <chrono>
#include <thread>

#include "event_log.hpp"
#include "fettle/sim/plc.hpp"

namespace plc = fettle::drivers::plc;
namespace packml = fettle::packml;
using fettle::sim::PlcSimOptions;
using fettle::sim::PlcSimulator;
using fettle::test::EventLog;
using fettle::test::fast_options;
using std::chrono::milliseconds;

namespace {

constexpr milliseconds kWait{3000};

PlcSimOptions sim_options() {
  PlcSimOptions o;
  o.photo_positions_mm = {0.0, 120.0};
  o.home_mm = -60.0;
  o.slide_speed_mm_s = 1200.0;  // home → position 2: 180 mm in 150 ms
  o.heartbeat_period_ms = 20;
  o.fettle_heartbeat_timeout_ms = 300;
  return o;
}

/// Polls `pred` on the simulator's snapshot until it holds or `timeout` passes.
template <class Pred>
bool sim_until(const PlcSimulator& sim, Pred pred, milliseconds timeout = kWait) {
  const auto end = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < end) {
    if (pred(sim.snapshot())) return true;
    std::this_thread::sleep_for(milliseconds(5));
  }
  return pred(sim.snapshot());
}

class PlcLinkTest : public ::testing::Test {
 protected:
  void SetUp() override { start_sim(sim_options()); }

  void start_sim(PlcSimOptions o) {
    sim = std::make_unique<PlcSimulator>(std::move(o));
    sim->start();
  }

  void start_link(plc::LinkOptions o) {
    link = std::make_unique<plc::Link>(events.executor(), std::move(o), events.handler());
    link->start();
  }

  void start_link() { start_link(fast_options(sim->port())); }

  void expect_up() {
    ASSERT_TRUE(events.wait_for<plc::LinkUp>(kWait)) << "no LinkUp; events:\n" << events.dump();
  }

  EventLog events;  // declared first: destroyed after the link
  std::unique_ptr<PlcSimulator> sim;
  std::unique_ptr<plc::Link> link;
};

TEST_F(PlcLinkTest, ComesUpAndReportsTheSlide) {
  start_link();
  expect_up();
  const auto slide = events.wait_for<plc::SlideState>(kWait);
  ASSERT_TRUE(slide);
  EXPECT_EQ(slide->status, plc::SlideStatus::at_home);
  EXPECT_EQ(slide->position, 0);
  EXPECT_TRUE(link->status().up);
  EXPECT_EQ(link->status().connects, 1);
}

// The device lifecycle (device.hpp): configure() checks, activate() starts the thread and the
// link comes up, deactivate() stops it (no event after), and a second activate() comes up again.
TEST_F(PlcLinkTest, TheLinkGoesThroughTheDeviceLifecycle) {
  link = std::make_unique<plc::Link>(events.executor(), fast_options(sim->port()), events.handler());
  EXPECT_EQ(link->kind(), "plc");
  EXPECT_EQ(link->lifecycle(), fettle::drivers::Lifecycle::unconfigured);
  const auto early = link->activate();
  ASSERT_FALSE(early.ok());
  EXPECT_EQ(early.error().code, "plc.lifecycle");
  ASSERT_TRUE(link->configure().ok());
  ASSERT_TRUE(link->activate().ok());
  EXPECT_EQ(link->lifecycle(), fettle::drivers::Lifecycle::active);
  expect_up();
  link->deactivate();
  EXPECT_EQ(link->lifecycle(), fettle::drivers::Lifecycle::inactive);
  EXPECT_FALSE(link->status().connected);
  const int connects = link->status().connects;
  ASSERT_TRUE(link->activate().ok());
  const auto end = std::chrono::steady_clock::now() + kWait;
  while (std::chrono::steady_clock::now() < end && !(link->status().connects > connects && link->status().up))
    std::this_thread::sleep_for(milliseconds(5));
  EXPECT_GT(link->status().connects, connects) << events.dump();
  EXPECT_TRUE(link->status().up) << events.dump();
}

TEST_F(PlcLinkTest, ConfigureRefusesOptionsThatCannotWorkNamingTheKey) {
  auto o = fast_options(sim->port());
  o.heartbeat_timeout_ms = o.poll_period_ms;
  link = std::make_unique<plc::Link>(events.executor(), o, events.handler());
  auto st = link->configure();
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.error().code, "plc.config");
  EXPECT_NE(st.error().message.find("[plc] heartbeat_timeout_ms"), std::string::npos) << st.error().message;
  EXPECT_EQ(link->lifecycle(), fettle::drivers::Lifecycle::unconfigured);
  o = fast_options(sim->port());
  o.address = "plc.local";
  link = std::make_unique<plc::Link>(events.executor(), o, events.handler());
  st = link->configure();
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.error().message.find("[plc] address 'plc.local' is not an IPv4 address"), std::string::npos)
      << st.error().message;
}

TEST_F(PlcLinkTest, HeartbeatRunsBothWays) {
  start_link();
  expect_up();
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.fettle_heartbeat_ok; }));
  const auto first = sim->snapshot().fettle.heartbeat;
  ASSERT_TRUE(sim_until(*sim, [first](const auto& s) { return s.fettle.heartbeat != first; }));
  const auto plc_hb = link->status().inputs.heartbeat;
  std::this_thread::sleep_for(milliseconds(100));
  EXPECT_NE(link->status().inputs.heartbeat, plc_hb);
  EXPECT_TRUE(link->status().up);
}

TEST_F(PlcLinkTest, CycleRequestIsPostedOnceAndAcknowledgedByToggle) {
  start_link();
  expect_up();
  sim->part_arrives(7);
  const auto req = events.wait_for<plc::CycleRequest>(kWait);
  ASSERT_TRUE(req) << events.dump();
  EXPECT_EQ(req->recipe_id, 7);
  std::this_thread::sleep_for(milliseconds(100));
  EXPECT_EQ(sim->snapshot().cycles_accepted, 0);
  EXPECT_EQ(events.all<plc::CycleRequest>().size(), 1U) << "pending request posted more than once";
  link->accept_cycle();
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.cycles_accepted == 1; }));
  sim->part_arrives(8);
  const auto next = events.wait_for<plc::CycleRequest>(kWait);
  ASSERT_TRUE(next);
  EXPECT_EQ(next->recipe_id, 8);
}

TEST_F(PlcLinkTest, SlideCommandTravelsAndArrives) {
  start_link();
  expect_up();
  ASSERT_TRUE(link->command_slide(2).ok());
  const auto moving = events.wait_for<plc::SlideState>(
      kWait, [](const plc::SlideState& s) { return s.status == plc::SlideStatus::moving; });
  ASSERT_TRUE(moving) << events.dump();
  EXPECT_EQ(moving->position, 2);
  const auto arrived = events.wait_for<plc::SlideState>(kWait);
  ASSERT_TRUE(arrived);
  EXPECT_EQ(arrived->status, plc::SlideStatus::at_position);
  EXPECT_EQ(arrived->position, 2);
  EXPECT_DOUBLE_EQ(sim->snapshot().slide_mm, 120.0);
  ASSERT_TRUE(link->command_slide(0).ok());
  const auto home = events.wait_for<plc::SlideState>(
      kWait, [](const plc::SlideState& s) { return s.status == plc::SlideStatus::at_home; });
  ASSERT_TRUE(home) << events.dump();
  EXPECT_DOUBLE_EQ(sim->snapshot().slide_mm, -60.0);
}

// A slide command is done only when the PLC acknowledged it (slide_command_ack) and reports the
// slide at its target: an earlier "at position" is never taken for the new command.
TEST_F(PlcLinkTest, ASlideMoveIsDoneOnlyOnceThePlcAcknowledgedItsCommand) {
  start_link();
  expect_up();
  const auto first = link->command_slide(2);
  ASSERT_TRUE(first.ok());
  EXPECT_EQ(*first, 1U);
  const auto done = [](std::uint64_t number, int target) {
    return [=](const plc::SlideState& s) { return s.reached(number, target); };
  };
  ASSERT_TRUE(events.wait_for<plc::SlideState>(kWait, done(*first, 2)))
      << events.dump();
  // Again to the same position: the slide is there already, yet the command counts only once the
  // PLC took it.
  const auto second = link->command_slide(2);
  ASSERT_TRUE(second.ok());
  EXPECT_EQ(*second, 2U);
  const auto again = events.wait_for<plc::SlideState>(kWait, done(*second, 2));
  ASSERT_TRUE(again) << events.dump();
  EXPECT_EQ(sim->registers().at(plc::reg::slide_command_ack), sim->registers().at(plc::reg::slide_command_toggle));
}

// Results go out one at a time: the next only once the PLC acknowledged the last (cycle_result_ack),
// so a PLC never loses one, even when two come within one of its scans.
TEST_F(PlcLinkTest, ResultsWaitForThePlcsAcknowledgeAndNoneIsLost) {
  start_link();
  expect_up();
  ASSERT_TRUE(sim->apply("results-ack off").ok());
  ASSERT_TRUE(link->report_result(plc::CycleResult::ok).ok());
  ASSERT_TRUE(link->report_result(plc::CycleResult::fault).ok());
  EXPECT_EQ(link->status().results_waiting, 2);
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.results.size() == 1; }));
  std::this_thread::sleep_for(milliseconds(150));  // several polls: the second must wait
  EXPECT_EQ(sim->snapshot().results, std::vector<plc::CycleResult>{plc::CycleResult::ok});
  EXPECT_EQ(link->status().results_waiting, 2);
  EXPECT_TRUE(events.all<plc::ResultAcknowledged>().empty());
  ASSERT_TRUE(sim->apply("results-ack on").ok());
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.results.size() == 2; }));
  EXPECT_EQ(sim->snapshot().results, (std::vector<plc::CycleResult>{plc::CycleResult::ok, plc::CycleResult::fault}));
  const auto acked = events.wait_for<plc::ResultAcknowledged>(
      kWait, [](const plc::ResultAcknowledged& r) { return r.result == plc::CycleResult::fault; });
  ASSERT_TRUE(acked) << events.dump();
  EXPECT_EQ(link->status().results_waiting, 0);
}

// When fettled starts, acknowledges the PLC holds from before are taken as what they say: none of
// Fettle's slide commands or results is pending, so the PLC neither moves nor reads a result.
TEST_F(PlcLinkTest, AtStartNothingOfFettlesIsPendingWhateverThePlcAcknowledged) {
  sim->force_register(plc::reg::slide_command_ack, 1);
  sim->force_register(plc::reg::cycle_result_ack, 1);
  start_link();
  expect_up();
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.fettle_written; }));
  const auto regs = sim->registers();
  EXPECT_EQ(regs.at(plc::reg::slide_command_toggle), 1);
  EXPECT_EQ(regs.at(plc::reg::cycle_result_toggle), 1);
  EXPECT_EQ(link->status().results_waiting, 0);
}

TEST_F(PlcLinkTest, PackMLStateCodeReachesThePlc) {
  start_link();
  expect_up();
  ASSERT_TRUE(link->set_state(packml::State::execute).ok());
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.fettle.state == packml::State::execute; }));
  ASSERT_TRUE(link->set_state(packml::State::held).ok());
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.fettle.state == packml::State::held; }));
  EXPECT_EQ(sim->registers().at(plc::reg::packml_state), 11);
}

// fettled passes through acting states within microseconds (Resetting -> Idle, Starting ->
// Execute): each is on the register for a poll of its own, in order, so the PLC sees them all.
TEST_F(PlcLinkTest, EveryStateReachesThePlcInOrderEvenTransientOnes) {
  start_link();
  expect_up();
  using S = packml::State;
  const std::vector<S> path{S::resetting, S::idle, S::starting, S::execute, S::holding, S::held};
  for (const auto s : path) ASSERT_TRUE(link->set_state(s).ok());
  ASSERT_TRUE(link->set_state(S::held).ok());  // the same state again is no new state
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.fettle.state == packml::State::held; }));
  const auto seen = sim->snapshot().states;
  ASSERT_GE(seen.size(), path.size());
  const std::vector<S> tail(seen.end() - static_cast<std::ptrdiff_t>(path.size()), seen.end());
  EXPECT_EQ(tail, path);
}

TEST_F(PlcLinkTest, CycleResultsReachThePlcEachOnce) {
  start_link();
  expect_up();
  ASSERT_TRUE(link->report_result(plc::CycleResult::ok).ok());
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.results.size() == 1; }));
  ASSERT_TRUE(link->report_result(plc::CycleResult::nok).ok());
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.results.size() == 2; }));
  ASSERT_TRUE(link->report_result(plc::CycleResult::regrind).ok());
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.results.size() == 3; }));
  const std::vector<plc::CycleResult> expected{plc::CycleResult::ok, plc::CycleResult::nok,
                                               plc::CycleResult::regrind};
  EXPECT_EQ(sim->snapshot().results, expected);
}

TEST_F(PlcLinkTest, LatchedFaultIsClearedOnlyByPlcReset) {
  start_link();
  expect_up();
  ASSERT_TRUE(link->raise_fault(42).ok());
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.fettle.fault_latched && s.fettle.fault_code == 42; }));
  ASSERT_TRUE(link->raise_fault(43).ok());  // first fault stays
  sim->send_command(packml::Command::stop);
  ASSERT_TRUE(events.wait_for<plc::PackMLCommand>(
      kWait, [](const plc::PackMLCommand& c) { return c.command == packml::Command::stop; }));
  std::this_thread::sleep_for(milliseconds(60));
  auto s = sim->snapshot();
  EXPECT_TRUE(s.fettle.fault_latched);
  EXPECT_EQ(s.fettle.fault_code, 42);
  sim->send_command(packml::Command::reset);
  ASSERT_TRUE(events.wait_for<plc::PackMLCommand>(
      kWait, [](const plc::PackMLCommand& c) { return c.command == packml::Command::reset; }));
  ASSERT_TRUE(sim_until(*sim, [](const auto& s2) { return !s2.fettle.fault_latched && s2.fettle.fault_code == 0; }));
}

class PlcCommandTest : public PlcLinkTest, public ::testing::WithParamInterface<packml::Command> {};

TEST_P(PlcCommandTest, PackMLCommandFromThePlcIsPostedAndAcknowledged) {
  start_link();
  expect_up();
  sim->send_command(GetParam());
  const auto c = events.wait_for<plc::PackMLCommand>(kWait);
  ASSERT_TRUE(c) << events.dump();
  EXPECT_EQ(c->command, GetParam());
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.commands_acknowledged == 1; }));
  EXPECT_EQ(events.all<plc::PackMLCommand>().size(), 1U);
}

INSTANTIATE_TEST_SUITE_P(AllCommands, PlcCommandTest,
                         ::testing::Values(packml::Command::reset, packml::Command::start, packml::Command::stop,
                                           packml::Command::hold, packml::Command::unhold, packml::Command::abort,
                                           packml::Command::clear),
                         [](const auto& p) { return std::string(packml::name(p.param)); });

TEST_F(PlcLinkTest, StaleCommandFromBeforeStartIsNotObeyed) {
  sim->send_command(packml::Command::start);
  ASSERT_TRUE(sim_until(*sim, [](const auto& s) { return s.plc.command_toggle == 1; }));
  start_link();
  expect_up();
  std::this_thread::sleep_for(milliseconds(150));
  EXPECT_TRUE(events.all<plc::PackMLCommand>().empty()) << events.dump();
  sim->send_command(packml::Command::reset);
  const auto c = events.wait_for<plc::PackMLCommand>(kWait);
  ASSERT_TRUE(c);
  EXPECT_EQ(c->command, packml::Command::reset);
}

TEST_F(PlcLinkTest, InvalidCommandsAreRefusedWithAReason) {
  start_link();
  EXPECT_EQ(link->command_slide(3).error().code, "plc.bad_slide_target");
  EXPECT_EQ(link->command_slide(-1).error().code, "plc.bad_slide_target");
  EXPECT_EQ(link->raise_fault(0).error().code, "plc.bad_fault_code");
  EXPECT_EQ(link->set_state(packml::State::undefined).error().code, "plc.bad_state");
  EXPECT_EQ(link->report_result(plc::CycleResult::none).error().code, "plc.bad_result");
}

// ---- faults ----

TEST_F(PlcLinkTest, DroppedConnectionGoesDownAndReconnects) {
  start_link();
  expect_up();
  sim->drop_connections();
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  EXPECT_EQ(down->reason, plc::LinkDownReason::io_error) << down->detail;
  const auto again = events.wait_for<plc::Reconnecting>(kWait);
  ASSERT_TRUE(again);
  EXPECT_EQ(again->attempt, 1);
  EXPECT_EQ(again->delay_ms, 20);
  expect_up();
  EXPECT_EQ(link->status().connects, 2);
}

TEST_F(PlcLinkTest, FrozenPlcHeartbeatIsALinkFaultUntilItRuns) {
  start_link();
  expect_up();
  sim->freeze_heartbeat(true);
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  EXPECT_EQ(down->reason, plc::LinkDownReason::heartbeat_stale);
  EXPECT_FALSE(link->status().up);
  // While the PLC is stale, its requests are not acted upon.
  sim->part_arrives(5);
  std::this_thread::sleep_for(milliseconds(100));
  EXPECT_TRUE(events.all<plc::CycleRequest>().empty());
  sim->freeze_heartbeat(false);
  expect_up();
  EXPECT_EQ(link->status().connects, 1) << "a stale heartbeat must not need a reconnect";
  ASSERT_TRUE(events.wait_for<plc::CycleRequest>(kWait));
}

TEST_F(PlcLinkTest, SlideFaultIsReportedAndClearedByReset) {
  start_link();
  expect_up();
  sim->slide_fault(true);
  const auto fault = events.wait_for<plc::SlideState>(
      kWait, [](const plc::SlideState& s) { return s.status == plc::SlideStatus::fault; });
  ASSERT_TRUE(fault) << events.dump();
  ASSERT_TRUE(link->command_slide(1).ok());  // a faulted slide does not move
  std::this_thread::sleep_for(milliseconds(100));
  EXPECT_EQ(sim->snapshot().plc.slide_status, plc::SlideStatus::fault);
  sim->send_command(packml::Command::reset);
  ASSERT_TRUE(events.wait_for<plc::SlideState>(
      kWait, [](const plc::SlideState& s) { return s.status == plc::SlideStatus::at_home; }))
      << events.dump();
}

TEST_F(PlcLinkTest, OutOfRangeValueIsAFaultNeverAGuess) {
  // A non-zero register base, to check the address in the event.
  sim.reset();
  auto o = sim_options();
  o.register_base = 100;
  start_sim(o);
  auto lo = fast_options(sim->port());
  lo.register_base = 100;
  start_link(lo);
  expect_up();
  sim->force_register(plc::reg::slide_state, 9);
  const auto bad = events.wait_for<plc::ValueOutOfRange>(kWait);
  ASSERT_TRUE(bad) << events.dump();
  EXPECT_EQ(bad->address, 104);
  EXPECT_EQ(bad->offset, plc::reg::slide_state);
  EXPECT_EQ(bad->value, 9);
  EXPECT_NE(bad->allowed.find("4 (fault)"), std::string::npos);
  // Nothing from the bad block is acted upon, and the violation is posted once.
  sim->part_arrives(3);
  std::this_thread::sleep_for(milliseconds(150));
  EXPECT_TRUE(events.all<plc::CycleRequest>().empty());
  EXPECT_EQ(events.all<plc::ValueOutOfRange>().size(), 1U);
  sim->release_register(plc::reg::slide_state);
  const auto req = events.wait_for<plc::CycleRequest>(kWait);
  ASSERT_TRUE(req);
  EXPECT_EQ(req->recipe_id, 3);
}

TEST_F(PlcLinkTest, CycleRequestWithoutRecipeIsOutOfRange) {
  start_link();
  expect_up();
  sim->force_register(plc::reg::cycle_request_toggle, 1);  // request toggled, recipe_id still 0
  const auto bad = events.wait_for<plc::ValueOutOfRange>(kWait);
  ASSERT_TRUE(bad) << events.dump();
  EXPECT_EQ(bad->offset, plc::reg::recipe_id);
  EXPECT_EQ(bad->value, 0);
  EXPECT_TRUE(events.all<plc::CycleRequest>().empty());
}

// A PLC program written for map version 1 (no slide or result acknowledges) never comes up.
TEST_F(PlcLinkTest, WrongInterfaceVersionNeverComesUp) {
  sim->force_register(plc::reg::interface_version, 1);
  start_link();
  const auto bad = events.wait_for<plc::ValueOutOfRange>(kWait);
  ASSERT_TRUE(bad) << events.dump();
  EXPECT_EQ(bad->offset, plc::reg::interface_version);
  std::this_thread::sleep_for(milliseconds(100));
  EXPECT_TRUE(events.all<plc::LinkUp>().empty());
  sim->release_all_registers();
  expect_up();
}

TEST_F(PlcLinkTest, SlowRepliesTimeOutAndRecover) {
  start_link();
  expect_up();
  sim->set_reply_delay_ms(300);  // > response_timeout_ms 150
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  EXPECT_EQ(down->reason, plc::LinkDownReason::timeout) << down->detail;
  sim->set_reply_delay_ms(0);
  expect_up();
}

TEST_F(PlcLinkTest, StoppedServerIsRetriedWithBackoffAndRecovers) {
  start_link();
  expect_up();
  const int port = sim->port();
  sim.reset();  // the PLC goes away
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  // Back-off 20, 40, 80, 160, 160 ms (fast_options) between attempts.
  for (int i = 0; i < 5; ++i) ASSERT_TRUE(events.wait_for<plc::Reconnecting>(kWait)) << events.dump();
  const auto tries = events.all<plc::Reconnecting>();
  const std::vector<int> expected{20, 40, 80, 160, 160};
  for (std::size_t i = 0; i < expected.size(); ++i) {
    EXPECT_EQ(tries[i].attempt, static_cast<int>(i) + 1);
    EXPECT_EQ(tries[i].delay_ms, expected[i]);
  }
  EXPECT_EQ(events.all<plc::LinkDown>().size(), 1U) << "one LinkDown per outage, not per attempt";
  auto o = sim_options();
  o.port = port;
  start_sim(o);
  expect_up();
  EXPECT_GE(link->status().connect_attempts, 6);
  // The back-off starts over after recovery.
  sim->drop_connections();
  ASSERT_TRUE(events.wait_for<plc::Reconnecting>(kWait, [](const auto& r) { return r.delay_ms == 20; }));
}

TEST_F(PlcLinkTest, NoPlcAtStartIsConnectFailedThenRecovers) {
  const int port = sim->port();
  sim.reset();
  start_link(fast_options(port));
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down);
  EXPECT_EQ(down->reason, plc::LinkDownReason::connect_failed);
  EXPECT_NE(down->detail.find("127.0.0.1:" + std::to_string(port)), std::string::npos) << down->detail;
  auto o = sim_options();
  o.port = port;
  start_sim(o);
  expect_up();
}

TEST_F(PlcLinkTest, StopIsPromptEvenDuringALongBackoff) {
  const int port = sim->port();
  sim.reset();
  auto o = fast_options(port);
  o.reconnect_initial_ms = 5000;
  o.reconnect_max_ms = 5000;
  start_link(o);
  ASSERT_TRUE(events.wait_for<plc::Reconnecting>(kWait));
  const auto t0 = std::chrono::steady_clock::now();
  link->stop();
  EXPECT_LT(std::chrono::steady_clock::now() - t0, milliseconds(1000));
}

// ---- the simulator's own inputs ----

TEST(PlcSimScript, ParsesTimedLinesAndNamesBadOnes) {
  const auto ok = fettle::sim::parse_plc_script("# faults\npart 3\nat 1.5 freeze on\nat 0.5 drop\n\n");
  ASSERT_TRUE(ok);
  ASSERT_EQ(ok->size(), 3U);
  EXPECT_EQ((*ok)[0].command, "part 3");
  EXPECT_EQ((*ok)[1].command, "drop");  // sorted by time
  EXPECT_DOUBLE_EQ((*ok)[2].at_s, 1.5);
  const auto bad = fettle::sim::parse_plc_script("part 1\nat soon drop\n");
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("line 2"), std::string::npos);
}

TEST(PlcSimCommands, ApplyRejectsUnknownAndBadArguments) {
  PlcSimulator sim(sim_options());
  EXPECT_TRUE(sim.apply("part 12").ok());
  EXPECT_TRUE(sim.apply("force 4 9").ok());
  EXPECT_FALSE(sim.apply("force 40 9").ok());
  EXPECT_FALSE(sim.apply("part 0").ok());
  EXPECT_FALSE(sim.apply("freeze maybe").ok());
  EXPECT_FALSE(sim.apply("teleport").ok());
}

TEST_F(PlcLinkTest, ScriptedPartsArriveAtTheirTimes) {
  start_link();
  expect_up();
  auto script = fettle::sim::parse_plc_script("at 0.05 part 21\nat 0.1 slide-fault on\n");
  ASSERT_TRUE(script);
  sim->run_script(*script);
  const auto req = events.wait_for<plc::CycleRequest>(kWait);
  ASSERT_TRUE(req);
  EXPECT_EQ(req->recipe_id, 21);
  ASSERT_TRUE(events.wait_for<plc::SlideState>(
      kWait, [](const plc::SlideState& s) { return s.status == plc::SlideStatus::fault; }));
}

}  // namespace
