#include <gtest/gtest.h>

#include <stdexcept>

#include "fettle/core/log.hpp"

using fettle::log::Target;

TEST(Log, JournalIsChosenUnderSystemd) {
  EXPECT_EQ(fettle::log::resolve_target(Target::automatic, "8:1234", nullptr), Target::journal);
  EXPECT_EQ(fettle::log::resolve_target(Target::automatic, nullptr, "0123abcd"), Target::journal);
}

TEST(Log, StderrIsChosenOutsideSystemd) {
  EXPECT_EQ(fettle::log::resolve_target(Target::automatic, nullptr, nullptr), Target::stderr_text);
  EXPECT_EQ(fettle::log::resolve_target(Target::automatic, "", ""), Target::stderr_text);
}

TEST(Log, ExplicitTargetWins) {
  EXPECT_EQ(fettle::log::resolve_target(Target::stderr_text, "8:1234", "x"), Target::stderr_text);
}

TEST(Log, ComponentLevelsComeFromOptionsAndOverrideWins) {
  fettle::log::Options o;
  o.target = Target::stderr_text;
  o.default_level = "warn";
  o.component_levels = {{"plc", "debug"}};
  fettle::log::init(o);
  EXPECT_EQ(fettle::log::get("plc")->level(), spdlog::level::debug);
  EXPECT_EQ(fettle::log::get("camera")->level(), spdlog::level::warn);

  o.override_level = "error";
  fettle::log::init(o);  // re-init applies to loggers that already exist
  EXPECT_EQ(fettle::log::get("plc")->level(), spdlog::level::err);
  EXPECT_EQ(fettle::log::get("camera")->level(), spdlog::level::err);
}

TEST(Log, BadLevelIsRejectedWithTheAllowedNames) {
  fettle::log::Options o;
  o.component_levels = {{"robot", "chatty"}};
  try {
    fettle::log::init(o);
    FAIL() << "expected invalid_argument";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("component 'robot'"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("trace, debug, info"), std::string::npos) << e.what();
  }
}

TEST(Log, ScopesNestAndRestore) {
  EXPECT_EQ(fettle::log::context().count("CYCLE_ID"), 0U);
  {
    fettle::log::Scope a{"CYCLE_ID", "7"};
    EXPECT_EQ(fettle::log::context().at("CYCLE_ID"), "7");
    {
      fettle::log::Scope b{"CYCLE_ID", "8"};
      EXPECT_EQ(fettle::log::context().at("CYCLE_ID"), "8");
    }
    EXPECT_EQ(fettle::log::context().at("CYCLE_ID"), "7");
  }
  EXPECT_EQ(fettle::log::context().count("CYCLE_ID"), 0U);
}

TEST(Log, JournalSinkWithoutJournaldDoesNotThrow) {
  fettle::log::Options o;
  o.target = Target::journal;
  fettle::log::init(o);
  fettle::log::Scope s{"STATE", "Idle"};
  EXPECT_NO_THROW(fettle::log::get("test")->error("journal record with fields"));
  o.target = Target::stderr_text;
  fettle::log::init(o);
}
