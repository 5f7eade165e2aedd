// fettle-sim soak --cycles N --fault-rate R --out DIR: drives fettled (a separate process, as
// under systemd) through N cycles on the simulated cell (in this process, loopback, ephemeral
// ports) in accelerated time, with a random fault from one of the devices in a share R of the
// cycles. Afterwards it checks what issue 11 asks of a soak:
//   - fettled never crashed or restarted (one pid from start to end; it exits 0 on SIGTERM);
//   - every cycle fettled started has a complete record with its outcome (the journal's start
//     and end lines; report.json with the same result; every file it lists exists);
//   - every injected fault reached the PLC with its code (fault register), and the journal's
//     end line of that cycle carries the same code;
//   - no trajectory reached the robot without passing validation (the record's validate step
//     before every upload; the simulated robot saw no point outside its limits);
//   - fettled's resident memory grew less than --max-rss-growth-pct after the warm-up.
// Writes DIR/soak.json (per cycle: seed, fault, outcome, code, seconds, RSS) and prints one
// line per cycle and a summary. Exit 0 only if every check passed.
//
// To keep 500 cycles within an hour on two cores the simulated cell is faster than the demo:
// the camera delivers --resolution (516x386 by default), the robot runs --speedup times real
// time, the grinding simulation is off (runs take their time but remove no material), and the
// cell file fettled gets has verification_scan = false (a re-scan would see the casting
// unground). Everything else - the protocols, the vision and planning, validation, records -
// is what fettled does in the demo.
#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include <nlohmann/json.hpp>

#include "fettle/config/load.hpp"
#include "fettle/core/atomic_file.hpp"
#include "fettle/cli/cli.hpp"
#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/process/pipeline.hpp"
#include "fettle/drivers/packml.hpp"
#include "fettle/drivers/plc_registers.hpp"
#include "fettle/sim/cell.hpp"
#include "sim_common.hpp"

extern char** environ;

namespace {

namespace fs = std::filesystem;
using fettle::packml::State;
using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;
using json = nlohmann::ordered_json;

struct Args {
  fs::path config = "config/cell.sim.toml";
  fs::path out;
  fs::path fettled;
  int cycles = 50;
  double fault_rate = 0.3;
  std::uint64_t seed = 1;
  std::string resolution = "516x386";
  double speedup = 100.0;
  int warmup = 0;  ///< 0 = max(5, cycles / 10)
  double max_rss_growth_pct = 10.0;  ///< 0: not checked (fettled under AddressSanitizer)
  double min_ok_pct = 80.0;  ///< cycles without an injected fault that must end OK or NOK
  int keep_cycles = 30;
  int heartbeat_timeout_ms = 1000;  ///< fettled's [plc] and [spindle] heartbeat_timeout_ms (and the robot's missed pings)
  fs::path planning_cache;  ///< a planning cache to start from (else the one next to the shipped recipe)
};

std::string read_text(const fs::path& p) {
  std::ifstream in(p);
  return {std::istreambuf_iterator<char>(in), {}};
}

bool wait_until(const std::function<bool()>& pred, std::chrono::milliseconds timeout) {
  const auto end = Clock::now() + timeout;
  while (Clock::now() < end) {
    if (pred()) return true;
    std::this_thread::sleep_for(20ms);
  }
  return pred();
}

/// A fault the soak can inject: what to do, when, the fault codes fettled must report.
struct FaultKind {
  std::string name;
  std::string device;
  std::set<int> codes;
  enum class When { before_request, slide_moving, robot_running, no_cycle } when = When::before_request;
  std::vector<std::string> inject;  ///< CellSim::inject lines
  std::vector<std::string> undo;    ///< lines that end the condition once the fault is latched
};

/// At most this share of the drawn faults may find their cycle ended before the moment to
/// inject them (a robot fault in a cycle refused at planning, say).
constexpr double kMaxNotInjectedPct = 25.0;

std::vector<FaultKind> fault_kinds() {
  using W = FaultKind::When;
  return {
      {"PLC link drop during the scan", "plc", {101}, W::slide_moving, {"plc drop"}, {}},
      {"PLC heartbeat frozen", "plc", {101}, W::no_cycle, {"plc freeze on"}, {"plc freeze off"}},
      {"PLC slide_state register out of range", "plc", {103}, W::no_cycle, {"plc force 4 9"}, {"plc release all"}},
      {"slide fault", "plc", {105}, W::before_request, {"plc slide-fault on"}, {}},
      {"camera frames lost", "camera", {201}, W::before_request, {"camera drop 2"}, {}},
      {"robot NAKs the trajectory", "robot", {301}, W::before_request, {"robot nak TRAJ ENVELOPE"}, {}},
      {"robot FAULT mid-run", "robot", {302}, W::before_request, {"robot fault-at 40 ESTOP"}, {}},
      {"robot link lost mid-run", "robot", {303}, W::robot_running, {"robot drop"}, {}},
      {"robot link lost mid-upload", "robot", {303}, W::before_request, {"robot disconnect-at-chunk 2"}, {}},
      {"spindle overcurrent mid-run", "spindle", {401}, W::robot_running, {"spindle fault overcurrent"}, {}},
      {"empty fixture", "part", {501}, W::before_request, {"part empty"}, {}},
      {"wrong part", "part", {502}, W::before_request, {}, {}},  // load_wrong instead of load
  };
}

std::string cell_toml(const fs::path& dir, const fettle::config::CellConfig& shipped, const fs::path& part, int plc,
                      int robot, int spindle, int keep_cycles, int heartbeat_timeout_ms) {
  const int recipe_id = shipped.cell.recipes.front().plc_recipe_id;  // the one the simulated PLC requests
  std::ostringstream t;
  auto list = [](const auto& v) {
    std::ostringstream o;
    o << "[";
    for (std::size_t i = 0; i < v.size(); ++i) o << (i ? ", " : "") << std::to_string(v[i]);
    o << "]";
    return o.str();
  };
  const auto& s = shipped.safety;
  t << "# written by fettle-sim soak\n[cell]\nname = \"soak-cell\"\nstate_dir = \"" << (dir / "state").string()
    << "\"\nworkers = 2\nverification_scan = false\n\n[[cell.recipes]]\nplc_recipe_id = " << recipe_id << "\nfile = \""
    << part.string()
    << "\"\n\n[logging]\nlevel = \"info\"\n\n"
    << "[plc]\naddress = \"127.0.0.1\"\nport = " << plc
    << "\nunit_id = 1\nresponse_timeout_ms = 300\npoll_period_ms = 20\nheartbeat_timeout_ms = " << heartbeat_timeout_ms << "\n"
    << "reconnect_initial_ms = 100\nreconnect_max_ms = 500\n\n"
    << "[slide]\nphoto_positions_mm = " << list(shipped.slide.photo_positions_mm) << "\ntravel_timeout_ms = 20000\n\n"
    << "[camera]\naddress = \"127.0.0.1\"\nframe_timeout_ms = 1500\nretries = 1\nexposure_us = 10000.0\n"
    << "pixel_format = \"Coord3D_C16\"\n\n"
    << "[robot]\naddress = \"127.0.0.1\"\nport = " << robot
    << "\ncell_id = \"soak-cell\"\nreply_timeout_ms = 2000\nping_period_ms = 500\nmissed_pings = "
    << std::max(3, (heartbeat_timeout_ms + 499) / 500) << "\n"
    << "chunk_points = 20\nrun_timeout_ms = 120000\nreconnect_initial_ms = 100\nreconnect_max_ms = 500\n\n"
    << "[spindle]\ntransport = \"socketcand\"\naddress = \"127.0.0.1\"\nport = " << spindle
    << "\ninterface = \"" << shipped.spindle.interface << "\"\nnode_id = " << shipped.spindle.node_id
    << "\nmode = \"profile_velocity\"\nheartbeat_timeout_ms = " << heartbeat_timeout_ms << "\n\n"
    << "[calibration]\nfile = \"" << fs::absolute(shipped.calibration.file).string() << "\"\n\n"
    << "[safety]\nworkspace_min_mm = " << list(s.workspace_min_mm) << "\nworkspace_max_mm = " << list(s.workspace_max_mm)
    << "\ntool_axis_cone_deg = " << std::to_string(s.tool_axis_cone_deg)
    << "\nmax_speed_mm_s = " << std::to_string(s.max_speed_mm_s)
    << "\nmax_spindle_rpm = " << std::to_string(s.max_spindle_rpm)
    << "\nsafe_height_mm = " << std::to_string(s.safe_height_mm) << "\n\n"
    << "[control]\nsocket = \"" << (dir / "fettled.sock").string() << "\"\n\n"
    << "[records]\nkeep_cycles = " << keep_cycles << "\nkeep_mb = 5000.0\nmin_free_mb = 100.0\n";
  return t.str();
}

/// fettled's resident set size in kB (0 if it is gone).
long rss_kb(pid_t pid) {
  std::istringstream in(read_text("/proc/" + std::to_string(pid) + "/status"));
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("VmRSS:", 0) == 0) return std::atol(line.c_str() + 6);
  return 0;
}

