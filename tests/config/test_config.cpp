// Configuration files: every mistake is reported with file:line:column, the key,
// the bad value and what is allowed; the shipped files are valid.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>

#include "fettle/config/load.hpp"

namespace fs = std::filesystem;
using fettle::config::check_file;
using fettle::config::ConfigError;
using fettle::config::Diagnostic;
using fettle::config::FileKind;
using ::testing::HasSubstr;

namespace {

const fs::path kConfigDir = fs::path(FETTLE_SOURCE_DIR) / "config";

// A minimal valid cell file; tests change one thing in it.
const std::string kCell = R"([cell]
name = "test-cell"

[plc]
address = "127.0.0.1"
port = 1502

[slide]
photo_positions_mm = [0.0, 100.0]

[camera]
address = "127.0.0.1"

[robot]
address = "127.0.0.1"
port = 30100
cell_id = "test-cell"

[spindle]
transport = "sim"

[safety]
workspace_min_mm = [-500.0, -500.0, 0.0]
workspace_max_mm = [500.0, 500.0, 800.0]
)";

const std::string kPart = R"([part]
id = "p"

[template]
source = "simulator"

[[tools]]
name = "disc"
shape = "cylinder"
diameter_mm = 40.0

[[regions]]
name = "ring"
type = "ring_flash"
tool = "disc"
roi_center_mm = [0.0, 0.0, 10.0]
roi_size_mm = [100.0, 100.0, 20.0]
)";

class ConfigFileTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("fettle-config-test-" + std::to_string(::getpid()) + "-" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }

  fs::path write(const std::string& name, const std::string& text) {
    const fs::path p = dir_ / name;
    std::ofstream(p) << text;
    return p;
  }
  static std::string replace(std::string text, const std::string& from, const std::string& to) {
    const auto pos = text.find(from);
    EXPECT_NE(pos, std::string::npos) << "test bug: '" << from << "' not in text";
    return text.replace(pos, from.size(), to);
  }

  fs::path dir_;
};

std::string all(const std::vector<Diagnostic>& d) {
  std::string s;
  for (const auto& x : d) s += x.to_string() + "\n";
  return s;
}

}  // namespace

TEST(ShippedConfig, SimCellIsValid) {
  const auto d = check_file(kConfigDir / "cell.sim.toml");
  EXPECT_TRUE(d.empty()) << all(d);
}

TEST(ShippedConfig, ExampleCellIsValid) {
  const auto d = check_file(kConfigDir / "cell.example.toml");
  EXPECT_TRUE(d.empty()) << all(d);
}

TEST(ShippedConfig, PumpBodyRecipeIsValid) {
  const auto d = check_file(kConfigDir / "parts" / "pump-body.toml");
  EXPECT_TRUE(d.empty()) << all(d);
}

TEST(ShippedConfig, SimCellLoadsIntoStructsWithResolvedPaths) {
  const auto cfg = fettle::config::load_cell(kConfigDir / "cell.sim.toml");
  EXPECT_EQ(cfg.cell.name, "sim-cell");
  EXPECT_EQ(cfg.plc.address, "127.0.0.1");
  EXPECT_EQ(cfg.plc.poll_period_ms, 20);
  ASSERT_EQ(cfg.slide.photo_positions_mm.size(), 2U);
  EXPECT_DOUBLE_EQ(cfg.slide.photo_positions_mm[1], 120.0);
  ASSERT_EQ(cfg.cell.recipes.size(), 1U);
  EXPECT_TRUE(cfg.cell.recipes[0].file.is_absolute());
  EXPECT_TRUE(fs::exists(cfg.cell.recipes[0].file));
  EXPECT_EQ(cfg.spindle.transport, "socketcand");  // fettle-sim cell serves the drive over socketcand
  EXPECT_EQ(cfg.spindle.port, 29536);
}

