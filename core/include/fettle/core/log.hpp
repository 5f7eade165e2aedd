#pragma once
// Logging for all Fettle programs (spdlog).
//
// Under systemd (JOURNAL_STREAM or INVOCATION_ID in the environment) records go to
// journald with their priority and structured fields (FETTLE_COMPONENT, and the
// thread's context such as FETTLE_CYCLE_ID, FETTLE_STATE, FETTLE_DEVICE);
// otherwise human-readable lines go to stderr.
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <spdlog/logger.h>

namespace fettle::log {

enum class Target { automatic, journal, stderr_text };

struct Options {
  std::string program = "fettle";                       ///< SYSLOG_IDENTIFIER in the journal
  std::string default_level = "info";                  ///< trace|debug|info|warn|error|critical|off
  std::map<std::string, std::string> component_levels;  ///< e.g. {"plc": "debug"}
  std::optional<std::string> override_level;           ///< --log-level: wins over everything
  Target target = Target::automatic;
  /// Similar lines (the same logger, level and text with its numbers left out) beyond
  /// `burst_lines` within `rate_window_ms` are not written; the next similar line after the
  /// window says how many were suppressed. A device that floods (a robot sending FAULT lines
  /// as fast as it can) cannot fill the disk or make journald drop real messages
  /// (docs/security.md "Limits"; test Log.SimilarLinesBeyondTheBurstAreCountedNotWritten).
  /// 0 burst_lines: no limit.
  int burst_lines = 20;
  int rate_window_ms = 5000;
};

/// The rate limit of Options::burst_lines around `inner` (init() puts it round every sink).
spdlog::sink_ptr rate_limited(spdlog::sink_ptr inner, int burst_lines, int window_ms);

/// The level names accepted in configs and on the command line.
const std::vector<std::string>& level_names();
/// True if `name` is one of level_names().
bool is_level_name(std::string_view name);

/// Where records go for the given environment (automatic → journal under systemd).
Target resolve_target(Target requested, const char* journal_stream, const char* invocation_id);

/// Sets up logging; throws std::invalid_argument naming a bad level. May be called again.
void init(const Options& options);

/// The logger of one component ("plc", "camera", "vision", ...), created on first use
/// with that component's configured level.
std::shared_ptr<spdlog::logger> get(std::string_view component);

/// Structured fields attached to every record this thread logs while the scope lives,
/// e.g. `log::Scope cycle{"CYCLE_ID", id};` → FETTLE_CYCLE_ID=… in the journal.
class Scope {
 public:
  Scope(std::string key, std::string value);
  ~Scope();
  Scope(const Scope&) = delete;
  Scope& operator=(const Scope&) = delete;

 private:
  std::string key_;
  std::optional<std::string> previous_;
};

/// The current thread's structured fields (for sinks and tests).
const std::map<std::string, std::string>& context();

}  // namespace fettle::log
