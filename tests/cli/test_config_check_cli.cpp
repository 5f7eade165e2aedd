// `fettle config check` as a user runs it: exit codes and messages.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

namespace fs = std::filesystem;
using ::testing::HasSubstr;

namespace {

struct CliRun {
  int exit_code;
  std::string output;  // stdout and stderr
};

CliRun run_fettle(const std::string& args) {
  const std::string cmd = std::string(FETTLE_BIN_DIR) + "/fettle " + args + " 2>&1";
  FILE* pipe = ::popen(cmd.c_str(), "r");
  EXPECT_NE(pipe, nullptr);
  std::string out;
  std::array<char, 4096> buf{};
  while (std::fgets(buf.data(), buf.size(), pipe) != nullptr) out += buf.data();
  const int status = ::pclose(pipe);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

const std::string kConfigDir = std::string(FETTLE_SOURCE_DIR) + "/config";

fs::path temp_file(const std::string& name, const std::string& text) {
  const fs::path p = fs::temp_directory_path() / ("fettle-cli-" + std::to_string(::getpid()) + "-" + name);
  std::ofstream(p) << text;
  return p;
}

std::string sim_cell_with(const std::string& from, const std::string& to) {
  std::ifstream in(kConfigDir + "/cell.sim.toml");
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto pos = text.find(from);
  EXPECT_NE(pos, std::string::npos);
  text.replace(pos, from.size(), to);
  // The copy lives elsewhere: point its recipe at the shipped one.
  const auto r = text.find("\"parts/pump-body.toml\"");
  text.replace(r, std::string("\"parts/pump-body.toml\"").size(), "\"" + kConfigDir + "/parts/pump-body.toml\"");
  return text;
}

}  // namespace

TEST(FettleConfigCheck, ShippedFilesPass) {
  for (const char* f : {"/cell.sim.toml", "/cell.example.toml", "/parts/pump-body.toml"}) {
    const CliRun r = run_fettle("config check " + kConfigDir + f);
    EXPECT_EQ(r.exit_code, 0) << f << ": " << r.output;
    EXPECT_THAT(r.output, HasSubstr(": OK"));
  }
}

TEST(FettleConfigCheck, UnknownKeyOnLineOneExitsOneNamingFileLineAndKey) {
  const fs::path f = temp_file("unknown.toml", "speling = 1\n" + sim_cell_with("", ""));
  const CliRun r = run_fettle("config check " + f.string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_THAT(r.output, HasSubstr(f.string() + ":1:1: key 'speling': unknown key"));
  fs::remove(f);
}

TEST(FettleConfigCheck, WrongTypeExitsOneNamingFileLineAndKey) {
  const fs::path f = temp_file("type.toml", sim_cell_with("workers = 0", "workers = \"two\""));
  const CliRun r = run_fettle("config check " + f.string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_THAT(r.output, HasSubstr(f.string() + ":8:11: key 'cell.workers': must be an integer, got string \"two\""));
  fs::remove(f);
}

TEST(FettleConfigCheck, OutOfRangeExitsOneNamingFileLineAndKey) {
  const fs::path f = temp_file("range.toml", sim_cell_with("port = 30100", "port = 99999"));
  const CliRun r = run_fettle("config check " + f.string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_THAT(r.output, HasSubstr("key 'robot.port': value 99999 is out of range (allowed 1 to 65535)"));
  EXPECT_THAT(r.output, HasSubstr(f.string() + ":"));
  fs::remove(f);
}

TEST(FettleCli, UsageErrorsExitTwo) {
  EXPECT_EQ(run_fettle("").exit_code, 2);
  EXPECT_EQ(run_fettle("config check").exit_code, 2);
  EXPECT_EQ(run_fettle("--no-such-flag config check x").exit_code, 2);
}

TEST(FettleCli, HelpExitsZero) {
  const CliRun r = run_fettle("config check --help");
  EXPECT_EQ(r.exit_code, 0);
  EXPECT_THAT(r.output, HasSubstr("FILE"));
}
