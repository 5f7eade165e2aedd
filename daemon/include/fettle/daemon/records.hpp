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
// cycle; the journal keeps its lines. Not thread-safe: use from the daemon's event loop, except
// write_file() which only touches the cycle's own directory and may run on a worker.
#include <cstdint>
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

  [[nodiscard]] nlohmann::json to_json() const;
  static CycleSummary from_json(const nlohmann::json& j);
};

class Records {
 public:
  Records(std::filesystem::path state_dir, config::RecordsSection retention);

  /// Creates the state directory if needed, reads the journal and appends an "interrupted"
  /// line for every cycle that started and never ended. Returns those cycles' ids.
  Result<std::vector<std::string>> open();

  /// Starts a cycle: a new id, its directory, a "start" line in the journal.
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

 private:
  Status append(const nlohmann::json& line);
  std::filesystem::path dir_;
  config::RecordsSection retention_;
  std::vector<CycleSummary> cycles_;  ///< journal order (oldest first)
  std::uint64_t sequence_ = 0;
};

/// UTC now as "2026-11-30T09:15:02.123Z".
std::string utc_now_iso();

}  // namespace fettle::daemon
