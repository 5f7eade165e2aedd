// fettled end to end: the simulated cell (fettle::sim::CellSim, in this process, on loopback
// with ephemeral ports; the camera on UDP 3956, hence RESOURCE_LOCK gige) and fettled as a
// separate process. Three cycles, then one scenario per fault; each ends in the documented
// state with the documented code and recovers; fettled never crashes; every cycle has a record.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <sstream>
#include <string>
#include <thread>

#include <nlohmann/json.hpp>

#include "fettle/config/load.hpp"
#include "fettle/drivers/packml.hpp"
#include "fettle/drivers/plc_registers.hpp"
#include "fettle/sim/cell.hpp"

extern char** environ;

namespace fs = std::filesystem;
using fettle::packml::State;
using namespace std::chrono_literals;

namespace {

const fs::path kSource = FETTLE_SOURCE_DIR;
const fs::path kBin = FETTLE_BIN_DIR;

std::string read_text(const fs::path& p) {
  std::ifstream in(p);
  return {std::istreambuf_iterator<char>(in), {}};
}

/// Runs a command, returns its standard output (empty if it could not start).
std::string run_output(const std::string& command) {
  std::string out;
  FILE* f = ::popen(command.c_str(), "r");
  if (f == nullptr) return out;
  char buf[4096];
  std::size_t n = 0;
  while ((n = std::fread(buf, 1, sizeof buf, f)) > 0) out.append(buf, n);
  ::pclose(f);
  return out;
}

/// FETTLE_TEST_TIME_SCALE (1 to 100; CMake sets 10 in the sanitizer builds) stretches every
/// wait of this file: under the sanitizers fettled and the simulated cell run several times slower.
double time_scale() {
  static const double scale = [] {
    const char* env = std::getenv("FETTLE_TEST_TIME_SCALE");
    const double v = env != nullptr ? std::atof(env) : 1.0;
    return std::isfinite(v) ? std::clamp(v, 1.0, 100.0) : 1.0;
  }();
  return scale;
}

bool wait_until(const std::function<bool()>& pred, std::chrono::milliseconds timeout) {
  const auto end = std::chrono::steady_clock::now() +
                   std::chrono::duration_cast<std::chrono::milliseconds>(timeout * time_scale());
  while (std::chrono::steady_clock::now() < end) {
    if (pred()) return true;
    std::this_thread::sleep_for(20ms);
  }
  return pred();
}

std::string cell_toml(const fs::path& dir, int plc, int robot, int spindle) {
  std::ostringstream t;
  t << "[cell]\nname = \"test-cell\"\nstate_dir = \"" << (dir / "state").string() << "\"\nworkers = 2\n"
    << "verification_scan = true\n\n[[cell.recipes]]\nplc_recipe_id = 1\nfile = \""
    << (dir / "parts/pump-body.toml").string() << "\"\n\n"
    << "[logging]\nlevel = \"info\"\n\n"
    << "[plc]\naddress = \"127.0.0.1\"\nport = " << plc
    << "\nunit_id = 1\nresponse_timeout_ms = 300\npoll_period_ms = 20\nheartbeat_timeout_ms = 1000\n"
    << "reconnect_initial_ms = 100\nreconnect_max_ms = 500\n\n"
    << "[slide]\nphoto_positions_mm = [0.0, 120.0]\ntravel_timeout_ms = 20000\n\n"
    << "[camera]\naddress = \"127.0.0.1\"\nframe_timeout_ms = 1500\nretries = 1\nexposure_us = 10000.0\n"
    << "pixel_format = \"Coord3D_C16\"\n\n"
    << "[robot]\naddress = \"127.0.0.1\"\nport = " << robot
    << "\ncell_id = \"test-cell\"\nreply_timeout_ms = 2000\nping_period_ms = 500\nmissed_pings = 3\n"
    // the run timeout stretches too: under TSan the simulated robot grinds a casting in ~215 s
    << "chunk_points = 20\nrun_timeout_ms = " << static_cast<long>(120000 * time_scale())
    << "\nreconnect_initial_ms = 100\nreconnect_max_ms = 500\n\n"
    << "[spindle]\ntransport = \"socketcand\"\naddress = \"127.0.0.1\"\nport = " << spindle
    // heartbeat as in config/cell.sim.toml: the default 300 ms can be missed while the test
    // process (which hosts the simulated drive) builds a casting on a busy machine
    << "\ninterface = \"can0\"\nnode_id = 1\nmode = \"profile_velocity\"\nheartbeat_timeout_ms = 1000\n\n"
    << "[calibration]\nfile = \"" << (kSource / "config/calibration.sim.toml").string() << "\"\n\n"
    << "[safety]\nworkspace_min_mm = [-600.0, -600.0, -20.0]\nworkspace_max_mm = [600.0, 600.0, 800.0]\n"
    << "tool_axis_cone_deg = 60.0\nmax_speed_mm_s = 200.0\nmax_spindle_rpm = 12000.0\nsafe_height_mm = 80.0\n\n"
    << "[control]\nsocket = \"" << (dir / "fettled.sock").string() << "\"\n\n"
    << "[records]\nkeep_cycles = 100\nkeep_mb = 5000.0\nmin_free_mb = 1.0\n";
  return t.str();
}

/// One inet socket of a process, from /proc/<pid>/net/{tcp,udp}{,6} and /proc/<pid>/fd.
struct InetSocket {
  std::string proto;  ///< "tcp", "udp", "tcp6", "udp6"
  std::string local;  ///< "127.0.0.1:40000"; IPv6 as its hex
  std::string remote;
  int state = 0;      ///< TCP: 1 established, 10 listen
  [[nodiscard]] std::string text() const { return proto + " " + local + " -> " + remote + " state " + std::to_string(state); }
};

std::string decode_address(const std::string& hex) {
  const auto colon = hex.find(':');
  const std::string ip = hex.substr(0, colon);
  const int port = std::stoi(hex.substr(colon + 1), nullptr, 16);
  if (ip.size() != 8) return ip + ":" + std::to_string(port);
  const auto v = static_cast<std::uint32_t>(std::stoul(ip, nullptr, 16));  // network order read as little-endian
  return std::to_string(v & 0xFFU) + "." + std::to_string((v >> 8U) & 0xFFU) + "." + std::to_string((v >> 16U) & 0xFFU) +
         "." + std::to_string(v >> 24U) + ":" + std::to_string(port);
}

std::vector<InetSocket> inet_sockets(pid_t pid) {
  std::set<std::string> inodes;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator("/proc/" + std::to_string(pid) + "/fd", ec)) {
    const auto target = fs::read_symlink(e.path(), ec).string();
    if (target.rfind("socket:[", 0) == 0) inodes.insert(target.substr(8, target.size() - 9));
  }
  std::vector<InetSocket> out;
  for (const char* proto : {"tcp", "udp", "tcp6", "udp6"}) {
    std::istringstream in(read_text("/proc/" + std::to_string(pid) + "/net/" + proto));
    std::string line;
    std::getline(in, line);  // header
    while (std::getline(in, line)) {
      std::istringstream f(line);
      std::string sl, local, remote, st, queues, timer, retr, uid, timeout, inode;
      f >> sl >> local >> remote >> st >> queues >> timer >> retr >> uid >> timeout >> inode;
      if (inodes.count(inode) == 0) continue;
      out.push_back(InetSocket{proto, decode_address(local), decode_address(remote), std::stoi(st, nullptr, 16)});
    }
  }
  return out;
}

