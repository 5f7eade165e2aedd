// Config files with every kind of mistake, each starting from the shipped simulator cell
// (config/cell.sim.toml) with one thing broken: every one gives diagnostics that name the
// file (and the line where there is one), load_cell throws ConfigError, nothing crashes or hangs.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <csignal>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include "../support/child_process.hpp"
#include "fettle/config/load.hpp"
#include "../../config/src/reader.hpp"

namespace fs = std::filesystem;
using fettle::config::check_file;
using fettle::config::ConfigError;
using fettle::config::Diagnostic;
using fettle::config::FileKind;
using ::testing::HasSubstr;

namespace {

const fs::path kConfigDir = fs::path(FETTLE_SOURCE_DIR) / "config";

std::string read_text(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

std::string all(const std::vector<Diagnostic>& d) {
  std::string s;
  for (const auto& x : d) s += x.to_string() + "\n";
  return s;
}

class ConfigBadInput : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("fettle-config-bad-" + std::to_string(::getpid()) + "-" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::create_directories(dir_);
    // The shipped cell with its relative paths made absolute, so it is valid from here.
    cell_ = read_text(kConfigDir / "cell.sim.toml");
    cell_ = replace(cell_, "\"parts/pump-body.toml\"", "\"" + (kConfigDir / "parts/pump-body.toml").string() + "\"");
    cell_ = replace(cell_, "\"calibration.sim.toml\"", "\"" + (kConfigDir / "calibration.sim.toml").string() + "\"");
  }
  void TearDown() override { fs::remove_all(dir_); }

  fs::path write(const std::string& text) {
    const fs::path p = dir_ / "cell.toml";
    std::ofstream(p, std::ios::binary) << text;
    return p;
  }
  static std::string replace(std::string text, const std::string& from, const std::string& to) {
    const auto pos = text.find(from);
    EXPECT_NE(pos, std::string::npos) << "test bug: '" << from << "' not in text";
    return pos == std::string::npos ? text : text.replace(pos, from.size(), to);
  }

  /// The diagnostics of `text` as a cell file; expects at least one, each naming the file,
  /// and load_cell to throw ConfigError with the same count.
  std::vector<Diagnostic> problems(const std::string& text) {
    const auto f = write(text);
    auto d = check_file(f, FileKind::cell);
    EXPECT_FALSE(d.empty()) << "accepted:\n" << text;
    for (const auto& x : d) EXPECT_EQ(x.file, f.string()) << x.to_string();
    try {
      (void)fettle::config::load_cell(f);
      ADD_FAILURE() << "load_cell accepted it";
    } catch (const ConfigError& e) {
      EXPECT_EQ(e.diagnostics().size(), d.size());
    }
    return d;
  }

  fs::path dir_;
  std::string cell_;
};

}  // namespace

TEST_F(ConfigBadInput, TheStartingPointIsValid) {
  const auto d = check_file(write(cell_), FileKind::cell);
  EXPECT_TRUE(d.empty()) << all(d);
}

TEST_F(ConfigBadInput, EmptyFileNamesTheMissingTables) {
  const auto d = problems("");
  EXPECT_THAT(all(d), HasSubstr("cell"));
  EXPECT_THAT(all(d), HasSubstr("safety"));
}

TEST_F(ConfigBadInput, BinaryGarbageIsASyntaxError) {
  const auto d = problems(std::string("\x7f" "ELF\x02\x01\x01\0\0\0\xff\xfe\n[[[\n", 16));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_THAT(d[0].message, HasSubstr("TOML syntax error"));
  EXPECT_GE(d[0].line, 1);
}

TEST_F(ConfigBadInput, InvalidUtf8InAStringIsASyntaxError) {
  const auto d = problems(replace(cell_, "name = \"sim-cell\"", "name = \"sim-\xc3\x28-cell\""));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].line, 6);
}

TEST_F(ConfigBadInput, DuplicateKeyIsReportedAtItsSecondDefinition) {
  const auto d = problems(replace(cell_, "port = 1502\n", "port = 1502\nport = 1503\n"));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].line, 21);
}

TEST_F(ConfigBadInput, DuplicateTableIsReported) {
  const auto d = problems(cell_ + "\n[plc]\nport = 1503\n");
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_GT(d[0].line, 60);
}

TEST_F(ConfigBadInput, ValueWhereATableIsExpected) {
  // At the top: after [[cell.recipes]] the key would belong to the recipe table.
  const auto d = problems("logging = \"info\"\n" + replace(cell_, "[logging]\nlevel = \"info\"", ""));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "logging");
  EXPECT_EQ(d[0].line, 1);
}

TEST_F(ConfigBadInput, TableWhereAValueIsExpected) {
  const auto d = problems(replace(cell_, "port = 1502\n", "port = { number = 1502 }\n"));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "plc.port");
}

TEST_F(ConfigBadInput, IntegerTooLargeForTomlIsASyntaxError) {
  const auto d = problems(replace(cell_, "port = 1502\n", "port = 99999999999999999999999\n"));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].line, 20);
}

