// Interoperability: our PLC link against a PLC played by python3-pymodbus (not our code),
// mbpoll (not our code) reading the simulated PLC, and the `fettle-sim plc` program.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <regex>
#include <string>
#include <vector>

#include "../support/child.hpp"
#include "../support/sim_cell_file.hpp"
#include "event_log.hpp"

namespace plc = fettle::drivers::plc;
namespace packml = fettle::packml;
using fettle::test::Child;
using fettle::test::EventLog;
using fettle::test::run_capture;
using fettle::test::fast_options;
using std::chrono::milliseconds;

namespace {

constexpr milliseconds kWait{5000};
const std::string kPython = "/usr/bin/python3";  // Debian's, where python3-pymodbus lives
const std::string kScript = std::string(FETTLE_SOURCE_DIR) + "/tests/plc/pymodbus_plc.py";
const std::string kSim = std::string(FETTLE_BIN_DIR) + "/fettle-sim";

const std::regex kListening(R"(^listening 127\.0\.0\.1:(\d+)$)");

std::optional<int> listening_port(Child& c) {
  const auto m = c.wait_line(kListening, kWait);
  if (!m) return std::nullopt;
  return std::stoi((*m)[1].str());
}

bool pymodbus_available() {
  const std::string cmd = kPython + " -c 'import pymodbus.server.async_io' >/dev/null 2>&1";
  return std::system(cmd.c_str()) == 0;  // NOLINT(cert-env33-c)
}

TEST(PlcInterop, LinkTalksToAPymodbusPlcAndRecoversWhenItRestarts) {
  if (!pymodbus_available())
    GTEST_SKIP() << "python3-pymodbus (with python3-serial-asyncio) is not importable by " << kPython;
  const std::vector<std::string> argv{kPython, kScript, "--register-base", "40", "--recipe", "42", "--command", "3"};
  auto py = std::make_unique<Child>(argv);
  ASSERT_TRUE(py->started());
  const auto port = listening_port(*py);
  ASSERT_TRUE(port) << "pymodbus PLC did not report its port:\n" << py->output();

  EventLog events;
  auto options = fast_options(*port);
  options.register_base = 40;
  plc::Link link(events.executor(), options, events.handler());
  link.start();
  ASSERT_TRUE(events.wait_for<plc::LinkUp>(kWait)) << events.dump();

  // Heartbeat each way, cycle request and its acknowledge.
  ASSERT_TRUE(py->wait_line(std::regex("^fettle heartbeat running$"), kWait)) << py->output();
  const auto req = events.wait_for<plc::CycleRequest>(kWait);
  ASSERT_TRUE(req) << events.dump();
  EXPECT_EQ(req->recipe_id, 42);
  const auto slide = events.first<plc::SlideState>(kWait);
  ASSERT_TRUE(slide) << events.dump();
  EXPECT_EQ(slide->status, plc::SlideStatus::at_home);
  link.accept_cycle();
  ASSERT_TRUE(py->wait_line(std::regex("^accepted 42$"), kWait)) << py->output();

  // The PackML command the pymodbus PLC sends after the acknowledge (3 = Stop).
  const auto cmd = events.wait_for<plc::PackMLCommand>(kWait);
  ASSERT_TRUE(cmd) << events.dump();
  EXPECT_EQ(cmd->command, packml::Command::stop);
  ASSERT_TRUE(py->wait_line(std::regex("^command acknowledged$"), kWait)) << py->output();

  // State code and result as the PLC reads them.
  ASSERT_TRUE(link.set_state(packml::State::execute).ok());
  ASSERT_TRUE(py->wait_line(std::regex("^state 6$"), kWait)) << py->output();
  ASSERT_TRUE(link.report_result(plc::CycleResult::nok).ok());
  ASSERT_TRUE(py->wait_line(std::regex("^result 2$"), kWait)) << py->output();

  // The PLC goes away: link down; it comes back on the same port: link up again.
  py.reset();
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  ASSERT_TRUE(events.wait_for<plc::Reconnecting>(kWait));
  auto argv2 = argv;
  argv2.insert(argv2.end(), {"--port", std::to_string(*port)});
  py = std::make_unique<Child>(argv2);
  ASSERT_TRUE(listening_port(*py)) << py->output();
  ASSERT_TRUE(events.wait_for<plc::LinkUp>(kWait)) << events.dump();
  EXPECT_EQ(link.status().connects, 2);
}

// The handshakes of map version 2 with a PLC that is not Fettle's code: a slide move shorter than
// one poll (acknowledged and arrived in one update, never "moving") completes, and two results in a
// row both reach the PLC, in order, each acknowledged.
TEST(PlcInterop, SlideAndResultHandshakesWithAPymodbusPlc) {
  if (!pymodbus_available())
    GTEST_SKIP() << "python3-pymodbus (with python3-serial-asyncio) is not importable by " << kPython;
  Child py({kPython, kScript, "--recipe", "5"});
  ASSERT_TRUE(py.started());
  const auto port = listening_port(py);
  ASSERT_TRUE(port) << "pymodbus PLC did not report its port:\n" << py.output();
  EventLog events;
  plc::Link link(events.executor(), fast_options(*port), events.handler());
  link.start();
  ASSERT_TRUE(events.wait_for<plc::LinkUp>(kWait)) << events.dump();

  const auto command = link.command_slide(2);
  ASSERT_TRUE(command.ok());
  const auto arrived =
      events.wait_for<plc::SlideState>(kWait, [&](const plc::SlideState& s) { return s.reached(*command, 2); });
  ASSERT_TRUE(arrived) << events.dump() << py.output();
  ASSERT_TRUE(py.wait_line(std::regex("^slide to 2$"), kWait)) << py.output();
  for (const auto& s : events.all<plc::SlideState>())
    EXPECT_NE(s.status, plc::SlideStatus::moving) << "this PLC never reports moving: " << events.dump();

  ASSERT_TRUE(link.report_result(plc::CycleResult::nok).ok());
  ASSERT_TRUE(link.report_result(plc::CycleResult::fault).ok());
  ASSERT_TRUE(py.wait_line(std::regex("^result 2$"), kWait)) << py.output();
  ASSERT_TRUE(py.wait_line(std::regex("^result 4$"), kWait)) << py.output();
  ASSERT_TRUE(events.wait_for<plc::ResultAcknowledged>(
      kWait, [](const plc::ResultAcknowledged& r) { return r.result == plc::CycleResult::fault; }))
      << events.dump();
  EXPECT_EQ(link.status().results_waiting, 0);
}

TEST(PlcInterop, MbpollReadsTheSimulatedPlcHoldingRegisters) {
  if (!std::filesystem::exists("/usr/bin/mbpoll")) GTEST_SKIP() << "mbpoll is not installed";
  Child sim({kSim, "plc", "--listen", "127.0.0.1:0", "--run-for-s", "30"});
  ASSERT_TRUE(sim.started());
  const auto port = listening_port(sim);
  ASSERT_TRUE(port) << sim.output();
  int rc = 0;
  // mbpoll's references are 1-based: reference 1 is holding register 0 (interface_version).
  const auto out = run_capture("/usr/bin/mbpoll -m tcp -a 1 -r 1 -c 10 -t 4 -p " + std::to_string(*port) +
                                   " -1 127.0.0.1",
                               rc);
  ASSERT_EQ(rc, 0) << out;
  EXPECT_NE(out.find("[1]: \t2\n"), std::string::npos) << "interface_version should read 2:\n" << out;
  EXPECT_NE(out.find("[5]: \t1\n"), std::string::npos) << "slide_state should read 1 (at home):\n" << out;
  EXPECT_NE(out.find("[10]: \t"), std::string::npos) << out;
}

TEST(PlcInterop, FettleSimPlcProgramTakesCommandsOnStdin) {
  Child sim({kSim, "plc", "--listen", "127.0.0.1:0", "--heartbeat-period-ms", "20", "--run-for-s", "30"});
  ASSERT_TRUE(sim.started());
  const auto port = listening_port(sim);
  ASSERT_TRUE(port) << sim.output();
  EventLog events;
  plc::Link link(events.executor(), fast_options(*port), events.handler());
  link.start();
  ASSERT_TRUE(events.wait_for<plc::LinkUp>(kWait)) << events.dump();
  sim.write_line("part 9");
  const auto req = events.wait_for<plc::CycleRequest>(kWait);
  ASSERT_TRUE(req) << events.dump() << sim.output();
  EXPECT_EQ(req->recipe_id, 9);
  link.accept_cycle();
  ASSERT_TRUE(sim.wait_line(std::regex("accepted the cycle request for recipe 9"), kWait)) << sim.output();
  sim.write_line("freeze on");
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  EXPECT_EQ(down->reason, plc::LinkDownReason::heartbeat_stale);
  sim.write_line("freeze off");
  ASSERT_TRUE(events.wait_for<plc::LinkUp>(kWait)) << events.dump();
  sim.write_line("teleport");
  ASSERT_TRUE(sim.wait_line(std::regex("^error .*unknown command"), kWait)) << sim.output();
}

// A cell assembled from the separate simulators: `fettle-sim plc --cell` listens where the cell
// file's [plc] says, and fettled's link to that address comes up.
TEST(PlcInterop, FettleSimPlcWithACellFileListensWhereTheCellSays) {
  char tmpl[] = "/tmp/fettle-plc-cell-XXXXXX";
  ASSERT_NE(::mkdtemp(tmpl), nullptr);
  const std::filesystem::path dir(tmpl);
  const int port = fettle::test::free_tcp_port();
  const auto cell = fettle::test::write_sim_cell(dir, {port, fettle::test::free_tcp_port(), 1});
  Child sim({kSim, "plc", "--cell", cell.string(), "--heartbeat-period-ms", "20", "--run-for-s", "30"});
  ASSERT_TRUE(sim.started());
  const auto listening = listening_port(sim);
  ASSERT_TRUE(listening) << sim.output();
  EXPECT_EQ(*listening, port);
  EventLog events;
  plc::Link link(events.executor(), fast_options(port), events.handler());
  link.start();
  EXPECT_TRUE(events.wait_for<plc::LinkUp>(kWait)) << events.dump() << sim.output();
  link.stop();
  std::filesystem::remove_all(dir);
}

TEST(PlcInterop, FettleSimPlcRejectsABadListenAddress) {
  int rc = 0;
  const auto out = run_capture(kSim + " plc --listen 127.0.0.1:99999 --run-for-s 1", rc);
  EXPECT_EQ(rc, 1) << out;
  EXPECT_NE(out.find("port must be"), std::string::npos) << out;
}

}  // namespace
