// systemd/fettled.service and fettle-sim.service: required settings, hardening measured by
// `systemd-analyze security --offline=true` (overall exposure <= 3.0), `systemd-analyze
// verify`, and the sysusers.d entry applied to an empty root.
#include <filesystem>
#include <regex>
#include <fstream>
#include <iostream>
#include <set>
#include <sstream>
#include <string>

#include <gtest/gtest.h>

#include "test_systemd_support.hpp"

namespace {

namespace fs = std::filesystem;
using fettle::test::quote;
using fettle::test::run;

const fs::path build_dir = fs::path(FETTLE_BIN_DIR).parent_path();
const fs::path unit_dir = build_dir / "systemd";

std::set<std::string> words(const std::string& s) {
  std::set<std::string> out;
  std::stringstream ss(s);
  std::string w;
  while (ss >> w) out.insert(w);
  return out;
}

std::string one(const std::multimap<std::string, std::string>& m, const std::string& key) {
  const auto n = m.count(key);
  if (n != 1) return "<" + std::to_string(n) + " values>";
  return m.find(key)->second;
}

/// systemd-analyze that knows `security --offline=`, or the reason to skip.
std::string analyze_or_reason(fs::path& program) {
  program = fettle::test::find_program("systemd-analyze");
  if (program.empty()) return "systemd-analyze is not installed (Debian package systemd)";
  const auto help = run(quote(program) + " --help");
  if (help.output.find("--offline") == std::string::npos)
    return "systemd-analyze is too old for --offline (needs systemd >= 250): " + help.output.substr(0, 80);
  return {};
}

double exposure(const fs::path& analyze, const fs::path& unit, std::string& output) {
  const auto r = run(quote(analyze) + " security --offline=true --no-pager " + quote(unit.string()));
  output = r.output;
  std::smatch m;
  static const std::regex overall(R"(Overall exposure level for \S+: ([0-9]+(\.[0-9]+)?))");
  if (!std::regex_search(output, m, overall)) return -1.0;
  return std::stod(m[1].str());
}

TEST(SystemdUnits, FettledHasTheRequiredSettings) {
  const auto text = fettle::test::read_text(unit_dir / "fettled.service");
  ASSERT_FALSE(text.empty()) << "missing " << (unit_dir / "fettled.service");
  EXPECT_FALSE(std::regex_search(text, std::regex("@[A-Z_]+@"))) << "an @VAR@ was not configured";
  const auto s = fettle::test::unit_settings(text);
  EXPECT_EQ(one(s, "Type"), "notify");
  EXPECT_EQ(one(s, "Restart"), "on-failure");
  EXPECT_EQ(one(s, "WatchdogSec"), "10s");
  EXPECT_EQ(one(s, "User"), "fettle");
  EXPECT_EQ(one(s, "StateDirectory"), "fettle");
  EXPECT_EQ(one(s, "ConfigurationDirectory"), "fettle");
  EXPECT_EQ(one(s, "RuntimeDirectory"), "fettle");
  EXPECT_EQ(one(s, "RuntimeDirectoryMode"), "0750") << "group fettle must reach the 0660 socket, others not";
  EXPECT_NE(one(s, "ExecStart").find("fettled --config ${CONFIGURATION_DIRECTORY}/cell.toml"), std::string::npos);
  EXPECT_EQ(one(s, "ExecStart").find("--allow-root"), std::string::npos);
  for (const char* key : {"NoNewPrivileges", "ProtectHome", "PrivateTmp", "ProtectKernelTunables",
                          "ProtectKernelModules", "ProtectKernelLogs", "ProtectControlGroups", "LockPersonality",
                          "MemoryDenyWriteExecute", "RestrictRealtime"})
    EXPECT_EQ(one(s, key), "yes") << key;
  EXPECT_EQ(one(s, "ProtectSystem"), "strict");
  const std::set<std::string> caps{"CAP_NET_RAW", "CAP_SYS_NICE"};
  EXPECT_EQ(words(one(s, "CapabilityBoundingSet")), caps);
  EXPECT_EQ(words(one(s, "AmbientCapabilities")), caps);
  EXPECT_EQ(words(one(s, "RestrictAddressFamilies")),
            (std::set<std::string>{"AF_UNIX", "AF_INET", "AF_INET6", "AF_CAN", "AF_NETLINK", "AF_PACKET"}));
  const auto filters = s.equal_range("SystemCallFilter");
  ASSERT_NE(filters.first, filters.second);
  EXPECT_EQ(filters.first->second, "@system-service");
}

void expect_exposure_at_most_3(const std::string& unit) {
  fs::path analyze;
  if (const auto reason = analyze_or_reason(analyze); !reason.empty()) GTEST_SKIP() << reason;
  std::string out;
  const double level = exposure(analyze, unit_dir / unit, out);
  ASSERT_GE(level, 0.0) << "no overall exposure in:\n" << out;
  EXPECT_LE(level, 3.0) << out;
  std::cout << unit << ": overall exposure " << level << "\n";
}

TEST(SystemdUnits, FettledExposureIsAtMost3) { expect_exposure_at_most_3("fettled.service"); }
TEST(SystemdUnits, FettleSimExposureIsAtMost3) { expect_exposure_at_most_3("fettle-sim.service"); }

TEST(SystemdUnits, ExposureCheckCanFail) {
  // The same analysis on a unit without hardening must score far above 3.0.
  fs::path analyze;
  if (const auto reason = analyze_or_reason(analyze); !reason.empty()) GTEST_SKIP() << reason;
  fettle::test::TempDir dir;
  const auto unit = dir.path() / "plain.service";
  std::ofstream(unit) << "[Service]\nExecStart=/bin/true\n";
  std::string out;
  const double level = exposure(analyze, unit, out);
  ASSERT_GE(level, 0.0) << out;
  EXPECT_GT(level, 3.0) << out;
}

TEST(SystemdUnits, VerifyAcceptsBothUnits) {
  fs::path analyze;
  if (const auto reason = analyze_or_reason(analyze); !reason.empty()) GTEST_SKIP() << reason;
  fettle::test::TempDir dir;
  // Does verify work here at all (it may need a running systemd)? Try a trivial unit first.
  const auto probe = dir.path() / "probe.service";
  std::ofstream(probe) << "[Unit]\nDescription=probe\n[Service]\nExecStart=/bin/true\n";
  const auto p = run(quote(analyze) + " verify " + quote(probe.string()));
  if (p.exit_code != 0) GTEST_SKIP() << "systemd-analyze verify does not work offline here: " << p.output;
  // The build-tree units name the install paths; point ExecStart at the built programs.
  for (const auto& [unit, program] : {std::pair{"fettled.service", "fettled"}, std::pair{"fettle-sim.service", "fettle-sim"}}) {
    const fs::path built = fs::path(FETTLE_BIN_DIR) / program;
    if (!fs::exists(built)) {
      ADD_FAILURE() << built << " is not built";
      continue;
    }
    std::string text = fettle::test::read_text(unit_dir / unit);
    text = std::regex_replace(text, std::regex("ExecStart=\\S+/" + std::string(program) + " "),
                              "ExecStart=" + built.string() + " ");
    const auto copy = dir.path() / unit;
    std::ofstream(copy) << text;
    const auto r = run(quote(analyze) + " verify " + quote(copy.string()));
    EXPECT_EQ(r.exit_code, 0) << unit << ":\n" << r.output;
    EXPECT_EQ(r.output, "") << unit << ": verify printed warnings";
  }
}

TEST(SystemdUnits, SysusersCreatesTheFettleUser) {
  const fs::path sysusers = fettle::test::find_program("systemd-sysusers");
  if (sysusers.empty()) GTEST_SKIP() << "systemd-sysusers is not installed";
  fettle::test::TempDir root;
  fs::create_directories(root.path() / "etc");
  const auto r = run(quote(sysusers.string()) + " --root=" + quote(root.path().string()) + " " +
                     quote(FETTLE_SOURCE_DIR "/systemd/fettle.sysusers"));
  if (r.exit_code != 0 && r.output.find("ermission") != std::string::npos)
    GTEST_SKIP() << "systemd-sysusers needs privileges here: " << r.output;
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto passwd = fettle::test::read_text(root.path() / "etc/passwd");
  std::smatch m;
  ASSERT_TRUE(std::regex_search(passwd, m, std::regex("^fettle:x:([0-9]+):([0-9]+):[^:]*:/var/lib/fettle:([^\n]*)$",
                                                      std::regex::multiline)))
      << passwd;
  EXPECT_LT(std::stoi(m[1].str()), 1000) << "a system user";
  EXPECT_NE(m[3].str().find("nologin"), std::string::npos) << "no login shell: " << m[3].str();
  EXPECT_NE(fettle::test::read_text(root.path() / "etc/group").find("fettle:x:"), std::string::npos);
}

}  // namespace