/// The planner's signed-distance grid fettled builds for the recipe (~45 s on 2 cores) is kept
/// in the build tree between the tests of this file and between runs: it is keyed by the
/// golden samples and the settings, so a stale copy is rejected by fettled (with a warning),
/// rebuilt and kept again. The vision cache is keyed by the golden file's path and mtime and
/// is not worth sharing.
const fs::path kPlanningCache = ".pump-body.planning-cache";
const fs::path kCacheStore = kBin.parent_path() / "test-cache" / "fettled";

void copy_tree(const fs::path& from, const fs::path& to) {
  fs::remove_all(to);
  fs::create_directories(to.parent_path());
  fs::copy(from, to, fs::copy_options::recursive);
}

class Fettled : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    if (!fs::exists(kBin / "fettled")) GTEST_SKIP() << "fettled not built";
    dir_ = fs::temp_directory_path() / ("fettle-test-fettled-" + std::to_string(::getpid()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    // The recipe and its golden template (written by fettle-sim golden) in the test's own directory.
    fs::create_directories(dir_ / "parts");
    fs::copy_file(kSource / "config/parts/pump-body.toml", dir_ / "parts/pump-body.toml");
    const std::string golden = (kBin / "fettle-sim").string() + " golden --part " + (dir_ / "parts/pump-body.toml").string() +
                               " > " + (dir_ / "golden.log").string() + " 2>&1";
    ASSERT_EQ(std::system(golden.c_str()), 0) << read_text(dir_ / "golden.log");
    if (fs::exists(kCacheStore / kPlanningCache / "sdf-grid.bin"))
      copy_tree(kCacheStore / kPlanningCache, dir_ / "parts" / kPlanningCache);
    // The devices first, on free ports; then the cell file fettled reads, with those ports.
    const auto shipped = fettle::config::load_cell(kSource / "config/cell.sim.toml");
    fettle::sim::CellSimOptions o;
    o.cell = shipped;
    o.cell.robot.cell_id = "test-cell";  // the simulated robot checks HELLO's cell id against this
    o.plc_port = o.robot_port = o.spindle_port = 0;
    o.castings = 0;
    o.auto_start = false;
    // The simulator's default, as in the demo (a run takes 15-30 s there; at 4, A takes 2.5
    // times longer); the mid-run scenarios act within a second of the spindle starting.
    o.robot_speedup = 10.0;
    cell_ = new fettle::sim::CellSim(o);
    cell_->on_event([](const std::string& line) { std::cerr << "[cell] " << line << "\n"; });
    cell_->start();
    const auto config = dir_ / "cell.toml";
    std::ofstream(config) << cell_toml(dir_, cell_->plc_port(), cell_->robot_port(), cell_->spindle_port());
    spawn_fettled(false);
  }

  /// Starts fettled on the test's cell file; its output goes to fettled.log (appended to on a restart).
  static void spawn_fettled(bool append) {
    const std::string exe = (kBin / "fettled").string();
    const std::string log = (dir_ / "fettled.log").string();
    const std::string config = (dir_ / "cell.toml").string();
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_addopen(&fa, 1, log.c_str(), O_WRONLY | O_CREAT | (append ? O_APPEND : O_TRUNC), 0644);
    posix_spawn_file_actions_adddup2(&fa, 1, 2);
    // Not the simulated cell's sockets of this process (Asio's are not close-on-exec): fettled
    // gets what systemd would give it, stdin/stdout/stderr.
    posix_spawn_file_actions_addclosefrom_np(&fa, 3);
    std::vector<std::string> args{exe, "--config", config, "--allow-root"};
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    pid_ = 0;
    reaped_.reset();
    ASSERT_EQ(posix_spawn(&pid_, exe.c_str(), &fa, nullptr, argv.data(), environ), 0);
    posix_spawn_file_actions_destroy(&fa);
  }

  /// Waits up to `timeout` for fettled to exit; its wait status, or nullopt if it still runs.
  static std::optional<int> wait_exit(std::chrono::milliseconds timeout) {
    if (!wait_until([] { return !alive(); }, timeout)) return std::nullopt;
    return reaped_;
  }

  static void TearDownTestSuite() {
    // fettled stops on SIGTERM with exit status 0 (what systemd expects); a sanitizer report
    // during the run or the shutdown makes it non-zero (TSan exits 66, LeakSanitizer 23).
    bool clean_exit = true;
    if (pid_ > 0) {
      ::kill(pid_, SIGTERM);
      const auto status = wait_exit(10s);
      if (!status.has_value()) {
        ::kill(pid_, SIGKILL);
        ::waitpid(pid_, nullptr, 0);
        pid_ = 0;
        clean_exit = false;
        ADD_FAILURE() << "fettled did not exit within " << 10 * time_scale() << " s of SIGTERM\n" << tail_log();
      } else if (!WIFEXITED(*status) || WEXITSTATUS(*status) != 0) {
        clean_exit = false;
        ADD_FAILURE() << "fettled's exit on SIGTERM: wait status " << *status << "\n" << tail_log();
      }
    } else if (reaped_.has_value()) {  // it had exited before the teardown: a test saw it gone or waited for it
      clean_exit = false;
      std::cerr << "fettled had exited with wait status " << *reaped_ << "\n";
    }
    delete cell_;
    cell_ = nullptr;
    // Keep the grid for the next test (ctest runs each in its own process) and the next run.
    if (fs::exists(dir_ / "parts" / kPlanningCache / "sdf-grid.bin")) {
      std::error_code ec;
      const fs::path tmp = kCacheStore / ("tmp-" + std::to_string(::getpid()));
      copy_tree(dir_ / "parts" / kPlanningCache, tmp);
      fs::remove_all(kCacheStore / kPlanningCache, ec);
      fs::rename(tmp, kCacheStore / kPlanningCache, ec);
      if (ec) fs::remove_all(tmp, ec);
    }
    // Kept when a test failed: fettled.log and the records say what happened.
    if (clean_exit && ::testing::UnitTest::GetInstance()->failed_test_count() == 0) fs::remove_all(dir_);
    else std::cerr << "kept " << dir_ << " (fettled.log, state/) for the failed test\n";
  }

  void SetUp() override {
    if (!fs::exists(kBin / "fettled")) GTEST_SKIP() << "fettled not built";
    // A failed suite set-up (e.g. UDP 3956 taken by another camera) is a failure, not a skip.
    if (cell_ == nullptr || pid_ <= 0) FAIL() << "the simulated cell or fettled did not start: see the set-up failure above";
    ASSERT_TRUE(alive()) << tail_log();
  }

  /// fettled still runs. If it has exited, its wait status is kept in reaped_ (and pid_ is 0, so
  /// nothing signals a pid the system may have reused).
  static bool alive() {
    if (pid_ <= 0) return false;
    int status = 0;
    const pid_t r = ::waitpid(pid_, &status, WNOHANG);
    if (r == 0) return true;
    if (r == pid_) reaped_ = status;
    pid_ = 0;
    return false;
  }

  static std::string tail_log() {
    const auto text = read_text(dir_ / "fettled.log");
    return "fettled log (tail):\n" + text.substr(text.size() > 4000 ? text.size() - 4000 : 0);
  }

  /// fettled answers `fettle status` on its control socket (it is configured and serving).
  static bool answers() {
    const std::string socket = (dir_ / "fettled.sock").string();
    return alive() && run_output((kBin / "fettle").string() + " status --socket " + socket + " --json 2>/dev/null")
                              .find("\"state\"") != std::string::npos;
  }

  static State state() { return cell_->plc().fettle.state; }
  static int fault_code() { return cell_->plc().fettle.fault_code; }

  static ::testing::AssertionResult reaches(State s, std::chrono::milliseconds timeout) {
    if (wait_until([&] { return cell_->plc().fettle_written && state() == s; }, timeout))
      return ::testing::AssertionSuccess();
    return ::testing::AssertionFailure() << "expected " << fettle::packml::name(s) << ", fettled is "
                                         << fettle::packml::name(state()) << " (fault " << fault_code() << ")\n"
                                         << tail_log();
  }

  static void plc(const std::string& command) { ASSERT_TRUE(cell_->inject("plc " + command)); }

  /// Reset + Start from wherever the cell is (Stopped, Idle, Aborted, Held) into Execute.
  static ::testing::AssertionResult to_execute() {
    for (int i = 0; i < 8; ++i) {
      const auto s = state();
      if (s == State::execute && !cell_->plc().fettle.fault_latched) return ::testing::AssertionSuccess();
      if (s == State::aborted) (void)cell_->inject("plc clear");
      else if (s == State::stopped || s == State::complete) (void)cell_->inject("plc reset");
      else if (s == State::idle) (void)cell_->inject("plc start");
      else if (s == State::held) {
        (void)cell_->inject("plc reset");  // clears the latched fault
        std::this_thread::sleep_for(200ms);
        (void)cell_->inject("plc unhold");
      } else if (s == State::execute) {
        (void)cell_->inject("plc reset");  // only the latch
      }
      wait_until([&] { return state() != s || (s == State::execute && !cell_->plc().fettle.fault_latched); }, 15s);
    }
    if (state() == State::execute && !cell_->plc().fettle.fault_latched) return ::testing::AssertionSuccess();
    return ::testing::AssertionFailure() << "could not bring fettled to Execute: " << fettle::packml::name(state())
                                         << tail_log();
  }

  /// One cycle for what is on the fixture; waits for a result. True if a result came.
  static bool good_cycle(std::uint64_t seed) {
    cell_->load(seed);
    const auto before = cell_->plc().results.size();
    cell_->request();
    // processing ~15 s, the run ~30 s (the simulator grinds the casting before the robot's
    // DONE), verification, possibly one re-grind: a few minutes on the 2-core machine
    return wait_until([&] { return cell_->plc().results.size() > before; }, 360s);
  }

  /// Requests a cycle and waits for the fault and the state it must end in.
  static void expect_fault(int code, State end, std::chrono::milliseconds timeout = 90s) {
    EXPECT_TRUE(wait_until([&] { return cell_->plc().fettle.fault_latched; }, timeout)) << tail_log();
    EXPECT_EQ(fault_code(), code) << tail_log();
    EXPECT_TRUE(reaches(end, 20s));
  }

  static bool spindle_turning() {
    return wait_until([&] { return cell_->spindle_rpm() > 1000.0; }, 90s);
  }

  static fs::path dir_;
  static fettle::sim::CellSim* cell_;
  static pid_t pid_;
  static std::optional<int> reaped_;  ///< fettled's wait status when alive() found it gone
};

