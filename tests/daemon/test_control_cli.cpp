// `fettle status` and `fettle cycles` (the built CLI in FETTLE_BIN_DIR) against a control
// server in this process, and against no server.
#include <filesystem>
#include <fstream>
#include <regex>
#include <string>

#include <gtest/gtest.h>

#include "test_control_support.hpp"
#include "test_systemd_support.hpp"

namespace {

namespace fs = std::filesystem;
using fettle::daemon::control::json;
using fettle::test::ControlFixture;
using fettle::test::quote;

const std::string fettle_cli = std::string(FETTLE_BIN_DIR) + "/fettle";

fettle::test::Run fettle(const std::string& args) { return fettle::test::run(quote(fettle_cli) + " " + args); }

using CliStatus = ControlFixture;

TEST_F(CliStatus, HumanReadableByDefault) {
  ASSERT_TRUE(start());
  const auto r = fettle("status --socket " + quote(socket().string()));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("state         Idle (code 4)"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("maintenance   off"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("fault         none"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("uptime        1 h 2 min 5 s"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("socket        " + socket().string()), std::string::npos) << r.output;
  EXPECT_EQ(r.output.find('{'), std::string::npos) << "no JSON without --json";
  EXPECT_EQ(handler.status_calls.load(), 1);
}

TEST_F(CliStatus, JsonForScripts) {
  ASSERT_TRUE(start());
  const auto r = fettle("status --json --socket " + quote(socket().string()));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const json j = json::parse(r.output, nullptr, false);
  ASSERT_FALSE(j.is_discarded()) << r.output;
  EXPECT_EQ(j.value("state", ""), "Idle");
  EXPECT_EQ(j.value("maintenance", true), false);
  EXPECT_EQ(j.value("cycles_total", 0), 5);
}

TEST_F(CliStatus, SocketFromTheConfigFile) {
  ASSERT_TRUE(start());
  // A copy of the shipped simulator cell file whose [control] socket is our test socket.
  const fs::path src = FETTLE_SOURCE_DIR "/config";
  fs::copy(src / "parts", dir.path() / "parts", fs::copy_options::recursive);
  fs::copy_file(src / "calibration.sim.toml", dir.path() / "calibration.sim.toml");
  std::string cell = fettle::test::read_text(src / "cell.sim.toml");
  cell = std::regex_replace(cell, std::regex("socket = \"[^\"]*\""), "socket = \"fettled.sock\"");
  std::ofstream(dir.path() / "cell.toml") << cell;
  const auto r = fettle("status --config " + quote((dir.path() / "cell.toml").string()));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("socket        " + socket().string()), std::string::npos) << r.output;
}

TEST_F(CliStatus, CyclesTableAndJson) {
  ASSERT_TRUE(start());
  auto r = fettle("cycles --limit 3 --socket " + quote(socket().string()));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(std::regex_search(r.output, std::regex("^id +started +result +duration_s\n")) ) << r.output;
  EXPECT_TRUE(std::regex_search(r.output, std::regex("\nc-0003 +2024-05-03T10:00:00Z +NOK +43\n"))) << r.output;
  EXPECT_EQ(r.output.find("c-0002"), std::string::npos) << "--limit 3 shows 5, 4, 3";

  r = fettle("cycles --json --socket " + quote(socket().string()));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const json j = json::parse(r.output, nullptr, false);
  ASSERT_TRUE(j.is_array()) << r.output;
  EXPECT_EQ(j.size(), 5U);
  EXPECT_EQ(j[0].value("id", ""), "c-0005");

  r = fettle("cycles --last --socket " + quote(socket().string()));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("id            c-0005"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("regions"), std::string::npos) << "--last shows nested fields too";
}

TEST_F(CliStatus, DaemonErrorsExitWith1AndSayWhy) {
  handler.no_cycles = true;
  ASSERT_TRUE(start());
  const auto r = fettle("cycles --socket " + quote(socket().string()));
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("fettled refused: journal /var/lib/fettle/journal: unreadable"), std::string::npos)
      << r.output;
  EXPECT_NE(r.output.find("[records.unreadable]"), std::string::npos) << r.output;
}

TEST(CliNoServer, StatusSaysIsFettledRunningAndExits3) {
  fettle::test::TempDir dir;
  const fs::path sock = dir.path() / "fettled.sock";
  auto r = fettle("status --socket " + quote(sock.string()));
  EXPECT_EQ(r.exit_code, 3) << r.output;
  EXPECT_NE(r.output.find("fettle: is fettled running? socket " + sock.string() + ": no such file"),
            std::string::npos)
      << r.output;

  // A socket file left by a crashed daemon: connection refused.
  {
    boost::asio::io_context io;
    fettle::test::FakeHandler h;
    fettle::daemon::control::Server s{io, h, {.socket_path = sock}};
    ASSERT_TRUE(s.start());
    ASSERT_EQ(::link(sock.c_str(), (dir.path() / "kept.sock").c_str()), 0);  // survives the server's cleanup
  }
  r = fettle("status --socket " + quote((dir.path() / "kept.sock").string()));
  EXPECT_EQ(r.exit_code, 3) << r.output;
  EXPECT_NE(r.output.find("is fettled running? socket " + (dir.path() / "kept.sock").string() +
                          ": connection refused"),
            std::string::npos)
      << r.output;

  r = fettle("cycles --socket " + quote(sock.string()));
  EXPECT_EQ(r.exit_code, 3) << r.output;
  EXPECT_NE(r.output.find("is fettled running?"), std::string::npos) << r.output;
}

TEST(CliNoServer, SocketAndConfigTogetherIsAUsageError) {
  const auto r = fettle("status --socket /x --config /y");
  EXPECT_EQ(r.exit_code, 2) << r.output;
}

}  // namespace
