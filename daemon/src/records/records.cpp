// Cycle records and the append-only journal (records.hpp).
#include "fettle/daemon/records.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <ctime>
#include <fstream>
#include <map>
#include <system_error>

#include "fettle/core/atomic_file.hpp"
#include "fettle/core/log.hpp"

namespace fettle::daemon {

namespace fs = std::filesystem;
using nlohmann::json;

std::string utc_now_iso() {
  const auto now = std::chrono::system_clock::now();
  const auto t = std::chrono::system_clock::to_time_t(now);
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()).count() % 1000;
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[40];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%S", &tm);
  char out[48];
  std::snprintf(out, sizeof out, "%s.%03dZ", buf, static_cast<int>(ms));
  return out;
}

json CycleSummary::to_json() const {
  json j{{"id", id},         {"started", started},     {"ended", ended}, {"result", result},
         {"recipe_id", recipe_id}, {"part_id", part_id}, {"dry", dry},     {"duration_s", duration_s},
         {"fault_code", fault_code}, {"fault", fault},  {"dir", dir.string()}};
  if (record_deleted) j["record_deleted"] = true;
  if (worst_gouge_mm) j["worst_gouge_mm"] = *worst_gouge_mm;
  if (!gouge.empty()) j["gouge"] = gouge;
  if (deepest_below_template_mm) j["deepest_below_template_mm"] = *deepest_below_template_mm;
  return j;
}

CycleSummary CycleSummary::from_json(const json& j) {
  CycleSummary s;
  s.id = j.value("id", "");
  s.started = j.value("started", "");
  s.ended = j.value("ended", "");
  s.result = j.value("result", "");
  s.recipe_id = j.value("recipe_id", 0);
  s.part_id = j.value("part_id", "");
  s.dry = j.value("dry", false);
  s.duration_s = j.value("duration_s", 0.0);
  s.fault_code = j.value("fault_code", 0);
  s.fault = j.value("fault", "");
  s.dir = j.value("dir", "");
  s.record_deleted = j.value("record_deleted", false);
  if (j.contains("worst_gouge_mm") && j["worst_gouge_mm"].is_number()) s.worst_gouge_mm = j["worst_gouge_mm"].get<double>();
  s.gouge = j.value("gouge", "");
  if (j.contains("deepest_below_template_mm") && j["deepest_below_template_mm"].is_number())
    s.deepest_below_template_mm = j["deepest_below_template_mm"].get<double>();
  return s;
}

Records::Records(fs::path state_dir, config::RecordsSection retention)
    : dir_(std::move(state_dir)), retention_(retention) {}

namespace {
bool disk_full(int e) { return e == ENOSPC || e == EDQUOT || e == EFBIG; }
double mib(std::uintmax_t bytes) { return static_cast<double>(bytes) / (1024.0 * 1024.0); }
}  // namespace

Status Records::append_now(const std::string& text) {
  const auto path = journal_path();
  const int fd = ::open(path.c_str(), O_WRONLY | O_APPEND | O_CREAT | O_CLOEXEC, 0640);
  if (fd < 0) {
    const int e = errno;
    return Error{disk_full(e) ? "records.disk_full" : "records.journal",
                 "cannot open the cycle journal " + path.string() + ": " + std::strerror(e) +
                     (disk_full(e) ? "" : " (check [cell] state_dir and its permissions)")};
  }
  struct stat before {};
  const bool sized = ::fstat(fd, &before) == 0;
  std::size_t done = 0;
  while (done < text.size()) {
    const auto n = ::write(fd, text.data() + done, text.size() - done);
    if (n < 0) {
      if (errno == EINTR) continue;
      const int e = errno;
      // No torn line in the middle of the journal: cut what this write added.
      if (done > 0 && sized) (void)::ftruncate(fd, before.st_size);
      ::close(fd);
      return Error{disk_full(e) ? "records.disk_full" : "records.journal",
                   "cannot append to " + path.string() + ": " + std::strerror(e)};
    }
    done += static_cast<std::size_t>(n);
  }
  const int rc = ::fsync(fd);
  const int e = errno;
  ::close(fd);
  if (rc != 0) return Error{"records.journal", "fsync of " + path.string() + " failed: " + std::strerror(e)};
  return {};
}

Status Records::append(const json& line) {
  pending_.push_back(line.dump() + "\n");
  // Lines that waited for room first, in their order; the rest stays pending.
  while (!pending_.empty()) {
    if (auto st = append_now(pending_.front()); !st) {
      if (pending_.size() > 100000) {  // a disk full for days: keep the newest, say so
        pending_.pop_front();
        log::get("records")->error("journal: dropped the oldest line waiting for disk space (100000 waiting)");
      }
      return Error{st.error().code, st.error().message + " (" + std::to_string(pending_.size()) +
                                        " journal line(s) kept in memory until there is room)"};
    }
    pending_.pop_front();
  }
  return {};
}