fs::path Fettled::dir_;
fettle::sim::CellSim* Fettled::cell_ = nullptr;
pid_t Fettled::pid_ = 0;
std::optional<int> Fettled::reaped_;

// Each TEST below runs in its own process under ctest (gtest_discover_tests), with its own
// fettled and simulated cell. A: the three cycles (~105 s on the 2-core machine, ~320 s
// under ASan).
// B: the faults that arrive over a device's wire (Modbus, GigE Vision, the robot's line
// protocol, CANopen), in one process so the journal can be checked across them all. Every
// fault case, one test each, runs in-process in test_cycle_faults.cpp.
TEST_F(Fettled, A_ThreeCyclesWithResultsAndRecords) {
  ASSERT_TRUE(reaches(State::stopped, 300s));
  ASSERT_TRUE(to_execute());
  {
    // The PLC sees every state fettled enters, the acting ones too, in order.
    const std::vector<State> path{State::stopped, State::resetting, State::idle, State::starting, State::execute};
    const auto seen = cell_->plc().states;
    auto it = seen.begin();
    for (const auto s : path) {
      it = std::find(it, seen.end(), s);
      ASSERT_NE(it, seen.end()) << "the PLC never saw " << fettle::packml::name(s) << " in order";
    }
  }
  for (std::uint64_t seed = 1; seed <= 3; ++seed) ASSERT_TRUE(good_cycle(seed)) << "cycle " << seed << tail_log();
  const auto results = cell_->plc().results;
  ASSERT_EQ(results.size(), 3U);
  for (auto r : results)
    EXPECT_TRUE(r == fettle::drivers::plc::CycleResult::ok || r == fettle::drivers::plc::CycleResult::nok);
  EXPECT_EQ(fault_code(), 0);
  // Every cycle's record: report.json with the result, the calibration's identity (sha256 of the
  // file as read) and every file it lists present.
  std::size_t records = 0;
  for (const auto& d : fs::directory_iterator(dir_ / "state/cycles")) {
    if (!d.is_directory()) continue;
    ++records;
    const auto report = nlohmann::json::parse(read_text(d.path() / "report.json"));
    const std::string result = report.value("result", "");
    EXPECT_TRUE(result == "OK" || result == "NOK") << d.path() << ": " << result;
    const std::string sha = report["calibration"].value("sha256", "");
    EXPECT_EQ(sha.size(), 64U) << d.path();
    EXPECT_EQ(sha.find_first_not_of("0123456789abcdef"), std::string::npos) << sha;
    for (const auto& f : report["files"]) EXPECT_TRUE(fs::exists(d.path() / f.get<std::string>())) << d.path() << " " << f;
    // [compensation] is on by default: each verified cycle measured where its tool cut
    // (docs/compensation.md); the simulated cell's riser face fixes the vertical at least
    const auto& comp = report["compensation"];
    ASSERT_TRUE(comp.is_object()) << d.path();
    EXPECT_GE(comp["measured"].value("directions_observed", 0), 1) << d.path() << ": " << comp.dump();
    EXPECT_GT(comp["measured"].value("points", 0), 100) << d.path() << ": " << comp.dump();
  }
  EXPECT_EQ(records, 3U);
  // the estimate outlives the daemon: three cycles in the state file, under this calibration
  const auto state = nlohmann::json::parse(read_text(dir_ / "state/compensation.json"));
  EXPECT_EQ(state.value("updates", 0), 3) << state.dump();
  EXPECT_EQ(state.value("calibration_id", "").size(), 64U) << state.dump();
}