TEST_F(ConfigBadInput, IntegerOutsideIntIsOutOfRangeNotWrapped) {
  // 2^32 + 1502 would be 1502 if truncated to 32 bits.
  const auto d = problems(replace(cell_, "port = 1502\n", "port = 4294968798\n"));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "plc.port");
  EXPECT_THAT(d[0].message, HasSubstr("out of range"));
}

TEST_F(ConfigBadInput, FractionWhereAnIntegerIsExpected) {
  const auto d = problems(replace(cell_, "port = 1502\n", "port = 1502.5\n"));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "plc.port");
}

TEST_F(ConfigBadInput, NanAndInfinityAreOutOfRange) {
  for (const std::string v : {"nan", "inf", "-inf", "+nan"}) {
    const auto d = problems(replace(cell_, "max_speed_mm_s = 200.0", "max_speed_mm_s = " + v));
    ASSERT_EQ(d.size(), 1U) << v << "\n" << all(d);
    EXPECT_EQ(d[0].key, "safety.max_speed_mm_s") << v;
  }
}

TEST_F(ConfigBadInput, VectorsOfTheWrongLengthOrType) {
  for (const std::string v : {"[-600.0, -600.0]", "[-600.0, -600.0, -20.0, 1.0]", "[]", "\"-600 -600 -20\"",
                              "[-600.0, -600.0, true]", "[[1.0], [2.0], [3.0]]"}) {
    const auto d = problems(replace(cell_, "[-600.0, -600.0, -20.0]", v));
    ASSERT_GE(d.size(), 1U) << v;
    EXPECT_THAT(d[0].key, HasSubstr("safety.workspace_min_mm")) << v << "\n" << all(d);
  }
}

TEST_F(ConfigBadInput, UnterminatedStringAndUnclosedTable) {
  EXPECT_EQ(problems(replace(cell_, "name = \"sim-cell\"", "name = \"sim-cell")).size(), 1U);
  EXPECT_EQ(problems(replace(cell_, "[plc]", "[plc")).size(), 1U);
}

TEST_F(ConfigBadInput, DuplicateRecipeIdIsNamed) {
  const std::string recipe = "[[cell.recipes]]\nplc_recipe_id = 1\nfile = \"" +
                             (kConfigDir / "parts/pump-body.toml").string() + "\"\n";
  const auto d = problems(replace(cell_, "[logging]", recipe + "\n[logging]"));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_THAT(d[0].message, HasSubstr("used twice"));
}

TEST_F(ConfigBadInput, RecipePathThatIsADirectoryOrADevice) {
  for (const std::string& path : {dir_.string(), std::string("/dev/zero"), std::string("/dev/null")}) {
    const auto out = fettle::test::run_in_child([&] {
      ::alarm(10);  // a read of /dev/zero that never ends is a hang: fail instead
      const auto f = write(replace(cell_, (kConfigDir / "parts/pump-body.toml").string(), path));
      if (check_file(f, FileKind::cell).empty()) std::_Exit(3);
    });
    EXPECT_EQ(out.how, fettle::test::ChildOutcome::How::returned) << path << ": " << out.detail;
  }
}

TEST_F(ConfigBadInput, TheFileItselfIsADeviceOrADirectory) {
  for (const fs::path& path : {fs::path("/dev/zero"), dir_}) {
    const auto out = fettle::test::run_in_child([&] {
      ::alarm(10);
      for (auto kind : {FileKind::automatic, FileKind::cell, FileKind::part})
        if (check_file(path, kind).empty()) std::_Exit(3);
    });
    EXPECT_EQ(out.how, fettle::test::ChildOutcome::How::returned) << path << ": " << out.detail;
  }
}

TEST_F(ConfigBadInput, DeeplyNestedArraysAreRefusedNotAStackOverflow) {
  const std::string deep = std::string(5000, '[') + std::string(5000, ']');
  const auto out = fettle::test::run_in_child([&] {
    const auto f = write(replace(cell_, "[-600.0, -600.0, -20.0]", deep));
    if (check_file(f, FileKind::cell).empty()) std::_Exit(3);
  });
  EXPECT_EQ(out.how, fettle::test::ChildOutcome::How::returned) << out.detail;
}

// A table header of 50 000 dotted parts overflowed the TOML parser's stack (SIGSEGV, a restart
// loop under systemd): refused on the text before parsing, with its line (issue 40, item 2;
// docs/security.md "Limits").
TEST_F(ConfigBadInput, AHeaderOfFiftyThousandDottedPartsIsRefusedWithItsLine) {
  std::string header = "[a";
  for (int i = 0; i < 50000; ++i) header += ".b";
  header += "]\nx = 1\n";
  const auto out = fettle::test::run_in_child([&] {
    const auto f = write(cell_ + "\n" + header);
    for (auto kind : {FileKind::automatic, FileKind::cell}) {
      const auto d = check_file(f, kind);
      if (d.empty()) std::_Exit(3);
      if (d.front().line == 0 || d.front().message.find("dotted parts") == std::string::npos) std::_Exit(4);
    }
  });
  EXPECT_EQ(out.how, fettle::test::ChildOutcome::How::returned) << out.detail;
  // and in this process, the message
  const auto d = problems(cell_ + "\n" + header);
  EXPECT_THAT(all(d), HasSubstr("more than 64 dotted parts: refused before parsing")) << all(d);
  EXPECT_GT(d.front().line, 1) << all(d);
  // dotted keys too, and inline tables nested deeper than the limit
  EXPECT_THAT(all(problems(cell_ + "\n[deep]\n" + std::string("k") + [] {
                std::string s;
                for (int i = 0; i < 100; ++i) s += ".k";
                return s;
              }() + " = 1\n")),
              HasSubstr("dotted parts"));
  std::string inl = "[deep]\nv = ";
  for (int i = 0; i < 100; ++i) inl += "{a = ";
  inl += "1";
  for (int i = 0; i < 100; ++i) inl += "}";
  EXPECT_THAT(all(problems(cell_ + "\n" + inl + "\n")), HasSubstr("nested deeper than 64"));
}