/// What one cycle of the soak did and saw.
struct CycleOutcome {
  int index = 0;
  std::uint64_t seed = 0;
  std::string fault;  ///< injected fault's name, "" for none
  std::string not_injected;  ///< why the fault was not injected after all (the cycle ended first)
  bool wheel_change = false;  ///< fettled asked for a new wheel (tool.worn): a maintenance stop
  std::string device;
  std::set<int> expected_codes;
  int plc_fault_code = 0;  ///< the PLC's fault register once latched
  std::string plc_result;  ///< OK / NOK / ... if a result came
  std::string state;       ///< fettled's PackML state at the end
  double seconds = 0.0;
  long rss_kb = 0;
  std::vector<std::string> problems;
};

/// Reads the journal as it grows; checks each ended cycle's record while it still exists.
class JournalChecker {
 public:
  explicit JournalChecker(fs::path state_dir) : dir_(std::move(state_dir)) {}

  /// New complete lines since the last call; returns problems found (records of ended cycles).
  std::vector<std::string> poll() {
    std::vector<std::string> problems;
    std::ifstream in(dir_ / "journal.jsonl");
    in.seekg(static_cast<std::streamoff>(offset_));
    std::string line;
    while (std::getline(in, line)) {
      if (in.eof()) break;  // a line still being written (no newline yet)
      offset_ += line.size() + 1;
      ++lines_;
      if (line.empty()) continue;
      json j;
      try {
        j = json::parse(line);
      } catch (const std::exception& e) {
        problems.push_back("journal line " + std::to_string(lines_) + " is not JSON: " + e.what());
        continue;
      }
      const std::string id = j.value("id", "");
      const std::string event = j.value("event", "");
      if (event == "start") {
        open_.insert(id);
        ++started_;
      } else if (event == "end") {
        if (open_.erase(id) == 0) problems.push_back("cycle " + id + ": an end without a start in the journal");
        ++ended_;
        last_end_ = j;
        check_record(j, problems);
      } else if (event == "interrupted") {
        problems.push_back("cycle " + id + " is marked interrupted: fettled restarted");
      }
    }
    return problems;
  }

  [[nodiscard]] const std::set<std::string>& open() const { return open_; }
  [[nodiscard]] int started() const { return started_; }
  [[nodiscard]] int ended() const { return ended_; }
  [[nodiscard]] int records_checked() const { return checked_; }
  [[nodiscard]] int uploads() const { return uploads_; }
  /// The last end line read (empty before any).
  [[nodiscard]] const json& last_end() const { return last_end_; }

 private:
  void check_record(const json& end, std::vector<std::string>& problems) {
    const std::string id = end.value("id", "");
    const fs::path dir = end.value("dir", "");
    const std::string what = "cycle " + id + ": ";
    if (!fs::exists(dir / "report.json")) return problems.push_back(what + "no report.json in " + dir.string());
    json r;
    try {
      r = json::parse(read_text(dir / "report.json"));
    } catch (const std::exception& e) {
      return problems.push_back(what + "report.json is not JSON: " + e.what());
    }
    ++checked_;
    if (r.value("result", "") != end.value("result", "?"))
      problems.push_back(what + "report.json says " + r.value("result", "") + ", the journal " + end.value("result", ""));
    if (r.value("result", "").empty() || r.value("result", "") == "running")
      problems.push_back(what + "report.json has no final result");
    for (const auto& f : r.value("files", json::array()))
      if (!fs::exists(dir / f.get<std::string>())) problems.push_back(what + "report.json lists " + f.get<std::string>() + ", missing");
    // Every upload (also a re-grind's) must follow its own validate step, one that passed.
    bool validated = false;
    for (const auto& s : r.value("steps", json::array())) {
      const std::string step = s.value("step", "");
      if (step.rfind("validate", 0) == 0) validated = !s.value("failed", false);
      if (step.rfind("upload", 0) == 0) {
        ++uploads_;
        if (!validated) problems.push_back(what + "'" + step + "' without a passed validate step before it");
        validated = false;
      }
    }
  }