/// One fault scenario: what to do to the cell, the fault code and the state it must end in.
struct FaultScenario {
  const char* name;
  int code;
  State end;
  std::chrono::milliseconds timeout;
  std::function<void()> provoke;  ///< loads a casting, injects the fault, requests the cycle
};

TEST_F(Fettled, B_FaultsOnTheWireEndInTheirStateAndTheCellRecovers) {
  ASSERT_TRUE(reaches(State::stopped, 300s));
  // The simulated robot injects only codes the protocol allows (a malformed FAULT line would
  // be a link fault, 303, not the robot fault 302 the injection means).
  const auto bad_code = cell_->inject("robot fault-at 40 E-STOP");
  ASSERT_FALSE(bad_code);
  EXPECT_NE(bad_code.error().message.find("not a protocol code"), std::string::npos) << bad_code.error().message;
  // Seeds differ from A's so a cached result cannot hide anything. The waits: processing takes
  // ~15-30 s at 1032x772 under load, the robot's run starts after it.
  const std::vector<FaultScenario> scenarios{
      {"PLC link drop mid-cycle", 101, State::held, 30s,
       [] {
         cell_->load(6);
         cell_->request();
         ASSERT_TRUE(wait_until([&] { return cell_->plc().cycles_accepted > 0 && cell_->plc().fettle.slide_target != 0; }, 30s))
             << tail_log();
         plc("drop");
       }},
      // The slide already in fault when the cycle commands it: no new slide state arrives, so
      // fettled must read the fault it already knows, not wait out travel_timeout_ms and report
      // a timeout (104).
      {"slide faulted before the cycle", 105, State::held, 10s,
       [] {
         cell_->load(3);
         plc("slide-fault on");
         std::this_thread::sleep_for(200ms);  // the PLC's slide state reaches fettled
         cell_->request();
       }},
      {"camera timeout", 201, State::held, 90s,
       [] {
         cell_->load(4);
         ASSERT_TRUE(cell_->inject("camera drop 2"));  // retries = 1: two attempts, both lost
         cell_->request();
       }},
      {"robot NAK", 301, State::held, 120s,
       [] {
         cell_->load(7);
         ASSERT_TRUE(cell_->inject("robot nak TRAJ ENVELOPE"));
         cell_->request();
       }},
      {"robot disconnect mid-run", 303, State::aborted, 30s,
       [] {
         cell_->load(8);
         cell_->request();
         ASSERT_TRUE(spindle_turning()) << tail_log();
         std::this_thread::sleep_for(300ms);
         ASSERT_TRUE(cell_->inject("robot drop"));
       }},
      {"spindle fault", 401, State::aborted, 30s,
       [] {
         cell_->load(9);
         cell_->request();
         ASSERT_TRUE(spindle_turning()) << tail_log();
         ASSERT_TRUE(cell_->inject("spindle fault overcurrent"));
       }},
  };
  for (const auto& s : scenarios) {
    SCOPED_TRACE(s.name);
    ASSERT_TRUE(to_execute());
    s.provoke();
    if (HasFatalFailure()) return;
    expect_fault(s.code, s.end, s.timeout);
    EXPECT_TRUE(alive()) << tail_log();
    if (HasFailure()) return;  // the next scenario would start from an unknown state
  }
  // Recovered after a reset: a good cycle.
  ASSERT_TRUE(to_execute());
  ASSERT_TRUE(good_cycle(10)) << tail_log();
  EXPECT_TRUE(alive());
  // Every cycle started has ended, with report.json in its directory.
  const auto journal = read_text(dir_ / "state/journal.jsonl");
  std::map<std::string, std::string> results;
  std::istringstream in(journal);
  std::string line;
  while (std::getline(in, line)) {
    const auto j = nlohmann::json::parse(line);
    if (j["event"] == "start") results[j["id"]] = "";
    if (j["event"] == "end") results[j["id"]] = j["result"];
  }
  std::multiset<std::string> kinds;
  int marked = 0;  // faulted cycles whose record marks the step the fault ended
  for (const auto& [id, result] : results) {
    EXPECT_FALSE(result.empty()) << "cycle " << id << " never ended";
    kinds.insert(result);
    const auto path = dir_ / "state/cycles" / id / "report.json";
    EXPECT_TRUE(fs::exists(path)) << id;
    if (!fs::exists(path)) continue;
    // A step the fault ended is marked failed, and only that one, the last: a record never shows
    // a failed step (a refused validate, say) as passed.
    const auto steps = nlohmann::json::parse(read_text(path)).value("steps", nlohmann::json::array());
    std::vector<std::size_t> failed;
    for (std::size_t i = 0; i < steps.size(); ++i)
      if (steps[i].value("failed", false)) failed.push_back(i);
    if (result == "OK" || result == "NOK") {
      EXPECT_TRUE(failed.empty()) << id << ": " << steps.dump();
    } else {
      EXPECT_LE(failed.size(), 1U) << id << ": " << steps.dump();
      if (!failed.empty()) {
        EXPECT_EQ(failed.front(), steps.size() - 1) << id << ": " << steps.dump();
        ++marked;
      }
    }
  }
  EXPECT_GE(marked, 4) << "the faults of B end their cycles inside a step (camera, robot, spindle)";
  EXPECT_EQ(kinds.count("FAULT"), 4U) << journal;
  EXPECT_EQ(kinds.count("ABORTED"), 2U) << journal;
  EXPECT_EQ(kinds.count("OK") + kinds.count("NOK"), 1U) << journal;
  EXPECT_EQ(results.size(), 7U) << journal;
  const auto report = nlohmann::json::parse(read_text(dir_ / "state/cycles" / results.rbegin()->first / "report.json"));
  EXPECT_TRUE(report.contains("steps"));

  // What the PLC saw on the wire: one result per accepted request, the faulted ones' FAULT too
  // (the one of the link drop after the link came back), and every state of the Hold and Abort
  // paths, the acting ones included, in order.
  const auto plc_seen = cell_->plc();
  EXPECT_EQ(static_cast<int>(plc_seen.results.size()), plc_seen.cycles_accepted);
  EXPECT_EQ(std::count(plc_seen.results.begin(), plc_seen.results.end(), fettle::drivers::plc::CycleResult::fault), 6);
  std::string states;
  for (const auto st : plc_seen.states) states += std::string(fettle::packml::name(st)) + " ";
  for (const std::string run : {"Execute Holding Held ", "Held Unholding Execute ", "Execute Aborting Aborted ",
                                "Aborted Clearing Stopped Resetting Idle Starting Execute "})
    EXPECT_NE((" " + states).find(" " + run), std::string::npos) << "the PLC never saw " << run << "in a row: " << states;
}

