// Logging: the target, levels, and the rate limit of similar lines.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <sstream>
#include <stdexcept>
#include <thread>

#include <spdlog/sinks/ostream_sink.h>

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

// A robot sending valid FAULT lines as fast as it could made fettled write 3.14 million lines
// in 10 s (issue 40, item 6). Similar lines (numbers apart) beyond the burst are counted, and
// the next one after the window says how many; other lines pass untouched.
TEST(Log, SimilarLinesBeyondTheBurstAreCountedNotWritten) {
  std::ostringstream out;
  auto inner = std::make_shared<spdlog::sinks::ostream_sink_mt>(out);
  inner->set_pattern("%n %l %v");
  auto logger = std::make_shared<spdlog::logger>("robot", fettle::log::rate_limited(inner, 5, 200));
  for (int i = 0; i < 10000; ++i) logger->warn("robot FAULT {} (seq {}): E-stop", 100 + i % 7, i);
  logger->info("link up");  // another shape: written
  std::this_thread::sleep_for(std::chrono::milliseconds(250));
  logger->warn("robot FAULT 3 (seq 99999): E-stop");  // after the window: the count, then this line
  const std::string text = out.str();
  const auto lines = static_cast<std::size_t>(std::count(text.begin(), text.end(), '\n'));
  EXPECT_EQ(lines, 5U + 1U + 1U + 1U) << text;
  EXPECT_NE(text.find("suppressed 9995 similar lines (rate limit 5 per 200 ms), the last: robot FAULT"), std::string::npos)
      << text;
  EXPECT_NE(text.find("robot info link up"), std::string::npos) << text;
  EXPECT_NE(text.find("seq 99999"), std::string::npos) << text;
  // what is suppressed and never followed is said at the flush
  for (int i = 0; i < 8; ++i) logger->error("spindle SDO abort {}", i);
  logger->flush();
  EXPECT_NE(out.str().find("suppressed 3 similar lines"), std::string::npos) << out.str();
}