std::optional<std::uintmax_t> Records::free_bytes() const {
  std::error_code ec;
  const auto info = fs::space(dir_, ec);
  if (ec) return std::nullopt;
  return info.available;
}

bool Records::space_short() const {
  if (retention_.min_free_mb <= 0.0) return false;
  const auto free = free_bytes();
  return free && mib(*free) < retention_.min_free_mb;
}

Result<std::vector<std::string>> Records::open() {
  std::error_code ec;
  fs::create_directories(cycles_dir(), ec);
  if (ec)
    return Error{"records.state_dir", "cannot create " + cycles_dir().string() + ": " + ec.message() +
                                          " (check [cell] state_dir and its permissions)"};
  cycles_.clear();
  std::map<std::string, std::size_t> index;
  std::ifstream in(journal_path());
  std::string line;
  int line_no = 0;
  auto log = log::get("records");
  while (std::getline(in, line)) {
    ++line_no;
    if (line.empty()) continue;
    json j = json::parse(line, nullptr, false);
    if (j.is_discarded() || !j.is_object()) {
      // A torn last line (power loss during append): keep going, it is the one interrupted.
      log->warn("{}:{}: unreadable journal line skipped", journal_path().string(), line_no);
      continue;
    }
    const std::string event = j.value("event", "");
    auto s = CycleSummary::from_json(j);
    if (event == "start") {
      index[s.id] = cycles_.size();
      s.result = "running";
      cycles_.push_back(s);
    } else if (auto it = index.find(s.id); it != index.end()) {
      auto& c = cycles_[it->second];
      if (event == "end") {
        c = s;
      } else if (event == "interrupted") {
        c.result = "INTERRUPTED";
      } else if (event == "deleted") {
        c.record_deleted = true;
      }
    }
    sequence_ = std::max<std::uint64_t>(sequence_, j.value("seq", 0ULL));
  }
  // A torn last line (no newline: power lost during an append) is terminated, so the next
  // line appended does not merge with it.
  if (std::ifstream tail(journal_path(), std::ios::binary | std::ios::ate); tail && tail.tellg() > 0) {
    tail.seekg(-1, std::ios::end);
    char last = '\n';
    tail.get(last);
    if (last != '\n') {
      const int fd = ::open(journal_path().c_str(), O_WRONLY | O_APPEND | O_CLOEXEC);
      if (fd >= 0) {
        if (::write(fd, "\n", 1) != 1) log->warn("{}: cannot terminate the torn last line", journal_path().string());
        (void)::fsync(fd);
        ::close(fd);
      }
    }
  }
  std::vector<std::string> interrupted;
  for (auto& c : cycles_) {
    if (c.result != "running") continue;
    c.result = "INTERRUPTED";
    interrupted.push_back(c.id);
    if (auto st = append(json{{"event", "interrupted"}, {"id", c.id}, {"at", utc_now_iso()}}); !st) return st.error();
    log->warn("cycle {} was interrupted (started {}, never ended): marked INTERRUPTED", c.id, c.started);
    // Its folder gets a report.json too, so that every cycle folder has one: what is known of it
    // (docs/daemon.md "Records"; test Records.ACycleWithoutEndShowsAsInterruptedAfterRestart).
    if (const fs::path dir = cycles_dir() / c.id; fs::is_directory(dir, ec) && !fs::exists(dir / "report.json", ec)) {
      const json report{{"id", c.id},
                        {"result", "INTERRUPTED"},
                        {"started", c.started},
                        {"interrupted_found", utc_now_iso()},
                        {"message", "fettled stopped during this cycle (killed, crashed or power lost); the files "
                                    "here are what it had written by then, the part's state is unknown"}};
      if (auto st = write_file_atomic(dir / "report.json", report.dump(2) + "\n"); !st)
        log->warn("cycle {}: {}", c.id, st.error().message);
    }
  }
  return interrupted;
}

