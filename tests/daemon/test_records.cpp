// Cycle records: journal, interrupted cycles after a restart, atomic files, retention; fault table.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <sched.h>
#include <sys/mount.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
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
  r.min_free_mb = 0.0;  // the machine's free space must not decide these tests
  return r;
}

std::string read_all(const fs::path& p) {
  std::ifstream in(p);
  return {std::istreambuf_iterator<char>(in), {}};
}

bool write_proc(const char* path, const std::string& text) {
  const int fd = ::open(path, O_WRONLY | O_CLOEXEC);
  if (fd < 0) return false;
  const bool ok = ::write(fd, text.data(), text.size()) == static_cast<ssize_t>(text.size());
  ::close(fd);
  return ok;
}

/// Mounts a tmpfs of `size` on `dir` in a mount namespace of this process only (each test runs
/// in its own process under ctest). Root: a new mount namespace; otherwise a user namespace
/// too, where the kernel allows it. Returns why not, or "" on success.
std::string mount_small_tmpfs(const fs::path& dir, const char* size) {
  fs::create_directories(dir);
  if (::geteuid() != 0) {
    const auto uid = ::geteuid();
    const auto gid = ::getegid();
    if (::unshare(CLONE_NEWUSER | CLONE_NEWNS) != 0)
      return std::string("unshare(CLONE_NEWUSER | CLONE_NEWNS): ") + std::strerror(errno) +
             " (not root and unprivileged user namespaces are off)";
    (void)write_proc("/proc/self/setgroups", "deny");
    if (!write_proc("/proc/self/uid_map", "0 " + std::to_string(uid) + " 1") ||
        !write_proc("/proc/self/gid_map", "0 " + std::to_string(gid) + " 1"))
      return "cannot write the user namespace's uid/gid map";
  } else if (::unshare(CLONE_NEWNS) != 0) {
    return std::string("unshare(CLONE_NEWNS): ") + std::strerror(errno);
  }
  if (::mount(nullptr, "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0)
    return std::string("making / private: ") + std::strerror(errno);
  const std::string options = std::string("size=") + size + ",mode=0700";
  if (::mount("tmpfs", dir.c_str(), "tmpfs", 0, options.c_str()) != 0)
    return std::string("mount tmpfs: ") + std::strerror(errno);
  return "";
}

/// Writes a file until the file system is full; returns the bytes written.
std::size_t fill_disk(const fs::path& file) {
  const int fd = ::open(file.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
  if (fd < 0) return 0;
  const std::string block(64 * 1024, 'f');
  std::size_t total = 0;
  for (;;) {
    const auto n = ::write(fd, block.data(), block.size());
    if (n <= 0) break;
    total += static_cast<std::size_t>(n);
  }
  ::close(fd);
  return total;
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
    c->result = "NOK";
    c->duration_s = 1.5;
    c->worst_gouge_mm = 0.58;  // the verification's worst gouge: `fettle cycles` shows it
    c->gouge = "gouged outside region side-parting-line at (46.10, -70.20, 34.40) mm (part frame), depth 0.580 mm";
    c->deepest_below_template_mm = 0.58;
    ASSERT_TRUE(r.end(*c, {{"steps", nlohmann::json::array()}}));
    EXPECT_EQ(r.last()->result, "NOK");
    ASSERT_TRUE(r.last()->worst_gouge_mm.has_value());
  }
  Records again(dir, keep(10, 100));
  auto interrupted = again.open();
  ASSERT_TRUE(interrupted);
  EXPECT_TRUE(interrupted->empty());
  ASSERT_EQ(again.count(), 1U);
  const auto c = again.cycles(5).front();
  EXPECT_EQ(c.result, "NOK");
  EXPECT_EQ(c.part_id, "pump-body");
  EXPECT_DOUBLE_EQ(c.duration_s, 1.5);
  ASSERT_TRUE(c.worst_gouge_mm.has_value());
  EXPECT_DOUBLE_EQ(*c.worst_gouge_mm, 0.58);
  EXPECT_NE(c.gouge.find("gouged outside region side-parting-line"), std::string::npos) << c.gouge;
  ASSERT_TRUE(c.deepest_below_template_mm.has_value());
  EXPECT_DOUBLE_EQ(*c.deepest_below_template_mm, 0.58);
  EXPECT_FALSE(CycleSummary::from_json(CycleSummary{}.to_json()).worst_gouge_mm.has_value());  // no verification
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
  // its folder has a report.json that says so
  {
    std::ifstream report(dir / "cycles" / id / "report.json");
    ASSERT_TRUE(report) << "no report.json in the interrupted cycle's folder";
    const auto j = nlohmann::json::parse(report);
    EXPECT_EQ(j.value("result", ""), "INTERRUPTED");
    EXPECT_EQ(j.value("id", ""), id);
  }
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

// Below [records] min_free_mb the oldest records go before a cycle, never the cycle itself;
// when that is not enough the cycle still goes on, with a warning that says where and what to do.
TEST(Records, BelowMinFreeTheOldestRecordsGoAndTheCycleGoesOnWithAWarning) {
  const auto dir = fresh_dir("min-free");
  {
    Records r(dir, keep(100, 1000));
    ASSERT_TRUE(r.open());
    for (int i = 0; i < 3; ++i) {
      auto c = r.begin(1, "p", false);
      ASSERT_TRUE(c);
      ASSERT_TRUE(Records::write_file(*c, "capture_1.ply", std::string(1000, 'x')));
      c->result = "OK";
      ASSERT_TRUE(r.end(*c));
    }
  }
  auto plenty = keep(100, 1000);
  plenty.min_free_mb = 1.0;  // met on any machine that can run the tests
  {
    Records r(dir, plenty);
    ASSERT_TRUE(r.open());
    auto c = r.begin(1, "p", false);
    ASSERT_TRUE(c);
    EXPECT_TRUE(r.warning().empty()) << r.warning();
    c->result = "OK";
    ASSERT_TRUE(r.end(*c));
  }
  std::size_t before = 0;
  for (const auto& e : fs::directory_iterator(dir / "cycles")) before += e.is_directory() ? 1U : 0U;
  ASSERT_EQ(before, 4U);

  auto scarce = keep(100, 1000);
  Records probe(dir, scarce);
  const auto free = probe.free_bytes();
  ASSERT_TRUE(free.has_value());
  scarce.min_free_mb = static_cast<double>(*free) / (1024.0 * 1024.0) + 1e6;  // a terabyte more than there is
  Records r(dir, scarce);
  ASSERT_TRUE(r.open());
  auto c = r.begin(1, "p", false);
  ASSERT_TRUE(c) << c.error().message;
  EXPECT_TRUE(fs::is_directory(c->dir)) << "the cycle goes on with its record";
  std::vector<std::string> left;
  for (const auto& e : fs::directory_iterator(dir / "cycles")) left.push_back(e.path().filename().string());
  ASSERT_EQ(left.size(), 1U) << "every older record is deleted";
  EXPECT_EQ(left.front(), c->id);
  EXPECT_NE(r.warning().find("min_free_mb"), std::string::npos) << r.warning();
  EXPECT_NE(r.warning().find(dir.string()), std::string::npos) << r.warning();
  const auto journal = read_all(dir / "journal.jsonl");
  std::size_t deleted = 0;
  for (std::size_t at = journal.find("\"deleted\""); at != std::string::npos; at = journal.find("\"deleted\"", at + 1)) ++deleted;
  EXPECT_EQ(deleted, 4U) << "the journal keeps every cycle's lines and says which records went";
  c->result = "OK";
  EXPECT_TRUE(r.end(*c));
  EXPECT_EQ(r.count(), 5U);
  fs::remove_all(dir);
}

// A real full disk (a 1 MB tmpfs): the cycle begins anyway, what cannot be written is an error
// that names the file, and the journal's lines wait in memory until there is room: none is lost.
TEST(RecordsOnAFullDisk, TheCycleGoesOnAndNoJournalLineIsLost) {
  const auto dir = fresh_dir("full-disk");
  if (const auto why = mount_small_tmpfs(dir, "1m"); !why.empty())
    GTEST_SKIP() << "cannot mount a small tmpfs here: " << why;
  const auto state = dir / "state";
  {
    Records r(state, keep(100, 1000));
    ASSERT_TRUE(r.open());
    ASSERT_GT(fill_disk(dir / "filler"), 0U);
    auto c = r.begin(1, "p", false);
    ASSERT_TRUE(c) << c.error().message;
    EXPECT_NE(r.warning().find("full"), std::string::npos) << r.warning();
    EXPECT_EQ(r.pending_lines(), 1U);
    const auto st = Records::write_file(*c, "report.json", std::string(8192, 'r'));
    ASSERT_FALSE(st) << "written on a full disk?";
    EXPECT_NE(st.error().message.find("report.json"), std::string::npos) << st.error().message;
    fs::remove(dir / "filler");
    c->result = "OK";
    EXPECT_TRUE(r.end(*c));
    EXPECT_EQ(r.pending_lines(), 0U);
  }
  Records again(state, keep(100, 1000));
  auto interrupted = again.open();
  ASSERT_TRUE(interrupted);
  EXPECT_TRUE(interrupted->empty()) << "the start line came before the end line";
  ASSERT_EQ(again.count(), 1U);
  EXPECT_EQ(again.cycles(1).front().result, "OK");
  ::umount2(dir.c_str(), MNT_DETACH);
  fs::remove_all(dir);
}

// Records on a small disk with min_free_mb: old records make room for new ones, every file of
// every cycle is written.
TEST(RecordsOnAFullDisk, MinFreeMakesRoomForEveryCycle) {
  const auto dir = fresh_dir("small-disk");
  if (const auto why = mount_small_tmpfs(dir, "1m"); !why.empty())
    GTEST_SKIP() << "cannot mount a small tmpfs here: " << why;
  auto retention = keep(100, 1000);
  retention.min_free_mb = 0.5;
  Records r(dir / "state", retention);
  ASSERT_TRUE(r.open());
  const std::string capture(300 * 1024, 'c');
  for (int i = 0; i < 6; ++i) {
    auto c = r.begin(1, "p", false);
    ASSERT_TRUE(c) << c.error().message;
    EXPECT_TRUE(r.warning().empty()) << "cycle " << i << ": " << r.warning();
    const auto st = Records::write_file(*c, "capture_1.ply", capture);
    EXPECT_TRUE(st) << "cycle " << i << ": " << st.error().message;
    c->result = "OK";
    EXPECT_TRUE(r.end(*c));
  }
  EXPECT_EQ(r.count(), 6U);
  std::size_t kept = 0;
  for (const auto& e : fs::directory_iterator(r.cycles_dir())) kept += e.is_directory() ? 1U : 0U;
  EXPECT_GE(kept, 1U);
  EXPECT_LT(kept, 6U) << "six 300 KB records cannot fit on 1 MB";
  ::umount2(dir.c_str(), MNT_DETACH);
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

// The fault of an error comes from where it came from and its kind, never from its code
// string: an error whose code looks like another component's maps by its source.
TEST(Faults, ErrorsMapToCodesByTheirSourceAndKind) {
  using fettle::ErrorKind;
  using fettle::daemon::ErrorSource;
  using fettle::daemon::FaultCode;
  auto map = [](ErrorSource source, ErrorKind kind, bool motion, FaultCode fallback = FaultCode::internal) {
    return fettle::daemon::fault_from_error({"any.code", "message", kind}, source, "step", motion, fallback).code;
  };
  EXPECT_EQ(map(ErrorSource::robot, ErrorKind::refused, false), FaultCode::robot_nak);
  EXPECT_EQ(map(ErrorSource::robot, ErrorKind::device_fault, true), FaultCode::robot_fault);
  EXPECT_EQ(map(ErrorSource::robot, ErrorKind::timeout, true), FaultCode::robot_timeout);
  EXPECT_EQ(map(ErrorSource::robot, ErrorKind::link_lost, true), FaultCode::robot_link_lost_moving);
  EXPECT_EQ(map(ErrorSource::robot, ErrorKind::link_lost, false), FaultCode::robot_unavailable);
  EXPECT_EQ(map(ErrorSource::robot, ErrorKind::cancelled, true), FaultCode::robot_link_lost_moving);
  EXPECT_EQ(map(ErrorSource::robot, ErrorKind::invalid_request, false), FaultCode::plan_failed);
  EXPECT_EQ(map(ErrorSource::robot, ErrorKind::unspecified, true, FaultCode::robot_fault), FaultCode::robot_fault);
  EXPECT_EQ(map(ErrorSource::camera, ErrorKind::no_data, false), FaultCode::camera_timeout);
  EXPECT_EQ(map(ErrorSource::camera, ErrorKind::unavailable, false), FaultCode::camera_unavailable);
  EXPECT_EQ(map(ErrorSource::spindle, ErrorKind::device_fault, true), FaultCode::spindle_fault);
  EXPECT_EQ(map(ErrorSource::spindle, ErrorKind::timeout, true), FaultCode::spindle_timeout);
  EXPECT_EQ(map(ErrorSource::spindle, ErrorKind::unavailable, false), FaultCode::spindle_unavailable);
  EXPECT_EQ(map(ErrorSource::spindle, ErrorKind::unavailable, true), FaultCode::spindle_fault);
  EXPECT_EQ(map(ErrorSource::process, ErrorKind::no_part, false), FaultCode::empty_fixture);
  EXPECT_EQ(map(ErrorSource::process, ErrorKind::wrong_part, false), FaultCode::wrong_part);
  EXPECT_EQ(map(ErrorSource::process, ErrorKind::unplannable, false), FaultCode::plan_failed);
  EXPECT_EQ(map(ErrorSource::process, ErrorKind::unspecified, false, FaultCode::vision_failed), FaultCode::vision_failed);
  EXPECT_EQ(map(ErrorSource::plc, ErrorKind::unavailable, false, FaultCode::slide_fault), FaultCode::slide_fault);
  const auto f = fettle::daemon::fault_from_error({"camera.fault", "no frame", ErrorKind::no_data}, ErrorSource::camera,
                                                  "capture 1", false, FaultCode::internal);
  EXPECT_EQ(f.describe(), "E201 camera.timeout (capture 1): camera.fault: no frame");
}
