// Cycle records: journal, interrupted cycles after a restart, atomic files, retention; fault table.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <set>
#include <string>

#include "fettle/daemon/faults.hpp"
#include "fettle/daemon/records.hpp"

namespace fs = std::filesystem;
using fettle::daemon::CycleSummary;
using fettle::daemon::Records;

namespace {

fs::path fresh_dir(const std::string& name) {
  const auto d = fs::temp_directory_path() / ("fettle-test-records-" + name + "-" + std::to_string(::getpid()));
  fs::remove_all(d);
  return d;
}

fettle::config::RecordsSection keep(int cycles, double mb) {
  fettle::config::RecordsSection r;
  r.keep_cycles = cycles;
  r.keep_mb = mb;
  return r;
}

}  // namespace

TEST(Records, BeginWriteEndAndReadBack) {
  const auto dir = fresh_dir("basic");
  {
    Records r(dir, keep(10, 100));
    ASSERT_TRUE(r.open());
    auto c = r.begin(1, "pump-body", false);
    ASSERT_TRUE(c) << c.error().message;
    EXPECT_TRUE(fs::is_directory(c->dir));
    ASSERT_TRUE(Records::write_file(*c, "report.json", "{\"x\":1}"));
    c->result = "OK";
    c->duration_s = 1.5;
    ASSERT_TRUE(r.end(*c, {{"steps", nlohmann::json::array()}}));
    EXPECT_EQ(r.last()->result, "OK");
  }
  Records again(dir, keep(10, 100));
  auto interrupted = again.open();
  ASSERT_TRUE(interrupted);
  EXPECT_TRUE(interrupted->empty());
  ASSERT_EQ(again.count(), 1U);
  const auto c = again.cycles(5).front();
  EXPECT_EQ(c.result, "OK");
  EXPECT_EQ(c.part_id, "pump-body");
  EXPECT_DOUBLE_EQ(c.duration_s, 1.5);
  std::ifstream in(c.dir / "report.json");
  std::string text((std::istreambuf_iterator<char>(in)), {});
  EXPECT_EQ(text, "{\"x\":1}");
  fs::remove_all(dir);
}

TEST(Records, ACycleWithoutEndShowsAsInterruptedAfterRestart) {
  const auto dir = fresh_dir("interrupted");
  std::string id;
  {
    Records r(dir, keep(10, 100));
    ASSERT_TRUE(r.open());
    auto c = r.begin(1, "p", false);
    ASSERT_TRUE(c);
    id = c->id;
    // no end(): the daemon "crashed"
  }
  {
    // A torn last line, as a power loss during an append leaves it.
    std::ofstream j(dir / "journal.jsonl", std::ios::app);
    j << "{\"event\":\"end\",\"id\":";
  }
  Records r(dir, keep(10, 100));
  auto interrupted = r.open();
  ASSERT_TRUE(interrupted);
  ASSERT_EQ(interrupted->size(), 1U);
  EXPECT_EQ(interrupted->front(), id);
  EXPECT_EQ(r.cycles(1).front().result, "INTERRUPTED");
  // Marked once: a second restart finds nothing new.
  Records r2(dir, keep(10, 100));
  auto again = r2.open();
  ASSERT_TRUE(again);
  EXPECT_TRUE(again->empty());
  EXPECT_EQ(r2.cycles(1).front().result, "INTERRUPTED");
  // New cycles get new ids.
  auto c = r2.begin(1, "p", false);
  ASSERT_TRUE(c);
  EXPECT_NE(c->id, id);
  fs::remove_all(dir);
}

TEST(Records, RetentionByCountKeepsTheNewest) {
  const auto dir = fresh_dir("count");
  Records r(dir, keep(3, 1000));
  ASSERT_TRUE(r.open());
  std::vector<std::string> ids;
  for (int i = 0; i < 6; ++i) {
    auto c = r.begin(1, "p", false);
    ASSERT_TRUE(c);
    ids.push_back(c->id);
    c->result = "OK";
    ASSERT_TRUE(r.end(*c));
  }
  std::set<std::string> left;
  for (const auto& e : fs::directory_iterator(r.cycles_dir())) left.insert(e.path().filename().string());
  EXPECT_EQ(left, (std::set<std::string>{ids[3], ids[4], ids[5]}));
  EXPECT_EQ(r.count(), 6U);  // the journal remembers every cycle
  EXPECT_TRUE(r.cycles(6).back().record_deleted);
  fs::remove_all(dir);
}