Result<CycleSummary> Records::begin(int recipe_id, const std::string& part_id, bool dry) {
  ++sequence_;
  const auto now = std::chrono::system_clock::to_time_t(std::chrono::system_clock::now());
  std::tm tm{};
  gmtime_r(&now, &tm);
  char stamp[32];
  std::strftime(stamp, sizeof stamp, "%Y%m%d-%H%M%S", &tm);
  char id[64];
  std::snprintf(id, sizeof id, "%s-%04llu", stamp, static_cast<unsigned long long>(sequence_ % 10000));
  CycleSummary s;
  s.id = id;
  s.started = utc_now_iso();
  s.result = "running";
  s.recipe_id = recipe_id;
  s.part_id = part_id;
  s.dry = dry;
  s.dir = cycles_dir() / s.id;
  auto log = log::get("records");
  // Room first: the oldest records go until min_free_mb is free (or none is left to delete).
  warning_.clear();
  if (space_short()) {
    const auto before = free_bytes().value_or(0);
    const auto removed = apply_retention();
    const auto after = free_bytes().value_or(0);
    log->warn("only {:.0f} MB free for records in {} ([records] min_free_mb {:.0f}): deleted the {} oldest cycle "
              "record(s), {:.0f} MB free now",
              mib(before), dir_.string(), retention_.min_free_mb, removed, mib(after));
    if (space_short())
      warning_ = "only " + std::to_string(static_cast<long long>(mib(after))) + " MB free for records in " +
                 dir_.string() + " after deleting every older cycle record ([records] min_free_mb " +
                 std::to_string(static_cast<long long>(retention_.min_free_mb)) +
                 "): this cycle's record may be incomplete; free space on that file system";
  }
  std::error_code ec;
  fs::create_directories(s.dir, ec);
  if (ec) {
    if (!disk_full(ec.value())) return Error{"records.cycle_dir", "cannot create " + s.dir.string() + ": " + ec.message()};
    warning_ = "the disk of " + dir_.string() + " is full: cycle " + s.id +
               " goes on without its record directory; free space on that file system";
  }
  json line = s.to_json();
  line["event"] = "start";
  line["seq"] = sequence_;
  if (auto st = append(line); !st) {
    if (st.error().code != "records.disk_full") return st.error();
    if (warning_.empty()) warning_ = st.error().message;
  }
  if (!warning_.empty()) log->warn("cycle {}: {}", s.id, warning_);
  cycles_.push_back(s);
  return s;
}

Status Records::write_file(const CycleSummary& cycle, std::string_view name, std::string_view data) {
  return write_file_atomic(cycle.dir / std::string(name), data);
}

Status Records::end(CycleSummary cycle, const json& extra) {
  cycle.ended = utc_now_iso();
  json line = cycle.to_json();
  line["event"] = "end";
  if (extra.is_object())
    for (const auto& [k, v] : extra.items()) line[k] = v;
  auto st = append(line);
  for (auto it = cycles_.rbegin(); it != cycles_.rend(); ++it)
    if (it->id == cycle.id) {
      *it = cycle;
      break;
    }
  apply_retention(cycle.id);
  return st;
}

std::vector<CycleSummary> Records::cycles(std::size_t limit) const {
  std::vector<CycleSummary> out;
  for (auto it = cycles_.rbegin(); it != cycles_.rend() && out.size() < limit; ++it) out.push_back(*it);
  return out;
}

std::optional<CycleSummary> Records::last() const {
  for (auto it = cycles_.rbegin(); it != cycles_.rend(); ++it)
    if (it->result != "running") return *it;
  return std::nullopt;
}

namespace {
std::uintmax_t dir_size(const fs::path& p) {
  std::uintmax_t total = 0;
  std::error_code ec;
  for (fs::recursive_directory_iterator it(p, ec), end; !ec && it != end; it.increment(ec))
    if (it->is_regular_file(ec)) total += it->file_size(ec);
  return total;
}
}  // namespace

std::size_t Records::apply_retention(const std::string& keep_id) {
  std::error_code ec;
  std::vector<fs::path> dirs;
  for (fs::directory_iterator it(cycles_dir(), ec), end; !ec && it != end; it.increment(ec))
    if (it->is_directory(ec)) dirs.push_back(it->path());
  std::sort(dirs.begin(), dirs.end());  // ids sort by time
  std::vector<std::uintmax_t> sizes;
  std::uintmax_t total = 0;
  for (const auto& d : dirs) total += sizes.emplace_back(dir_size(d));
  const auto max_bytes = static_cast<std::uintmax_t>(std::max(0.0, retention_.keep_mb) * 1024.0 * 1024.0);
  const auto keep = static_cast<std::size_t>(std::max(1, retention_.keep_cycles));
  std::size_t removed = 0;
  auto log = log::get("records");
  for (std::size_t i = 0; i < dirs.size(); ++i) {
    const std::size_t left = dirs.size() - removed;
    if (left <= keep && total <= max_bytes && !space_short()) break;
    const auto name = dirs[i].filename().string();
    if (name == keep_id) continue;
    fs::remove_all(dirs[i], ec);
    if (ec) {
      log->warn("retention: cannot remove {}: {}", dirs[i].string(), ec.message());
      continue;
    }
    total -= sizes[i];
    ++removed;
    for (auto& c : cycles_)
      if (c.id == name) c.record_deleted = true;
    (void)append(json{{"event", "deleted"}, {"id", name}, {"at", utc_now_iso()}});
    log->info("retention: removed cycle record {} (keep_cycles {}, keep_mb {}, min_free_mb {})", name,
              retention_.keep_cycles, retention_.keep_mb, retention_.min_free_mb);
  }
  return removed;
}

}  // namespace fettle::daemon
