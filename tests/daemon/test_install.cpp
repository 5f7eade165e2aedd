// `cmake --install` into a temp prefix: binaries, units, sysusers entry and example
// configs land where a Debian administrator expects them, with the prefix in the units.
#include <sys/stat.h>

#include <filesystem>
#include <string>

#include <gtest/gtest.h>

#include "test_systemd_support.hpp"

namespace {

namespace fs = std::filesystem;
using fettle::test::quote;
using fettle::test::run;

class Install : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    prefix_ = new fettle::test::TempDir;
    const fs::path build = fs::path(FETTLE_BIN_DIR).parent_path();
    const auto cmake = fettle::test::find_program("cmake");
    ASSERT_FALSE(cmake.empty());
    result_ = new fettle::test::Run(
        run(quote(cmake.string()) + " --install " + quote(build.string()) + " --prefix " + quote(prefix().string())));
  }
  static void TearDownTestSuite() {
    delete result_;
    delete prefix_;
  }
  void SetUp() override { ASSERT_EQ(result_->exit_code, 0) << result_->output; }
  static const fs::path& prefix() { return prefix_->path(); }

  static void expect_executable(const fs::path& p) {
    struct stat st {};
    ASSERT_EQ(::stat(p.c_str(), &st), 0) << p << " not installed";
    EXPECT_TRUE(S_ISREG(st.st_mode)) << p;
    EXPECT_EQ(st.st_mode & 0111U, 0111U) << p << " is not executable by all";
  }

  static inline fettle::test::TempDir* prefix_ = nullptr;
  static inline fettle::test::Run* result_ = nullptr;
};

TEST_F(Install, ProgramsGoToBinAndSbin) {
  expect_executable(prefix() / "bin/fettle");
  expect_executable(prefix() / "bin/fettle-sim");
  expect_executable(prefix() / "sbin/fettled");
  EXPECT_FALSE(fs::exists(prefix() / "bin/fettled")) << "a daemon belongs in sbin";
}

TEST_F(Install, UnitsNameTheInstalledPrograms) {
  const fs::path units = prefix() / "lib/systemd/system";
  const auto fettled = fettle::test::read_text(units / "fettled.service");
  const auto sim = fettle::test::read_text(units / "fettle-sim.service");
  ASSERT_FALSE(fettled.empty()) << "no " << units / "fettled.service";
  ASSERT_FALSE(sim.empty()) << "no " << units / "fettle-sim.service";
  EXPECT_NE(fettled.find("ExecStart=" + (prefix() / "sbin/fettled").string() + " --config"), std::string::npos)
      << fettled;
  EXPECT_NE(sim.find("ExecStart=" + (prefix() / "bin/fettle-sim").string() + " cell --config"), std::string::npos)
      << sim;
  EXPECT_NE(fettled.find("Documentation=file:" + (prefix() / "share/doc/fettle/service.md").string()),
            std::string::npos);
  EXPECT_EQ(fettled.find("@FETTLE_"), std::string::npos) << "an @VAR@ was not configured";
  EXPECT_EQ(sim.find("@FETTLE_"), std::string::npos) << "an @VAR@ was not configured";

  // The installed units pass verify, their programs being where they say.
  const auto analyze = fettle::test::find_program("systemd-analyze");
  if (analyze.empty()) GTEST_SKIP() << "systemd-analyze is not installed";
  for (const char* unit : {"fettled.service", "fettle-sim.service"}) {
    const auto r = run(quote(analyze.string()) + " verify " + quote((units / unit).string()));
    if (r.exit_code != 0 && r.output.find("not executable") == std::string::npos &&
        r.output.find(unit) == std::string::npos)
      GTEST_SKIP() << "systemd-analyze verify does not work offline here: " << r.output;
    EXPECT_EQ(r.exit_code, 0) << unit << ": " << r.output;
  }
}

TEST_F(Install, SysusersEntryAndDocs) {
  const auto sysusers = fettle::test::read_text(prefix() / "lib/sysusers.d/fettle.conf");
  EXPECT_NE(sysusers.find("u     fettle"), std::string::npos) << sysusers;
  EXPECT_TRUE(fs::exists(prefix() / "share/doc/fettle/service.md"));
  EXPECT_TRUE(fs::exists(prefix() / "share/doc/fettle/daemon-control.md"));
}

TEST_F(Install, ExampleConfigsGoToShareAndNothingToEtc) {
  const fs::path ex = prefix() / "share/fettle/examples";
  for (const char* f : {"cell.example.toml", "cell.sim.toml", "calibration.sim.toml", "parts/pump-body.toml"})
    EXPECT_TRUE(fs::is_regular_file(ex / f)) << ex / f;
  EXPECT_FALSE(fs::exists(ex / "include")) << "source folders must not be installed with the examples";
  EXPECT_FALSE(fs::exists(ex / "src"));
  EXPECT_FALSE(fs::exists(ex / "CMakeLists.txt"));
  EXPECT_FALSE(fs::exists(prefix() / "etc")) << "/etc/fettle is the administrator's (docs/service.md)";
  // The installed examples are valid as installed (their relative paths resolve there).
  const auto r = run(quote((prefix() / "bin/fettle").string()) + " config check " + quote((ex / "cell.sim.toml").string()));
  EXPECT_EQ(r.exit_code, 0) << r.output;
}

}  // namespace