TEST(ShippedConfig, PumpBodyHasFourRegionTypes) {
  const auto part = fettle::config::load_part(kConfigDir / "parts" / "pump-body.toml");
  ASSERT_EQ(part.regions.size(), 4U);
  EXPECT_EQ(part.regions[0].type, fettle::config::RegionType::ring_flash);
  EXPECT_EQ(part.regions[1].type, fettle::config::RegionType::riser);
  EXPECT_EQ(part.regions[2].type, fettle::config::RegionType::circle_flash);
  EXPECT_EQ(part.regions[3].type, fettle::config::RegionType::straight_flash);
  EXPECT_DOUBLE_EQ(part.regions[1].depth_per_pass_mm, 2.0);
  EXPECT_DOUBLE_EQ(part.verification.jump_edge_mm, 4.0);
  EXPECT_DOUBLE_EQ(part.vision.jump_edge_mm, 0.0);  // the first scan keeps every pixel (see the recipe)
}

TEST_F(ConfigFileTest, MinimalCellIsValid) {
  const auto d = check_file(write("cell.toml", kCell));
  EXPECT_TRUE(d.empty()) << all(d);
}

TEST_F(ConfigFileTest, UnknownKeyOnLineOneIsAnErrorAtThatLine) {
  const fs::path f = write("cell.toml", "colour = \"red\"\n" + kCell);
  const auto d = check_file(f);
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].file, f.string());
  EXPECT_EQ(d[0].line, 1);
  EXPECT_EQ(d[0].column, 1);
  EXPECT_EQ(d[0].key, "colour");
  EXPECT_THAT(d[0].message, HasSubstr("unknown key"));
  EXPECT_THAT(d[0].to_string(), HasSubstr(f.string() + ":1:1: key 'colour': unknown key"));
}