  fs::path dir_;
  std::size_t offset_ = 0;
  int lines_ = 0, started_ = 0, ended_ = 0, checked_ = 0, uploads_ = 0;
  std::set<std::string> open_;
  json last_end_;
};

class Soak {
 public:
  explicit Soak(Args a) : a_(std::move(a)), rng_(a_.seed) {}

  int run() {
    setup();
    std::printf("soak: %d cycles, fault rate %.2f, seed %llu, camera %s, robot x%.0f; fettled pid %d, log %s\n",
                a_.cycles, a_.fault_rate, static_cast<unsigned long long>(a_.seed), a_.resolution.c_str(), a_.speedup,
                static_cast<int>(pid_), (a_.out / "fettled.log").c_str());
    std::fflush(stdout);
    if (!reaches(State::stopped, 600s))
      return finish(alive() ? "fettled did not reach Stopped within 600 s (loading the recipe, building its planning grid)" +
                                  tail_log()
                            : "fettled ended during its start-up (" + ended_how_ + "); a bad cell file? " + tail_log());
    const auto kinds = fault_kinds();
    std::uniform_real_distribution<double> coin(0.0, 1.0);
    std::uniform_int_distribution<std::size_t> pick(0, kinds.size() - 1);
    const auto t_all = Clock::now();
    started_utc_ = fettle::sim::app::utc_now();
    for (int i = 1; i <= a_.cycles; ++i) {
      if (!alive()) return finish("fettled is gone before cycle " + std::to_string(i) + ": " + tail_log());
      if (!recover())
        return finish("cycle " + std::to_string(i) + ": Clear/Reset/Unhold/Start did not bring fettled back to Execute (" +
                      where() + ")" + tail_log());
      const bool faulty = coin(rng_) < a_.fault_rate;
      const FaultKind* kind = faulty ? &kinds[pick(rng_)] : nullptr;
      outcomes_.push_back(one_cycle(i, kind));
      const auto& o = outcomes_.back();
      drain_journal();
      print(o);
    }
    minutes_ = std::chrono::duration<double>(Clock::now() - t_all).count() / 60.0;
    std::printf("soak: %d cycles in %.0f s\n", a_.cycles, minutes_ * 60.0);
    return finish("");
  }

  ~Soak() {
    if (pid_ > 0) {
      ::kill(pid_, SIGKILL);
      ::waitpid(pid_, nullptr, 0);
    }
    if (cell_) cell_->stop();  // its event handler writes to cell_log_
  }

 private:
  void setup() {
    if (a_.out.empty()) throw fettle::UserError("--out is required");
    if (a_.cycles <= warmup())
      throw fettle::UserError("--cycles " + std::to_string(a_.cycles) + ": needs more cycles than the warm-up (" +
                              std::to_string(warmup()) + ", --warmup) to judge fettled's memory");
    fs::create_directories(a_.out / "parts");
    a_.out = fs::absolute(a_.out);
    if (a_.fettled.empty()) a_.fettled = fs::read_symlink("/proc/self/exe").parent_path() / "fettled";
    if (!fs::exists(a_.fettled))
      throw fettle::UserError("--fettled " + a_.fettled.string() + ": no such program (build fettled, or name it)");
    const auto shipped = fettle::config::load_cell(a_.config);
    if (shipped.cell.recipes.empty()) throw fettle::UserError(a_.config.string() + ": [[cell.recipes]] is empty");
    // The recipe in the soak's own directory with its golden template. When that directory has
    // no planner's grid yet, it is copied from --planning-cache or from next to the shipped
    // recipe, whichever has one (fettled rejects a stale one with a warning and rebuilds it).
    const fs::path shipped_part = shipped.cell.recipes.front().file;
    const fs::path part = a_.out / "parts" / shipped_part.filename();
    fs::copy_file(shipped_part, part, fs::copy_options::overwrite_existing);
    const fs::path cache = fettle::process::planning_cache_dir(part);
    for (const fs::path& from : {a_.planning_cache, fettle::process::planning_cache_dir(shipped_part)}) {
      if (fs::exists(fettle::process::sdf_grid_file(cache))) break;
      if (from.empty() || !fs::exists(fettle::process::sdf_grid_file(from))) continue;
      fs::remove_all(cache);
      fs::copy(from, cache, fs::copy_options::recursive);
      std::printf("soak: planner's grid copied from %s\n", from.c_str());
    }
    const int golden = run_program({fs::read_symlink("/proc/self/exe").string(), "golden", "--part", part.string()},
                                   a_.out / "golden.log");
    if (golden != 0)
      throw fettle::UserError("fettle-sim golden --part " + part.string() + " failed (" + describe(golden) +
                              "): " + read_text(a_.out / "golden.log"));

    fettle::sim::CellSimOptions o;
    o.cell = shipped;
    o.cell.robot.cell_id = "soak-cell";
    for (auto& r : o.cell.cell.recipes) r.file = part;
    o.plc_port = o.robot_port = o.spindle_port = 0;
    o.castings = 0;
    o.auto_start = false;
    o.robot_speedup = a_.speedup;
    o.grind = false;
    o.slide_speed_mm_s = 2000.0;
    std::tie(o.camera_width, o.camera_height) = fettle::sim::app::parse_resolution(a_.resolution);
    cell_ = std::make_unique<fettle::sim::CellSim>(o);
    cell_log_.open(a_.out / "cell.log");
    cell_->on_event([this](const std::string& line) { cell_log_ << line << "\n" << std::flush; });
    cell_->start();
    std::ofstream(a_.out / "cell.toml") << cell_toml(a_.out, shipped, part, cell_->plc_port(), cell_->robot_port(),
                                                     cell_->spindle_port(), a_.keep_cycles, a_.heartbeat_timeout_ms);
    fs::remove_all(a_.out / "state");
    journal_ = std::make_unique<JournalChecker>(a_.out / "state");
    spawn();
  }

