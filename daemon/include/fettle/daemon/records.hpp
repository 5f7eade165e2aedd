#pragma once
// Cycle records under [cell] state_dir (docs/daemon.md, "Records"):
//
//   <state_dir>/journal.jsonl          append-only, one JSON object per line, fsync'd:
//                                      {"event":"start",...} when a cycle begins,
//                                      {"event":"end",...} when it ends (result, fault, timings),
//                                      {"event":"interrupted",...} written at the next start-up
//                                      for a cycle that began and never ended (crash, power loss)
//   <state_dir>/cycles/<cycle id>/     one directory per cycle: captures, fused cloud, per-region
//                                      deviations, trajectory, report.json, preview.png; every file
//                                      written atomically (temp + fsync + rename)
//
// Retention ([records] keep_cycles, keep_mb) deletes the oldest cycle directories after each
// cycle; the journal keeps its lines. A full disk never stops a cycle: before each cycle the
// oldest records are deleted until [records] min_free_mb is free; what still cannot be written
// is a warning (warning()), and journal lines that could not be appended are kept in memory and
// appended, in order, as soon as there is room again. Not thread-safe: use from the daemon's
// event loop, except write_file() which only touches the cycle's own directory and may run on
// a worker.
#include <cstdint>
#include <deque>
#include <filesystem>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "fettle/config/cell.hpp"
#include "fettle/core/result.hpp"

namespace fettle::daemon {

/// One cycle as the journal knows it.
struct CycleSummary {
  std::string id;            ///< e.g. "20261130-091502-0007"
  std::string started;       ///< UTC, ISO 8601
  std::string ended;         ///< empty while running / when interrupted
  std::string result;        ///< "running", "OK", "NOK", "FAULT", "INTERRUPTED", "ABORTED"
  int recipe_id = 0;
  std::string part_id;
  bool dry = false;          ///< a dry cycle (no grinding)
  double duration_s = 0.0;
  int fault_code = 0;        ///< 0 = none
  std::string fault;         ///< Fault::describe()
  std::filesystem::path dir; ///< the cycle's record directory
  bool record_deleted = false;  ///< removed by retention
  /// The verification's worst gouge (mm; 0 when none is deeper than gouge_depth_mm; none for a
  /// cycle without a verification scan), `gouge` says where; and the deepest confirmed place
  /// below the template wherever the tool went, gouge or not (a trend to watch: a calibration
  /// drifting toward the part shows there before it gouges).
  std::optional<double> worst_gouge_mm;
  std::string gouge;
  std::optional<double> deepest_below_template_mm;

  [[nodiscard]] nlohmann::json to_json() const;
  static CycleSummary from_json(const nlohmann::json& j);
};

class Records {
 public:
  Records(std::filesystem::path state_dir, config::RecordsSection retention);

  /// Creates the state directory if needed, reads the journal and appends an "interrupted"
  /// line for every cycle that started and never ended. Returns those cycles' ids.
  Result<std::vector<std::string>> open();

  /// Starts a cycle: a new id, its directory, a "start" line in the journal. Makes room first
  /// (min_free_mb). A full disk is not an error here: the cycle goes on, warning() says what
  /// could not be recorded. Other failures (permissions) are errors.
  Result<CycleSummary> begin(int recipe_id, const std::string& part_id, bool dry);
  /// Writes one file of the cycle atomically (thread-safe for distinct names).
  static Status write_file(const CycleSummary& cycle, std::string_view name, std::string_view data);
  /// Ends a cycle: an "end" line with `extra` fields merged in, then retention.
  Status end(CycleSummary cycle, const nlohmann::json& extra = {});

  /// Newest first.
  [[nodiscard]] std::vector<CycleSummary> cycles(std::size_t limit) const;
  [[nodiscard]] std::optional<CycleSummary> last() const;
  [[nodiscard]] std::size_t count() const { return cycles_.size(); }
  [[nodiscard]] const std::filesystem::path& state_dir() const { return dir_; }
  [[nodiscard]] std::filesystem::path cycles_dir() const { return dir_ / "cycles"; }
  [[nodiscard]] std::filesystem::path journal_path() const { return dir_ / "journal.jsonl"; }

  /// Deletes the oldest cycle directories beyond the limits (never `keep_id`). Returns how many.
  std::size_t apply_retention(const std::string& keep_id = {});

  /// Bytes available to this process on the state directory's file system (nullopt if unknown).
  [[nodiscard]] std::optional<std::uintmax_t> free_bytes() const;
  /// The last disk-space warning (empty while records are written normally).
  [[nodiscard]] const std::string& warning() const { return warning_; }
  /// Journal lines waiting for room on the disk.
  [[nodiscard]] std::size_t pending_lines() const { return pending_.size(); }

 private:
  Status append(const nlohmann::json& line);
  Status append_now(const std::string& text);
  [[nodiscard]] bool space_short() const;
  std::filesystem::path dir_;
  config::RecordsSection retention_;
  std::vector<CycleSummary> cycles_;  ///< journal order (oldest first)
  std::uint64_t sequence_ = 0;
  std::string warning_;
  std::deque<std::string> pending_;  ///< journal lines not yet on disk (disk full), oldest first
};

/// UTC now as ISO 8601 with milliseconds, "YYYY-MM-DDThh:mm:ss.mmmZ".
std::string utc_now_iso();

}  // namespace fettle::daemon