/// The journal as id -> last event's result ("" while only started, "INTERRUPTED" when marked).
std::map<std::string, std::string> journal_results(const fs::path& journal) {
  std::map<std::string, std::string> results;
  std::istringstream in(read_text(journal));
  std::string line;
  while (std::getline(in, line)) {
    if (line.empty()) continue;
    const auto j = nlohmann::json::parse(line);
    if (j["event"] == "start") results[j["id"]] = "";
    if (j["event"] == "end") results[j["id"]] = j["result"];
    if (j["event"] == "interrupted") results[j["id"]] = "INTERRUPTED";
  }
  return results;
}

// C: what systemd does to a running daemon. SIGTERM while the robot grinds: the robot is told
// STOP, the spindle stops, the cycle's record is finalised (ABORTED, 602) and fettled exits 0.
// SIGKILL while the robot grinds: nothing can be finalised, so after the restart the cycle shows
// as INTERRUPTED in the journal and through `fettle cycles`; the robot halted when the
// connection went, the drive stopped when fettled's heartbeat did.
TEST_F(Fettled, C_SigtermAndSigkillMidCycle) {
  const fs::path journal = dir_ / "state/journal.jsonl";
  const std::string socket = (dir_ / "fettled.sock").string();
  const std::string fettle = (kBin / "fettle").string();
  ASSERT_TRUE(wait_until(answers, 300s)) << tail_log();  // the first start builds the planning grid

  // --- SIGTERM mid-run ---
  ASSERT_TRUE(to_execute());
  const auto halted_before = cell_->robot_stats().trajectories_halted;
  const auto executed_before = cell_->robot_stats().trajectories_executed;
  cell_->load(11);
  cell_->request();
  ASSERT_TRUE(spindle_turning()) << tail_log();
  std::this_thread::sleep_for(500ms);
  ASSERT_EQ(cell_->robot_stats().trajectories_executed, executed_before) << "the run ended before the signal";
  std::string term_id;
  for (const auto& [id, result] : journal_results(journal))
    if (result.empty()) term_id = id;
  ASSERT_FALSE(term_id.empty()) << read_text(journal);
  ASSERT_EQ(::kill(pid_, SIGTERM), 0);
  const auto status = wait_exit(60s);
  ASSERT_TRUE(status.has_value()) << "fettled did not exit within 60 s of SIGTERM\n" << tail_log();
  EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 0) << "wait status " << *status << "\n" << tail_log();
  // At once: the drive's own heartbeat-loss stop comes only a heartbeat timeout (1 s) after fettled's last one.
  EXPECT_LT(std::abs(cell_->spindle_rpm()), 1.0) << "fettled exited with the spindle turning";
  // Released before the exit: two heartbeat timeouts later the drive has not faulted.
  std::this_thread::sleep_for(2s);
  EXPECT_NE(cell_->spindle_state(), fettle::canopen::DriveState::fault)
      << "a clean stop left the drive faulted (heartbeat lost)\n" << tail_log();
  const auto robot = cell_->robot_stats();
  EXPECT_EQ(robot.trajectories_halted, halted_before + 1);
  EXPECT_EQ(robot.last_halt_reason, "STOP") << "the robot must be stopped by fettled, not by the lost connection";
  EXPECT_EQ(journal_results(journal)[term_id], "ABORTED") << read_text(journal);
  const auto report = nlohmann::json::parse(read_text(dir_ / "state/cycles" / term_id / "report.json"));
  EXPECT_EQ(report.value("result", ""), "ABORTED");
  EXPECT_EQ(report["fault"].value("code", 0), 602) << report.dump(2);

  // --- SIGKILL mid-run, then a restart ---
  // The PLC asks for the next cycle (the aborted one ended with a FAULT result): the restarted
  // fettled runs one for what is on the fixture once in Execute, so the next casting goes on first.
  cell_->load(12);
  spawn_fettled(true);
  ASSERT_TRUE(wait_until(answers, 120s)) << tail_log();
  ASSERT_TRUE(to_execute());
  const auto running = [&] {
    for (const auto& [id, result] : journal_results(journal))
      if (result.empty()) return true;
    return false;
  };
  if (!wait_until(running, 10s)) cell_->request();
  ASSERT_TRUE(spindle_turning()) << tail_log();
  std::this_thread::sleep_for(500ms);
  std::string kill_id;
  for (const auto& [id, result] : journal_results(journal))
    if (result.empty()) kill_id = id;
  ASSERT_FALSE(kill_id.empty()) << read_text(journal);
  ASSERT_EQ(::kill(pid_, SIGKILL), 0);
  ASSERT_TRUE(wait_exit(10s).has_value());
  EXPECT_TRUE(wait_until([&] { return cell_->robot_stats().trajectories_halted == halted_before + 2; }, 10s));
  EXPECT_EQ(cell_->robot_stats().last_halt_reason, "connection closed");
  EXPECT_TRUE(wait_until([] { return std::abs(cell_->spindle_rpm()) < 1.0; }, 10s))
      << "the drive kept turning at " << cell_->spindle_rpm() << " rpm without fettled's heartbeat";
  EXPECT_EQ(journal_results(journal)[kill_id], "") << "nothing can write after SIGKILL";

  spawn_fettled(true);
  ASSERT_TRUE(wait_until(answers, 120s)) << tail_log();
  EXPECT_EQ(journal_results(journal)[kill_id], "INTERRUPTED") << read_text(journal);
  const auto listed = nlohmann::json::parse(run_output(fettle + " cycles --socket " + socket + " --json"), nullptr, false);
  ASSERT_TRUE(listed.is_array()) << listed.dump();
  bool shown = false;
  for (const auto& c : listed)
    if (c.value("id", "") == kill_id) {
      shown = true;
      EXPECT_EQ(c.value("result", ""), "INTERRUPTED") << c.dump();
    }
  EXPECT_TRUE(shown) << kill_id << " not in `fettle cycles`: " << listed.dump();
  EXPECT_TRUE(alive()) << tail_log();
}