TEST(Records, RetentionBySizeNeverDeletesTheCurrentCycle) {
  const auto dir = fresh_dir("size");
  Records r(dir, keep(100, 0.5));  // 0.5 MB
  ASSERT_TRUE(r.open());
  const std::string big(400 * 1024, 'x');
  std::string last;
  for (int i = 0; i < 4; ++i) {
    auto c = r.begin(1, "p", false);
    ASSERT_TRUE(c);
    ASSERT_TRUE(Records::write_file(*c, "capture_1.ply", big));
    c->result = "OK";
    ASSERT_TRUE(r.end(*c));
    last = c->id;
  }
  std::vector<std::string> left;
  for (const auto& e : fs::directory_iterator(r.cycles_dir())) left.push_back(e.path().filename().string());
  ASSERT_EQ(left.size(), 1U);
  EXPECT_EQ(left.front(), last);
  fs::remove_all(dir);
}

TEST(Records, UnwritableStateDirIsAnErrorNamingIt) {
  Records r("/proc/fettle-no-such-dir", keep(1, 1));
  auto st = r.open();
  ASSERT_FALSE(st);
  EXPECT_NE(st.error().message.find("/proc/fettle-no-such-dir"), std::string::npos);
}

TEST(Faults, TableHasUniqueCodesAndIdsAndSafetyFaultsAbort) {
  using fettle::daemon::FaultCode;
  using fettle::daemon::FaultReaction;
  std::set<int> codes;
  std::set<std::string> ids;
  for (const auto& f : fettle::daemon::fault_table()) {
    EXPECT_TRUE(codes.insert(static_cast<int>(f.code)).second);
    EXPECT_TRUE(ids.insert(std::string(f.id)).second);
    EXPECT_FALSE(f.remedy.empty());
  }
  for (auto c : {FaultCode::robot_fault, FaultCode::spindle_fault, FaultCode::plc_link_lost_moving,
                 FaultCode::robot_link_lost_moving})
    EXPECT_EQ(fettle::daemon::info(c).reaction, FaultReaction::abort);
  for (auto c : {FaultCode::camera_timeout, FaultCode::empty_fixture, FaultCode::wrong_part, FaultCode::robot_nak})
    EXPECT_EQ(fettle::daemon::info(c).reaction, FaultReaction::hold);
}

TEST(Faults, ErrorsOfTheLinksMapToCodes) {
  using fettle::daemon::FaultCode;
  auto map = [](const std::string& code, bool motion, const std::string& msg = "") {
    return fettle::daemon::fault_from_error({code, msg}, "step", motion, FaultCode::internal).code;
  };
  EXPECT_EQ(map("robot.nak.ENVELOPE", false), FaultCode::robot_nak);
  EXPECT_EQ(map("robot.fault.COLLISION", true), FaultCode::robot_fault);
  EXPECT_EQ(map("robot.connection_lost", true), FaultCode::robot_link_lost_moving);
  EXPECT_EQ(map("robot.connection_lost", false), FaultCode::robot_unavailable);
  EXPECT_EQ(map("camera.fault", false), FaultCode::camera_timeout);
  EXPECT_EQ(map("spindle.fault", true), FaultCode::spindle_fault);
  EXPECT_EQ(map("vision.no_part", false, "only 3 scan points inside the [vision] crop box"), FaultCode::empty_fixture);
  EXPECT_EQ(map("vision.no_part", false, "the part was not found in the scan"), FaultCode::wrong_part);
  EXPECT_EQ(map("vision.empty_fixture", false, "no part on the fixture"), FaultCode::empty_fixture);
  EXPECT_EQ(map("vision.no_match", false, "whole-part fitness 0.34 below [vision] min_part_fitness"), FaultCode::wrong_part);
  EXPECT_EQ(map("something.else", false), FaultCode::internal);
  const auto f = fettle::daemon::fault_from_error({"camera.fault", "no frame"}, "capture 1", false, FaultCode::internal);
  EXPECT_EQ(f.describe(), "E201 camera.timeout (capture 1): camera.fault: no frame");
}