  /// Runs a program to its end with stdout and stderr in `log`; its wait status.
  static int run_program(std::vector<std::string> args, const fs::path& log) {
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_addopen(&fa, 1, log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    posix_spawn_file_actions_adddup2(&fa, 1, 2);
    std::vector<char*> argv;
    for (auto& s : args) argv.push_back(s.data());
    argv.push_back(nullptr);
    pid_t pid = 0;
    const int rc = posix_spawn(&pid, argv[0], &fa, nullptr, argv.data(), environ);
    posix_spawn_file_actions_destroy(&fa);
    if (rc != 0) throw fettle::DeviceError("cannot start " + args[0] + ": " + std::strerror(rc));
    int status = 0;
    ::waitpid(pid, &status, 0);
    return status;
  }

  /// `fettle tool changed NAME` for the wheel a tool.worn fault names ("wheel 'flat-16' is worn").
  void change_wheel(const std::string& fault, CycleOutcome& o) {
    const auto at = fault.find("wheel '");
    const auto end = at == std::string::npos ? at : fault.find('\'', at + 7);
    if (end == std::string::npos) {
      o.problems.push_back("tool.worn names no wheel: " + fault);
      return;
    }
    const std::string name = fault.substr(at + 7, end - at - 7);
    const fs::path fettle = a_.fettled.parent_path() / "fettle";
    const int status = run_program({fettle.string(), "tool", "changed", name, "--socket", (a_.out / "fettled.sock").string()},
                                   a_.out / "tool-changed.log");
    if (!WIFEXITED(status) || WEXITSTATUS(status) != 0)
      o.problems.push_back("fettle tool changed " + name + " failed (" + (a_.out / "tool-changed.log").string() + ")");
    else
      std::fprintf(stderr, "soak: a new wheel '%s' (fettle tool changed)\n", name.c_str());
  }

  void spawn() {
    const std::string exe = a_.fettled.string();
    const std::string log = (a_.out / "fettled.log").string();
    const std::string config = (a_.out / "cell.toml").string();
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_addopen(&fa, 1, log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    posix_spawn_file_actions_adddup2(&fa, 1, 2);
    posix_spawn_file_actions_addclosefrom_np(&fa, 3);  // not the simulated cell's sockets
    std::vector<std::string> args{exe, "--config", config};
    if (::geteuid() == 0) args.emplace_back("--allow-root");
    std::vector<char*> argv;
    for (auto& s : args) argv.push_back(s.data());
    argv.push_back(nullptr);
    const int rc = posix_spawn(&pid_, exe.c_str(), &fa, nullptr, argv.data(), environ);
    posix_spawn_file_actions_destroy(&fa);
    if (rc != 0) throw fettle::DeviceError("cannot start " + exe + ": " + std::strerror(rc));
  }

  /// True while fettled runs; once it is gone, reaps it and keeps how it ended.
  bool alive() {
    if (pid_ <= 0) return false;
    int status = 0;
    const pid_t r = ::waitpid(pid_, &status, WNOHANG);
    if (r == 0) return true;
    if (r == pid_) {
      ended_how_ = describe(status);
      pid_ = 0;
    }
    return false;
  }

  static std::string describe(int status) {
    if (WIFEXITED(status)) return "exited with status " + std::to_string(WEXITSTATUS(status));
    if (WIFSIGNALED(status))
      return std::string("killed by signal ") + ::strsignal(WTERMSIG(status)) + (WCOREDUMP(status) ? " (core dumped)" : "");
    return "wait status " + std::to_string(status);
  }

  std::string tail_log() const {
    const auto text = read_text(a_.out / "fettled.log");
    return "\nfettled log (tail):\n" + text.substr(text.size() > 3000 ? text.size() - 3000 : 0);
  }

  State state() const { return cell_->plc().fettle.state; }

  /// fettled's state and fault as the PLC sees them, for messages.
  std::string where() const {
    const auto p = cell_->plc();
    std::string w = "it is in " + std::string(fettle::packml::name(p.fettle.state));
    if (p.fettle.fault_latched) w += " with fault " + std::to_string(p.fettle.fault_code) + " latched";
    if (p.parts_requested > p.cycles_accepted) w += ", a cycle request pending";
    return w;
  }

  bool reaches(State s, std::chrono::milliseconds timeout) {
    return wait_until([&] { return !alive() || (cell_->plc().fettle_written && state() == s); }, timeout) && alive();
  }

  /// Back to Execute with no cycle request left over. A request raised just before a fault
  /// stopped fettled accepting it stays pending at the PLC (as on a real PLC) and starts a cycle
  /// after the recovery: that cycle runs out first, so the next one's outcome is its own.
  bool recover() {
    for (int i = 0; i < 5; ++i) {
      if (!to_execute()) return false;
      const auto p = cell_->plc();
      if (p.parts_requested <= p.cycles_accepted) return true;
      const auto results = p.results.size();
      std::printf("           (a cycle request from before the fault is still pending: letting its cycle run)\n");
      wait_until([&] {
        const auto q = cell_->plc();
        return !alive() || q.results.size() > results || q.fettle.fault_latched;
      }, 300s);
      drain_journal();
    }
    return false;
  }

  /// Reset + Start from wherever the cell is into Execute, as a PLC program would.
  bool to_execute() {
    for (int i = 0; i < 10; ++i) {
      const auto snap = cell_->plc();
      const auto s = snap.fettle.state;
      if (s == State::execute && !snap.fettle.fault_latched) return true;
      if (s == State::aborted) (void)cell_->inject("plc clear");
      else if (s == State::stopped || s == State::complete) (void)cell_->inject("plc reset");
      else if (s == State::idle) (void)cell_->inject("plc start");
      else if (s == State::held) {
        (void)cell_->inject("plc reset");
        std::this_thread::sleep_for(200ms);
        (void)cell_->inject("plc unhold");
      } else if (s == State::execute) {
        (void)cell_->inject("plc reset");
      }
      wait_until([&] { return !alive() || state() != s || (s == State::execute && !cell_->plc().fettle.fault_latched); }, 20s);
    }
    const auto snap = cell_->plc();
    return snap.fettle.state == State::execute && !snap.fettle.fault_latched;
  }

  CycleOutcome one_cycle(int index, const FaultKind* kind) {
    using W = FaultKind::When;
    CycleOutcome o;
    o.index = index;
    o.seed = static_cast<std::uint64_t>(1 + (index - 1) % 50);
    const auto t0 = Clock::now();
    const auto before = cell_->plc().results.size();
    const int runs_before = cell_->robot_stats().runs_started;
    const int accepted_before = cell_->plc().cycles_accepted;
    const int ended_before = journal_->ended();
    const int uploads_before = journal_->uploads();
    if (kind != nullptr) {
      o.fault = kind->name;
      o.device = kind->device;
      o.expected_codes = kind->codes;
    }
    auto inject = [&] {
      for (const auto& line : kind->inject)
        if (auto st = cell_->inject(line); !st) o.problems.push_back("inject '" + line + "': " + st.error().message);
    };
    const bool starts_cycle = kind == nullptr || kind->when != W::no_cycle;
    if (starts_cycle) {
      if (kind != nullptr && kind->name == "wrong part") cell_->load_wrong(o.seed);
      else if (kind == nullptr || kind->name != "empty fixture") cell_->load(o.seed);
    }
    if (kind != nullptr && (kind->when == W::before_request || kind->when == W::no_cycle)) inject();
    if (starts_cycle) cell_->request();
    if (kind != nullptr && kind->when == W::slide_moving) {
      if (wait_until([&] {
            const auto p = cell_->plc();
            return (p.cycles_accepted > accepted_before && p.fettle.slide_target != 0) || p.fettle.fault_latched;
          }, 60s) && !cell_->plc().fettle.fault_latched)
        inject();
      else o.not_injected = "the cycle ended before the slide moved";
    }
    if (kind != nullptr && kind->when == W::robot_running) {
      // Only into a run: a fault before it (fettled refusing the casting, say) leaves nothing to inject into.
      if (wait_until([&] { return cell_->robot_stats().runs_started > runs_before || cell_->plc().fettle.fault_latched || !alive(); }, 180s) &&
          cell_->robot_stats().runs_started > runs_before)
        inject();
      else o.not_injected = "the cycle ended before the robot ran";
    }
    // A fault with no cycle (the PLC's registers) shows within seconds; a cycle takes ~5-30 s.
    const auto timeout = starts_cycle ? 300s : 30s;
    const bool ended = wait_until(
        [&] { return !alive() || cell_->plc().results.size() > before || cell_->plc().fettle.fault_latched; }, timeout);
    auto snap = cell_->plc();
    if (!ended) o.problems.push_back("no result and no fault within " + std::to_string(timeout.count()) + " s");
    if (snap.results.size() > before) o.plc_result = std::string(fettle::drivers::plc::name(snap.results.back()));
    if (snap.fettle.fault_latched) o.plc_fault_code = snap.fettle.fault_code;
    // fettled writes the record, then the journal's end line, then the result to the PLC; a fault
    // reaches the PLC first. Wait for this cycle's end line.
    const bool accepted = snap.cycles_accepted > accepted_before;  // else no cycle started (and none to end)
    const bool journal_ended = wait_until([&] {
      drain_journal();
      return !alive() || !accepted || (journal_->ended() > ended_before && journal_->open().empty());
    }, 30s);
    if (kind != nullptr) {
      for (const auto& line : kind->undo)
        if (auto st = cell_->inject(line); !st) o.problems.push_back("undo '" + line + "': " + st.error().message);
    }
    // A robot fault armed before the request acts only on an upload: a cycle that ended before
    // one (fettled refusing the casting, say) never reached it.
    if (kind != nullptr && kind->device == "robot" && kind->when == W::before_request && journal_->uploads() == uploads_before)
      o.not_injected = "the cycle ended before an upload (" +
                       (o.plc_fault_code ? "fault " + std::to_string(o.plc_fault_code) : "result " + o.plc_result) + ")";
    // A one-shot robot fault the cycle never reached must not fire in a later one.
    (void)cell_->inject("robot clear");
    // fettled asks for a new wheel (tool.worn) before a cycle that could wear one past its life
    // (docs/compensation.md, "Wheel wear"): the soak's operator fits it. A maintenance stop, not
    // a failure; a fault armed for that cycle never came to be injected.
    if (o.plc_fault_code == 404) {
      o.wheel_change = true;
      change_wheel(journal_->last_end().value("fault", std::string()), o);
      if (kind != nullptr && o.not_injected.empty()) o.not_injected = "fettled asked for a new wheel first (tool.worn)";
    }
    if (kind != nullptr && o.not_injected.empty()) {
      if (o.expected_codes.count(o.plc_fault_code) == 0)
        o.problems.push_back("expected fault " + codes_text(o.expected_codes) + " at the PLC, got " +
                             (o.plc_fault_code ? std::to_string(o.plc_fault_code) : "none") +
                             (o.plc_result.empty() ? "" : " (result " + o.plc_result + ")"));
    } else if (o.plc_fault_code != 0 && !o.wheel_change) {
      unexpected_faults_.push_back("cycle " + std::to_string(index) + " (casting " + std::to_string(o.seed) + "): fault " +
                                   std::to_string(o.plc_fault_code) + " " + journal_->last_end().value("fault", std::string()));
    }
    // 601 (a step outlived its timeout) and 603 (an internal error) are bugs whatever was injected.
    if (o.plc_fault_code == 601 || o.plc_fault_code == 603)
      o.problems.push_back("fault " + std::to_string(o.plc_fault_code) + ": " + journal_->last_end().value("fault", std::string()));
    if (starts_cycle && accepted) {
      if (!journal_ended) {
        o.problems.push_back("no journal end line for this cycle within 30 s of its " +
                             std::string(o.plc_fault_code ? "fault" : "result"));
      } else if (o.plc_fault_code != 0) {
        // The end line of a cycle that faulted carries the code the PLC got.
        const auto& end = journal_->last_end();
        if (end.value("fault_code", 0) != o.plc_fault_code)
          o.problems.push_back("cycle " + end.value("id", std::string("?")) + " ended in the journal with fault code " +
                               std::to_string(end.value("fault_code", 0)) + ", the PLC got " +
                               std::to_string(o.plc_fault_code));
      } else if (!o.plc_result.empty()) {
        // and that of a cycle that ended without a fault the result the PLC got (the record's
        // result is checked against the end line as the journal is read)
        const auto& end = journal_->last_end();
        if (end.value("result", std::string()) != o.plc_result)
          o.problems.push_back("cycle " + end.value("id", std::string("?")) + " ended in the journal with result " +
                               end.value("result", std::string("none")) + ", the PLC got " + o.plc_result);
      }
    }
    o.state = std::string(fettle::packml::name(state()));
    o.seconds = std::chrono::duration<double>(Clock::now() - t0).count();
    o.rss_kb = rss_kb(pid_);
    // What fettled said about it: a fault latched between two cycles is in the log before this
    // cycle began, so from where the previous cycle's outcome was taken.
    if (auto said = log_warnings_since_last(); !o.problems.empty() && !said.empty())
      o.problems.push_back("fettled's warnings and errors since the previous cycle:" + said);
    for (const auto& p : o.problems) problems_.push_back("cycle " + std::to_string(index) + ": " + p);
    return o;
  }

  /// fettled's warning and error lines logged since the last call (at most the last 20), each on
  /// its own indented line; "" if none.
  std::string log_warnings_since_last() {
    std::ifstream in(a_.out / "fettled.log", std::ios::binary);
    in.seekg(static_cast<std::streamoff>(log_offset_));
    std::deque<std::string> lines;
    for (std::string line; std::getline(in, line);) {
      if (in.eof()) break;  // a line still being written: read it whole next time
      log_offset_ += line.size() + 1;
      if (line.find(" warning [") == std::string::npos && line.find(" error [") == std::string::npos &&
          line.find(" critical [") == std::string::npos)
        continue;
      lines.push_back(std::move(line));
      if (lines.size() > 20) lines.pop_front();
    }
    std::string out;
    for (const auto& l : lines) out += "\n             " + l;
    return out;
  }

  void drain_journal() {
    for (auto& p : journal_->poll()) problems_.push_back(std::move(p));
  }

  [[nodiscard]] int warmup() const { return a_.warmup > 0 ? a_.warmup : std::max(5, a_.cycles / 10); }

  static std::string pct(double v) {
    char b[32];
    std::snprintf(b, sizeof b, "%.1f %%", v);
    return b;
  }

  static std::string codes_text(const std::set<int>& codes) {
    std::string s;
    for (int c : codes) s += (s.empty() ? "" : "/") + std::to_string(c);
    return s;
  }

  void print(const CycleOutcome& o) const {
    std::string what = o.fault.empty() ? "no fault" : o.fault;
    std::string got = o.plc_fault_code ? "fault " + std::to_string(o.plc_fault_code) : "result " + o.plc_result;
    std::printf("[%4d/%d] %6.1f s  casting %2llu  %-40s -> %-11s %-8s RSS %5.0f MB%s\n", o.index, a_.cycles, o.seconds,
                static_cast<unsigned long long>(o.seed), what.c_str(), got.c_str(), o.state.c_str(),
                static_cast<double>(o.rss_kb) / 1024.0, o.problems.empty() ? "" : "  PROBLEM");
    if (!o.not_injected.empty()) std::printf("           (not injected: %s)\n", o.not_injected.c_str());
    for (const auto& p : o.problems) std::printf("           %s\n", p.c_str());
    std::fflush(stdout);
  }

  int finish(const std::string& fatal) {
    if (!fatal.empty()) problems_.push_back(fatal);
    // No crash, no restart: the process started at the beginning still runs (the soak never
    // restarts it; systemd is not here to), and it stops cleanly.
    const bool ran_throughout = alive();
    if (!ran_throughout) problems_.push_back("fettled stopped during the soak (" + ended_how_ + ")" + tail_log());
    // Every cycle it started has ended while it ran (a SIGTERM would end an open one as 602).
    wait_until([&] {
      drain_journal();
      return journal_->open().empty();
    }, 30s);
    for (const auto& id : journal_->open())
      problems_.push_back("cycle " + id + " started and had not ended in the journal 30 s after the soak's last cycle");
    if (ran_throughout) {
      ::kill(pid_, SIGTERM);
      if (wait_until([&] { return !alive(); }, 60s)) {
        if (ended_how_ != "exited with status 0")
          problems_.push_back("fettled on SIGTERM: " + ended_how_ + " (expected exit status 0)");
      } else {
        problems_.push_back("fettled did not exit within 60 s of SIGTERM");
      }
    }
    drain_journal();
    const auto robot = cell_->robot_stats();
    if (robot.limit_naks > 0)
      problems_.push_back("the simulated robot refused " + std::to_string(robot.limit_naks) +
                          " point(s) outside its limits: a trajectory passed fettled without validation");
    // Every trajectory the robot received was uploaded by a cycle whose record shows the
    // validate step before the upload (JournalChecker); some uploads fail on purpose.
    if (robot.trajectories_received > journal_->uploads())
      problems_.push_back("the robot received " + std::to_string(robot.trajectories_received) +
                          " trajectories, the records show only " + std::to_string(journal_->uploads()) +
                          " validated uploads");
    // Cycles without an injected fault should mostly end OK or NOK.
    int clean = 0, clean_ok = 0;
    for (const auto& o : outcomes_) {
      if ((!o.fault.empty() && o.not_injected.empty()) || o.wheel_change) continue;
      ++clean;
      if (o.plc_result == "OK" || o.plc_result == "NOK") ++clean_ok;
    }
    if (clean > 0 && 100.0 * clean_ok < a_.min_ok_pct * clean)
      problems_.push_back("only " + std::to_string(clean_ok) + " of " + std::to_string(clean) +
                          " cycles without an injected fault ended OK or NOK (--min-ok-pct " + pct(a_.min_ok_pct) + ")");
    // Memory: the largest RSS in the warm-up against the largest in the last tenth.
    const int warm = warmup();
    long warm_kb = 0, end_kb = 0;
    const auto n = static_cast<int>(outcomes_.size());
    for (const auto& o : outcomes_) {
      if (o.index <= warm) warm_kb = std::max(warm_kb, o.rss_kb);
      if (o.index > n - std::max(1, n / 10)) end_kb = std::max(end_kb, o.rss_kb);
    }
    double growth_pct = 0.0;
    if (n > warm && warm_kb > 0) {
      growth_pct = 100.0 * (static_cast<double>(end_kb) / static_cast<double>(warm_kb) - 1.0);
      if (a_.max_rss_growth_pct > 0.0 && growth_pct >= a_.max_rss_growth_pct)
        problems_.push_back("fettled's RSS grew " + pct(growth_pct) + " after the warm-up (" +
                            std::to_string(warm_kb / 1024) + " -> " + std::to_string(end_kb / 1024) + " MB)");
    } else if (fatal.empty()) {
      problems_.push_back("too few cycles after the warm-up (" + std::to_string(warm) + ") to judge memory");
    }
    // The soak must have tested what it claims: every device drawn 10 times or more had a fault
    // injected and reported; and few drawn faults found nothing to act on.
    std::map<std::string, int> by_fault, by_result, reached_by_device, drawn_by_device;
    for (const auto& k : fault_kinds()) reached_by_device[k.device], drawn_by_device[k.device];
    int drawn = 0, not_injected = 0, faults_injected = 0, faults_reported = 0;
    for (const auto& o : outcomes_) {
      ++by_result[o.plc_fault_code ? "fault " + std::to_string(o.plc_fault_code) : "result " + o.plc_result];
      if (o.fault.empty()) continue;
      ++drawn;
      ++drawn_by_device[o.device];
      if (!o.not_injected.empty()) {
        ++not_injected;
        continue;
      }
      ++faults_injected;
      ++by_fault[o.device + ": " + o.fault];
      if (o.expected_codes.count(o.plc_fault_code) != 0) ++faults_reported, ++reached_by_device[o.device];
    }
    for (const auto& [device, reached] : reached_by_device)
      if (drawn_by_device[device] >= 10 && reached == 0)
        problems_.push_back("none of the " + std::to_string(drawn_by_device[device]) + " " + device +
                            " faults drawn was injected and reported: the soak did not test that device");
    if (drawn >= 20 && 100.0 * not_injected > kMaxNotInjectedPct * drawn)
      problems_.push_back(std::to_string(not_injected) + " of " + std::to_string(drawn) +
                          " drawn faults were not injected (their cycle ended before the moment to inject; at most " +
                          pct(kMaxNotInjectedPct) + " may be): the soak tested less than it reports");
    json j;
    j["cycles"] = n;
    j["faults_drawn"] = drawn;
    j["faults_not_injected"] = not_injected;
    j["faults_reported_by_device"] = reached_by_device;
    j["fault_rate"] = a_.fault_rate;
    j["seed"] = a_.seed;
    j["resolution"] = a_.resolution;
    j["robot_speedup"] = a_.speedup;
    j["faults_injected"] = faults_injected;
    j["faults_reported_with_their_code"] = faults_reported;
    j["faults_by_kind"] = by_fault;
    j["outcomes"] = by_result;
    j["unexpected_faults"] = unexpected_faults_;
    j["journal"] = {{"started", journal_->started()}, {"ended", journal_->ended()},
                    {"records_checked", journal_->records_checked()}, {"uploads_after_validation", journal_->uploads()}};
    j["robot"] = {{"trajectories_received", robot.trajectories_received},
                  {"trajectories_executed", robot.trajectories_executed},
                  {"trajectories_halted", robot.trajectories_halted},
                  {"limit_naks", robot.limit_naks}};
    j["rss_mb"] = {{"warmup_cycles", warm}, {"warmup_max", static_cast<double>(warm_kb) / 1024.0},
                   {"last_tenth_max", static_cast<double>(end_kb) / 1024.0}, {"growth_pct", growth_pct},
                   {"limit_pct", a_.max_rss_growth_pct}, {"checked", a_.max_rss_growth_pct > 0.0}};
    j["fettled"] = {{"ran_throughout", ran_throughout}, {"ended", ended_how_}};
    j["problems"] = problems_;
    json per = json::array();
    for (const auto& o : outcomes_)
      per.push_back({{"cycle", o.index}, {"seed", o.seed}, {"fault", o.fault}, {"not_injected", o.not_injected},
                     {"plc_fault_code", o.plc_fault_code},
                     {"result", o.plc_result}, {"state", o.state}, {"seconds", o.seconds}, {"rss_kb", o.rss_kb}});
    j["per_cycle"] = per;
    if (auto st = fettle::write_file_atomic(a_.out / "soak.json", j.dump(1) + "\n"); !st)
      problems_.push_back("writing " + (a_.out / "soak.json").string() + ": " + st.error().message);
    cell_->stop();

    // summary.md: the run as docs/results.md's soak section (`make soak` puts it there with
    // scripts/update-results, pass or fail), so the figures there are the ones a run measured.
    {
      std::ostringstream m;
      char buf[1024];
      m << "## Soak: `make soak` (`fettle-sim soak`)\n\n";
      std::snprintf(buf, sizeof buf,
                    "%s, %d cycles in %.1f min, a random device fault in %.0f %% of them (seed %llu), camera %s, "
                    "robot x%.0f. Result: **%s**.\n\n",
                    started_utc_.c_str(), n, minutes_, 100.0 * a_.fault_rate, static_cast<unsigned long long>(a_.seed),
                    a_.resolution.c_str(), a_.speedup, problems_.empty() ? "PASSED" : "FAILED");
      m << buf << "| check | result |\n| --- | --- |\n";
      m << "| fettled ran throughout, exit status on SIGTERM | " << (ran_throughout ? "yes" : "no") << ", " << ended_how_
        << " |\n";
      m << "| cycles started / ended with a complete record | " << journal_->started() << " / "
        << journal_->records_checked() << " |\n";
      std::ostringstream devices;
      for (const auto& [device, reached] : reached_by_device)
        devices << (devices.tellp() > 0 ? ", " : "") << device << " " << reached;
      m << "| injected faults reported at the PLC with their code | " << faults_reported << " of " << faults_injected
        << " (" << devices.str() << "); " << not_injected << " of " << drawn
        << " drawn were not injected, their cycle having ended first |\n";
      m << "| uploads after a validate step / points the robot refused | " << journal_->uploads() << " / "
        << robot.limit_naks << " |\n";
      std::snprintf(buf, sizeof buf, "| RSS, warm-up max -> last tenth max | %.0f -> %.0f MB (%+.1f %%, %s) |\n",
                    static_cast<double>(warm_kb) / 1024.0, static_cast<double>(end_kb) / 1024.0, growth_pct,
                    a_.max_rss_growth_pct > 0.0 ? ("limit " + pct(a_.max_rss_growth_pct)).c_str() : "not checked");
      m << buf;
      std::ostringstream outcomes;
      for (const auto& [k, v] : by_result) outcomes << (outcomes.tellp() > 0 ? ", " : "") << k << " x" << v;
      m << "| outcomes | " << outcomes.str() << " |\n";
      if (!problems_.empty()) {
        m << "\nProblems:\n\n";
        for (const auto& p : problems_) m << "- " << p << "\n";
      }
      if (auto st = fettle::write_file_atomic(a_.out / "summary.md", m.str()); !st)
        problems_.push_back("writing " + (a_.out / "summary.md").string() + ": " + st.error().message);
    }

    std::printf("\n== soak summary (%s) ==\n", (a_.out / "soak.json").c_str());
    std::printf("cycles %d; faults drawn %d, injected %d (%d not: their cycle ended first), reported at the PLC with their code %d\n",
                n, drawn, faults_injected, not_injected, faults_reported);
    for (const auto& [device, reached] : reached_by_device) std::printf("  device   %-50s %d reported\n", device.c_str(), reached);
    for (const auto& [k, v] : by_fault) std::printf("  injected %-50s %d\n", k.c_str(), v);
    for (const auto& [k, v] : by_result) std::printf("  outcome  %-50s %d\n", k.c_str(), v);
    std::printf("journal: %d started, %d ended, %d records checked complete, %d uploads each after validation\n",
                journal_->started(), journal_->ended(), journal_->records_checked(), journal_->uploads());
    std::printf("robot: %d trajectories received, %d executed, %d halted, %d points refused for its limits\n",
                robot.trajectories_received, robot.trajectories_executed, robot.trajectories_halted, robot.limit_naks);
    const std::string limit = a_.max_rss_growth_pct > 0.0 ? "limit " + pct(a_.max_rss_growth_pct)
                                                          : "not checked: --max-rss-growth-pct 0";
    std::printf("fettled RSS: %.0f MB at most in the warm-up (%d cycles), %.0f MB at most in the last tenth: %+.1f %% (%s)\n",
                static_cast<double>(warm_kb) / 1024.0, warm, static_cast<double>(end_kb) / 1024.0, growth_pct,
                limit.c_str());
    std::printf("fettled: %s; on SIGTERM %s\n", ran_throughout ? "ran throughout" : "STOPPED during the soak",
                ended_how_.c_str());
    if (!unexpected_faults_.empty()) {
      std::printf("faults in cycles without an injected fault (fettled's own refusals, see its log; not a check):\n");
      for (const auto& f : unexpected_faults_) std::printf("  %s\n", f.c_str());
    }
    if (problems_.empty()) {
      std::printf("soak: PASSED\n");
      return fettle::exit_code::ok;
    }
    std::printf("soak: FAILED (%zu problems)\n", problems_.size());
    for (const auto& p : problems_) std::printf("  - %s\n", p.c_str());
    return fettle::exit_code::failure;
  }

  Args a_;
  std::mt19937_64 rng_;
  std::ofstream cell_log_;  // before cell_: the cell's threads write to it until cell_ stops
  std::unique_ptr<fettle::sim::CellSim> cell_;
  std::unique_ptr<JournalChecker> journal_;
  pid_t pid_ = 0;
  std::string ended_how_;  ///< how fettled ended, once it has
  std::vector<CycleOutcome> outcomes_;
  std::vector<std::string> problems_, unexpected_faults_;
  std::size_t log_offset_ = 0;  ///< how far log_warnings_since_last read fettled.log
  std::string started_utc_;     ///< when the cycles began, for summary.md
  double minutes_ = 0.0;        ///< how long they took
};

FETTLE_COMMAND("soak", [](CLI::App& app, const fettle::cli::Common& common) {
  auto a = std::make_shared<Args>();
  auto* cmd = app.add_subcommand(
      "soak", "Drive fettled through many cycles on the simulated cell with random device faults; check records, "
              "fault codes, validation and memory");
  cmd->add_option("--config", a->config, "Cell file the simulated cell follows (slide, calibration, safety, recipe)")
      ->capture_default_str()
      ->check(CLI::ExistingFile);
  cmd->add_option("--out", a->out, "Directory for fettled's cell file, records, logs and soak.json")->required();
  cmd->add_option("--fettled", a->fettled, "fettled program (default: next to fettle-sim)");
  cmd->add_option("--cycles", a->cycles, "Cycles to run")->capture_default_str()->check(CLI::Range(1, 100000));
  cmd->add_option("--fault-rate", a->fault_rate, "Share of cycles with an injected fault")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 1.0));
  cmd->add_option("--seed", a->seed, "Seed of the fault sequence")->capture_default_str();
  cmd->add_option("--resolution", a->resolution, "Camera range map WIDTHxHEIGHT")->capture_default_str();
  cmd->add_option("--speedup", a->speedup, "Robot execution speed-up (1 = real time)")
      ->capture_default_str()
      ->check(CLI::Range(1.0, 1000.0));
  cmd->add_option("--warmup", a->warmup, "Cycles before the memory baseline (0 = max(5, cycles/10))")->capture_default_str();
  cmd->add_option("--max-rss-growth-pct", a->max_rss_growth_pct,
                  "Allowed RSS growth after the warm-up (%); 0 = not checked (fettled under AddressSanitizer, whose "
                  "quarantine keeps freed memory: LeakSanitizer checks for leaks at its exit instead)")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 1000.0));
  cmd->add_option("--min-ok-pct", a->min_ok_pct, "Share of cycles without an injected fault that must end OK or NOK (%)")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 100.0));
  cmd->add_option("--planning-cache", a->planning_cache,
                  "Planning cache directory (with sdf-grid.bin) to start from when --out has none yet "
                  "(default: the one next to the shipped recipe, if any)");
  cmd->add_option("--heartbeat-timeout-ms", a->heartbeat_timeout_ms,
                  "fettled's [plc] and [spindle] heartbeat_timeout_ms, and [robot] missed_pings (of 500 ms) to match "
                  "(at least 3): how long a link may be silent before it faults (longer under a sanitizer)")
      ->capture_default_str()
      ->check(CLI::Range(100, 60000));
  cmd->add_option("--keep-cycles", a->keep_cycles, "[records] keep_cycles for fettled (records are ~10 MB each)")
      ->capture_default_str()
      ->check(CLI::Range(5, 100000));
  return std::vector<std::pair<CLI::App*, fettle::cli::Command::Runner>>{{cmd, [a, &common] {
    // The simulated devices' events go to DIR/cell.log, fettled's log to DIR/fettled.log; the
    // terminal gets one line per cycle and errors (--log-level info shows everything).
    if (!common.log_level) {
      fettle::log::Options lo;
      lo.program = "fettle-sim";
      lo.default_level = "error";  // the injected faults' own warnings would drown the cycle lines
      fettle::log::init(lo);
    }
    return Soak(*a).run();
  }}};
});

}  // namespace