// D: the attack surface of a running, connected fettled (docs/security.md): no TCP port listens,
// every TCP connection goes to a configured peer (PLC, robot, socketcand), and the camera's UDP
// sockets are bound to the camera's network (127.0.0.1 here), not to every interface.
// E: a wheel the cell predicts worn past its life stops the cycle before the scan with tool.worn
// (404, Held); `fettle tool changed` fits a new one and the next cycle grinds (docs/compensation.md,
// "Wheel wear"). The state file fettled starts from says the cup wheel removed 60 cm3: up to
// 1.3 x 0.05 x 60 = 3.9 mm of its radius, past its 3 mm life.
TEST_F(Fettled, E_AWornWheelStopsTheCellUntilANewOneIsFitted) {
  ASSERT_TRUE(wait_until(answers, 300s)) << tail_log();  // the first start builds the planning grid
  ASSERT_EQ(::kill(pid_, SIGTERM), 0);
  ASSERT_TRUE(wait_exit(60s).has_value());
  const auto state_file = dir_ / "state/compensation.json";
  const nlohmann::json worn = {{"bias_mm", {0.0, 0.0, 0.0}}, {"updates", 0}, {"tools", {{"flat-16", {{"removed_cm3", 60.0}}}}}};
  std::ofstream(state_file) << worn.dump(2);
  spawn_fettled(true);
  ASSERT_TRUE(wait_until(answers, 120s)) << tail_log();
  ASSERT_TRUE(to_execute());
  cell_->load(7);
  cell_->request();
  expect_fault(404, State::held);
  EXPECT_NE(read_text(dir_ / "fettled.log").find("wheel 'flat-16' is worn"), std::string::npos) << tail_log();
  const std::string socket = (dir_ / "fettled.sock").string();
  const auto out = run_output((kBin / "fettle").string() + " tool changed flat-16 --socket " + socket + " 2>&1");
  EXPECT_NE(out.find("a new wheel 'flat-16' is fitted"), std::string::npos) << out;
  const auto unknown = run_output((kBin / "fettle").string() + " tool changed flat-61 --socket " + socket + " 2>&1");
  EXPECT_NE(unknown.find("flat-61"), std::string::npos) << unknown;
  const auto state = nlohmann::json::parse(read_text(state_file));
  EXPECT_EQ(state["tools"]["flat-16"].value("removed_cm3", -1.0), 0.0) << state.dump();
  EXPECT_EQ(state["tools"]["flat-16"].value("changes", 0), 1) << state.dump();
  ASSERT_TRUE(to_execute());
  ASSERT_TRUE(good_cycle(7)) << tail_log();
  EXPECT_EQ(fault_code(), 0) << tail_log();
  // the new wheel counts the iron this cycle removed
  const auto after = nlohmann::json::parse(read_text(state_file));
  EXPECT_GT(after["tools"]["flat-16"].value("removed_cm3", 0.0), 1.0) << after.dump();
}