// Dots inside strings, comments and numbers are no nesting; what the limit allows parses as before.
TEST(ConfigNesting, DotsInStringsCommentsAndValuesAreNotCounted) {
  using fettle::config::detail::too_deeply_nested;
  std::string many_dots(200, '.');
  EXPECT_FALSE(too_deeply_nested("a = \"" + many_dots + "\"\n# " + many_dots + "\nb = 1.5\n'q" + many_dots + "' = 2\n", 64));
  EXPECT_FALSE(too_deeply_nested("s = \"\"\"\n" + many_dots + "\n\"\"\"\nv = [1.5, 2.5,\n 3.5]\n", 64));
  std::string ok = "[a";
  for (int i = 0; i < 63; ++i) ok += ".b";
  EXPECT_FALSE(too_deeply_nested(ok + "]\n", 64));
  const auto deep = too_deeply_nested("x = 1\n" + ok + ".c]\n", 64);
  ASSERT_TRUE(deep);
  EXPECT_EQ(deep->line, 2);
}

// A FIFO given to `fettle config check` blocked forever: auto mode parsed it before the reader
// checked the file type (issue 40, item 4). Now every mode refuses it at once, naming it.
TEST_F(ConfigBadInput, AFifoIsRefusedNotWaitedOn) {
  const fs::path fifo = dir_ / "cell.fifo";
  ASSERT_EQ(::mkfifo(fifo.c_str(), 0600), 0);
  const auto out = fettle::test::run_in_child([&] {
    ::alarm(10);
    for (auto kind : {FileKind::automatic, FileKind::cell, FileKind::part}) {
      const auto d = check_file(fifo, kind);
      if (d.empty() || d.front().message.find("not a regular file") == std::string::npos) std::_Exit(3);
    }
  });
  EXPECT_EQ(out.how, fettle::test::ChildOutcome::How::returned) << out.detail;
}

// A newline in [robot] cell_id made fettled send a second, injected protocol line; 200
// characters broke the protocol's limits; a NUL inside an address, a FIFO or /dev/zero as the
// calibration file and a 300-byte socket path passed the check and failed only at start
// (issue 40, item 9). Every string that goes on a wire is one token, every file read a regular
// file, every path of a sane length.
TEST_F(ConfigBadInput, StringsOnAWireAndPathsAreCheckedNotJustTheirType) {
  EXPECT_THAT(all(problems(replace(cell_, "cell_id = \"sim-cell\"", "cell_id = \"a\\n2 RUN 1 3000\""))),
              HasSubstr("control character (0x0a at byte 1)"));
  EXPECT_THAT(all(problems(replace(cell_, "cell_id = \"sim-cell\"", "cell_id = \"" + std::string(200, 'x') + "\""))),
              HasSubstr("is not an identifier: 1 to 32"));
  EXPECT_THAT(all(problems(replace(cell_, "cell_id = \"sim-cell\"", "cell_id = \"two words\""))),
              HasSubstr("robot.cell_id"));
  EXPECT_THAT(all(problems(replace(cell_, "address = \"127.0.0.1\"", "address = \"127.0.0.1\\u0000junk\""))),
              HasSubstr("control character (0x00"));
  const fs::path fifo = dir_ / "cal.fifo";
  ASSERT_EQ(::mkfifo(fifo.c_str(), 0600), 0);
  for (const std::string& bad : {fifo.string(), std::string("/dev/zero")}) {
    const auto text = replace(cell_, (kConfigDir / "calibration.sim.toml").string(), bad);
    const auto out = fettle::test::run_in_child([&] {
      ::alarm(10);
      const auto d = check_file(write(text), FileKind::cell);
      if (d.empty() || all(d).find("is not a regular file") == std::string::npos) std::_Exit(3);
    });
    EXPECT_EQ(out.how, fettle::test::ChildOutcome::How::returned) << bad << ": " << out.detail;
  }
  EXPECT_THAT(all(problems(replace(cell_, "socket = \"../var/fettle/fettled.sock\"",
                                   "socket = \"/run/" + std::string(300, 's') + ".sock\""))),
              HasSubstr("a Unix socket path is at most 107 bytes"));
}