TEST_F(ConfigFileTest, MisspelledKeySuggestsTheRightOne) {
  const auto d = check_file(write("cell.toml", replace(kCell, "port = 1502", "prot = 1502")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "plc.prot");
  EXPECT_EQ(d[0].line, 6);
  EXPECT_THAT(d[0].message, HasSubstr("did you mean 'port'?"));
}

TEST_F(ConfigFileTest, WrongTypeNamesKeyValueAndExpectedType) {
  const auto d = check_file(write("cell.toml", replace(kCell, "port = 1502", "port = \"1502\"")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "plc.port");
  EXPECT_EQ(d[0].line, 6);
  EXPECT_THAT(d[0].message, HasSubstr("must be an integer, got string \"1502\""));
}

TEST_F(ConfigFileTest, OutOfRangeValueNamesTheAllowedRange) {
  const auto d = check_file(write("cell.toml", replace(kCell, "port = 1502", "port = 70000")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "plc.port");
  EXPECT_EQ(d[0].line, 6);
  EXPECT_THAT(d[0].message, HasSubstr("value 70000 is out of range (allowed 1 to 65535)"));
}

// The cell's stated accuracies: read into [safety], a negative one named with its range.
TEST_F(ConfigFileTest, StatedAccuraciesAreReadAndANegativeOneIsNamed) {
  const std::string stated = "workspace_max_mm = [500.0, 500.0, 800.0]\ncalibration_accuracy_mm = 0.15\n"
                             "robot_accuracy_mm = 0.1\ntcp_accuracy_mm = 0.07\nrobot_repeatability_mm = 0.05\n";
  const auto cell = fettle::config::load_cell(write("cell.toml", replace(kCell, "workspace_max_mm = [500.0, 500.0, 800.0]\n", stated)));
  EXPECT_DOUBLE_EQ(cell.safety.calibration_accuracy_mm, 0.15);
  EXPECT_DOUBLE_EQ(cell.safety.robot_accuracy_mm, 0.1);
  EXPECT_DOUBLE_EQ(cell.safety.tcp_accuracy_mm, 0.07);
  EXPECT_DOUBLE_EQ(cell.safety.robot_repeatability_mm, 0.05);
  const auto d = check_file(write("cell.toml", replace(kCell, "workspace_max_mm = [500.0, 500.0, 800.0]\n",
                                                      "workspace_max_mm = [500.0, 500.0, 800.0]\nrobot_accuracy_mm = -0.1\n")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "safety.robot_accuracy_mm");
  EXPECT_THAT(d[0].message, HasSubstr("out of range"));
}

TEST_F(ConfigFileTest, BadIpv4AddressIsRejected) {
  const auto d = check_file(write("cell.toml", replace(kCell, "address = \"127.0.0.1\"\nport = 1502",
                                                       "address = \"127.0.0.300\"\nport = 1502")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "plc.address");
  EXPECT_THAT(d[0].message, HasSubstr("not an IPv4 address"));
}

TEST_F(ConfigFileTest, MissingRequiredKeyIsNamed) {
  const auto d = check_file(write("cell.toml", replace(kCell, "cell_id = \"test-cell\"\n", "")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "robot.cell_id");
  EXPECT_THAT(d[0].message, HasSubstr("required"));
}

TEST_F(ConfigFileTest, WrongElementInArrayIsNamedByIndex) {
  const auto d = check_file(write("cell.toml", replace(kCell, "[0.0, 100.0]", "[0.0, \"x\"]")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "slide.photo_positions_mm[1]");
}

TEST_F(ConfigFileTest, EmptyWorkspaceIsRejected) {
  const auto d =
      check_file(write("cell.toml", replace(kCell, "[500.0, 500.0, 800.0]", "[500.0, -600.0, 800.0]")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "safety.workspace_max_mm");
  EXPECT_THAT(d[0].message, HasSubstr("axis y"));
}

TEST_F(ConfigFileTest, SyntaxErrorGivesLineAndColumn) {
  const auto d = check_file(write("cell.toml", replace(kCell, "port = 1502", "port = = 1502")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].line, 6);
  EXPECT_THAT(d[0].message, HasSubstr("TOML syntax error"));
}

TEST_F(ConfigFileTest, MissingFileIsReported) {
  const auto d = check_file(dir_ / "nope.toml");
  ASSERT_EQ(d.size(), 1U);
  EXPECT_THAT(d[0].to_string(), HasSubstr("nope.toml: no such file"));
}

TEST_F(ConfigFileTest, EveryProblemIsReportedNotJustTheFirst) {
  std::string text = replace(kCell, "port = 1502", "port = 0");
  text = replace(text, "transport = \"sim\"", "transport = \"usb\"");
  text = "bogus = 1\n" + text;
  try {
    (void)fettle::config::load_cell(write("cell.toml", text));
    FAIL() << "expected ConfigError";
  } catch (const ConfigError& e) {
    EXPECT_EQ(e.diagnostics().size(), 3U) << e.what();
    EXPECT_THAT(e.what(), HasSubstr("bogus"));
    EXPECT_THAT(e.what(), HasSubstr("plc.port"));
    EXPECT_THAT(e.what(), HasSubstr("\"usb\" is not allowed (allowed: socketcan, socketcand, sim)"));
  }
}

TEST_F(ConfigFileTest, RecipeFileMustExist) {
  const auto d = check_file(
      write("cell.toml", replace(kCell, "name = \"test-cell\"\n",
                                 "name = \"test-cell\"\n[[cell.recipes]]\nplc_recipe_id = 1\nfile = \"missing.toml\"\n")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "cell.recipes[0].file");
  EXPECT_THAT(d[0].message, HasSubstr("does not exist"));
}

TEST_F(ConfigFileTest, CellCheckAlsoChecksItsRecipes) {
  write("part.toml", replace(kPart, "diameter_mm = 40.0", "diameter_mm = -40.0"));
  const auto d = check_file(
      write("cell.toml", replace(kCell, "name = \"test-cell\"\n",
                                 "name = \"test-cell\"\n[[cell.recipes]]\nplc_recipe_id = 1\nfile = \"part.toml\"\n")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_THAT(d[0].file, HasSubstr("part.toml"));
  EXPECT_EQ(d[0].key, "tools[0].diameter_mm");
}

TEST_F(ConfigFileTest, BadLogLevelInComponentsIsNamed) {
  const auto d = check_file(write("cell.toml", kCell + "\n[logging]\ncomponents = { plc = \"loud\" }\n"));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "logging.components.plc");
  EXPECT_THAT(d[0].message, HasSubstr("not a log level"));
}

TEST_F(ConfigFileTest, MinimalPartIsValid) {
  const auto d = check_file(write("part.toml", kPart));
  EXPECT_TRUE(d.empty()) << all(d);
}

TEST_F(ConfigFileTest, RegionWithUndefinedToolIsRejected) {
  const auto d = check_file(write("part.toml", replace(kPart, "tool = \"disc\"", "tool = \"grinder\"")));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "regions[0].tool");
  EXPECT_THAT(d[0].message, HasSubstr("no [[tools]] entry is named \"grinder\""));
}

TEST_F(ConfigFileTest, KeyOfAnotherRegionTypeIsUnknown) {
  const auto d = check_file(write("part.toml", kPart + "depth_per_pass_mm = 1.0\n"));
  ASSERT_EQ(d.size(), 1U) << all(d);
  EXPECT_EQ(d[0].key, "regions[0].depth_per_pass_mm");
  EXPECT_THAT(d[0].message, HasSubstr("unknown key"));
  EXPECT_THAT(d[0].message, HasSubstr("chamfer_deg"));  // lists what a ring_flash takes
}

TEST_F(ConfigFileTest, UnknownRegionTypeListsTheTypes) {
  const auto d = check_file(write("part.toml", replace(kPart, "type = \"ring_flash\"", "type = \"ring\"")));
  ASSERT_FALSE(d.empty());
  EXPECT_EQ(d[0].key, "regions[0].type");
  EXPECT_THAT(d[0].message, HasSubstr("ring_flash, riser, straight_flash, circle_flash"));
}

TEST_F(ConfigFileTest, RegionPoseIsRegionOrPart) {
  const auto bad = check_file(write("part.toml", kPart + "pose = \"whole\"\n"));
  ASSERT_EQ(bad.size(), 1U) << all(bad);
  EXPECT_EQ(bad[0].key, "regions[0].pose");
  EXPECT_THAT(bad[0].message, HasSubstr("region, part"));
  const auto good = write("part.toml", kPart + "pose = \"part\"\n");
  EXPECT_TRUE(check_file(good).empty());
  EXPECT_EQ(fettle::config::load_part(good).regions[0].pose, fettle::config::RegionPose::part);
  EXPECT_EQ(fettle::config::load_part(write("p2.toml", kPart)).regions[0].pose, fettle::config::RegionPose::region);
}

TEST_F(ConfigFileTest, KindCanBeForced) {
  const auto d = check_file(write("part.toml", kPart), FileKind::cell);
  EXPECT_FALSE(d.empty());  // a part file is not a valid cell file
}

TEST_F(ConfigFileTest, LoggingLevelsPerComponentComeFromTheCellFile) {
  const auto cfg = fettle::config::load_cell(
      write("cell.toml", kCell + "\n[logging]\nlevel = \"warn\"\ncomponents = { plc = \"debug\" }\n"));
  auto o = fettle::config::logging_options(cfg.logging, "fettled");
  o.target = fettle::log::Target::stderr_text;
  fettle::log::init(o);
  EXPECT_EQ(fettle::log::get("plc")->level(), spdlog::level::debug);
  EXPECT_EQ(fettle::log::get("robot")->level(), spdlog::level::warn);
  o.override_level = "trace";  // --log-level wins
  fettle::log::init(o);
  EXPECT_EQ(fettle::log::get("plc")->level(), spdlog::level::trace);
}