TEST_F(Fettled, D_ListensOnNoTcpPortAndTalksOnlyToItsConfiguredPeers) {
  ASSERT_TRUE(wait_until(answers, 300s)) << tail_log();
  ASSERT_TRUE(to_execute());  // every link is up
  const std::set<std::string> peers{"127.0.0.1:" + std::to_string(cell_->plc_port()),
                                    "127.0.0.1:" + std::to_string(cell_->robot_port()),
                                    "127.0.0.1:" + std::to_string(cell_->spindle_port())};
  const auto sockets = inet_sockets(pid_);
  std::set<std::string> connected;
  std::size_t udp = 0;
  for (const auto& s : sockets) {
    SCOPED_TRACE(s.text());
    if (s.proto.rfind("tcp", 0) == 0) {
      EXPECT_NE(s.state, 10) << "fettled listens on a TCP port";
      if (s.state == 1) {
        EXPECT_EQ(peers.count(s.remote), 1U) << "a TCP connection to something not in the cell file";
        connected.insert(s.remote);
      }
    } else {
      ++udp;
      EXPECT_EQ(s.local.rfind("127.0.0.1:", 0), 0U) << "a UDP socket bound beyond the camera's network";
    }
  }
  EXPECT_EQ(connected, peers) << "fettled should be connected to the PLC, the robot and the spindle's socketcand";
  EXPECT_GT(udp, 0U) << "the camera link (GigE Vision, UDP) should be open";
  EXPECT_TRUE(alive()) << tail_log();
}

}  // namespace
