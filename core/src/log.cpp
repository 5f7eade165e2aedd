#include "fettle/core/log.hpp"

#include <sys/uio.h>
#include <systemd/sd-journal.h>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cstdlib>
#include <mutex>
#include <stdexcept>
#include <unordered_map>

#include <spdlog/sinks/base_sink.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

namespace fettle::log {
namespace {

thread_local std::map<std::string, std::string> t_context;

int journal_priority(spdlog::level::level_enum level) {
  switch (level) {
    case spdlog::level::trace:
    case spdlog::level::debug: return 7;  // LOG_DEBUG
    case spdlog::level::info: return 6;   // LOG_INFO
    case spdlog::level::warn: return 4;   // LOG_WARNING
    case spdlog::level::err: return 3;    // LOG_ERR
    case spdlog::level::critical: return 2;  // LOG_CRIT
    default: return 6;
  }
}

/// Sends each record to journald with its priority and structured fields.
class JournalSink final : public spdlog::sinks::base_sink<std::mutex> {
 public:
  explicit JournalSink(std::string identifier) : identifier_(std::move(identifier)) {}

 protected:
  void sink_it_(const spdlog::details::log_msg& msg) override {
    std::vector<std::string> fields;
    fields.reserve(6 + t_context.size());
    fields.push_back("MESSAGE=" + std::string(msg.payload.data(), msg.payload.size()));
    fields.push_back("PRIORITY=" + std::to_string(journal_priority(msg.level)));
    fields.push_back("SYSLOG_IDENTIFIER=" + identifier_);
    fields.push_back("FETTLE_COMPONENT=" + std::string(msg.logger_name.data(), msg.logger_name.size()));
    if (msg.source.filename != nullptr) {
      fields.push_back(std::string("CODE_FILE=") + msg.source.filename);
      fields.push_back("CODE_LINE=" + std::to_string(msg.source.line));
    }
    for (const auto& [key, value] : t_context) fields.push_back("FETTLE_" + key + "=" + value);
    std::vector<iovec> iov(fields.size());
    for (std::size_t i = 0; i < fields.size(); ++i) {
      iov[i].iov_base = fields[i].data();
      iov[i].iov_len = fields[i].size();
    }
    // A missing journal socket must never stop the program: the record is dropped.
    (void)sd_journal_sendv(iov.data(), static_cast<int>(iov.size()));
  }
  void flush_() override {}

 private:
  std::string identifier_;
};

struct State {
  std::mutex mutex;
  Options options;
  spdlog::sink_ptr sink;
  std::map<std::string, std::shared_ptr<spdlog::logger>, std::less<>> loggers;
};

State& state() {
  static State s;
  return s;
}

spdlog::level::level_enum parse_level(const std::string& name) {
  if (!is_level_name(name)) {
    std::string allowed;
    for (const auto& n : level_names()) allowed += (allowed.empty() ? "" : ", ") + n;
    throw std::invalid_argument("unknown log level '" + name + "' (allowed: " + allowed + ")");
  }
  return spdlog::level::from_str(name);
}

spdlog::level::level_enum level_for(const Options& o, std::string_view component) {
  if (o.override_level) return parse_level(*o.override_level);
  auto it = o.component_levels.find(std::string(component));
  return parse_level(it != o.component_levels.end() ? it->second : o.default_level);
}

/// Options::burst_lines: similar lines beyond the burst within a window are counted, not written.
class RateLimitSink final : public spdlog::sinks::base_sink<std::mutex> {
 public:
  RateLimitSink(spdlog::sink_ptr inner, int burst, std::chrono::milliseconds window)
      : inner_(std::move(inner)), burst_(burst), window_(window) {}

 protected:
  void sink_it_(const spdlog::details::log_msg& msg) override {
    if (burst_ <= 0) return inner_->log(msg);
    std::string key(msg.logger_name.data(), msg.logger_name.size());
    key += '\x1f';
    key += static_cast<char>('0' + static_cast<int>(msg.level));
    for (const char c : msg.payload) {  // "similar": the same text but for its numbers
      if (std::isdigit(static_cast<unsigned char>(c)) == 0) key += c;
      else if (key.back() != '#') key += '#';
    }
    if (entries_.size() > kMaxShapes) report_all(msg), entries_.clear();
    auto& e = entries_[key];
    if (e.count == 0 || msg.time - e.window_start >= window_) {
      report(e, msg);
      e.window_start = msg.time;
      e.count = 0;
    }
    if (++e.count <= burst_) return inner_->log(msg);
    ++e.suppressed;
    e.example.assign(msg.payload.data(), msg.payload.size());
    e.level = msg.level;
    e.logger.assign(msg.logger_name.data(), msg.logger_name.size());
  }
  void flush_() override {
    // what was suppressed and never followed by another line is said at the flush
    if (!entries_.empty()) report_all(spdlog::details::log_msg{});
    inner_->flush();
  }

 private:
  struct Entry {
    spdlog::log_clock::time_point window_start{};
    int count = 0;
    std::size_t suppressed = 0;
    std::string example, logger;
    spdlog::level::level_enum level = spdlog::level::info;
  };
  static constexpr std::size_t kMaxShapes = 4096;

  void report(Entry& e, const spdlog::details::log_msg& now) {
    if (e.suppressed == 0) return;
    const std::string text = "suppressed " + std::to_string(e.suppressed) + " similar line" +
                             (e.suppressed == 1 ? "" : "s") + " (rate limit " + std::to_string(burst_) + " per " +
                             std::to_string(window_.count()) + " ms), the last: " + e.example;
    spdlog::details::log_msg m(e.logger, e.level, text);
    if (now.time != spdlog::log_clock::time_point{}) m.time = now.time;
    inner_->log(m);
    e.suppressed = 0;
  }
  void report_all(const spdlog::details::log_msg& now) {
    for (auto& [key, e] : entries_) report(e, now);
  }

  spdlog::sink_ptr inner_;
  int burst_;
  std::chrono::milliseconds window_;
  std::unordered_map<std::string, Entry> entries_;
};

spdlog::sink_ptr make_sink(const Options& o) {
  const Target t = resolve_target(o.target, std::getenv("JOURNAL_STREAM"), std::getenv("INVOCATION_ID"));
  spdlog::sink_ptr sink;
  if (t == Target::journal) {
    sink = std::make_shared<JournalSink>(o.program);
  } else {
    sink = std::make_shared<spdlog::sinks::stderr_color_sink_mt>();
    sink->set_pattern("%Y-%m-%d %H:%M:%S.%e %^%-5l%$ [%n] %v");
  }
  return rate_limited(std::move(sink), o.burst_lines, o.rate_window_ms);
}

}  // namespace

spdlog::sink_ptr rate_limited(spdlog::sink_ptr inner, int burst_lines, int window_ms) {
  if (burst_lines <= 0) return inner;
  return std::make_shared<RateLimitSink>(std::move(inner), burst_lines, std::chrono::milliseconds(window_ms));
}

const std::vector<std::string>& level_names() {
  static const std::vector<std::string> names{"trace", "debug", "info", "warn", "error", "critical", "off"};
  return names;
}

bool is_level_name(std::string_view name) {
  const auto& n = level_names();
  return std::find(n.begin(), n.end(), name) != n.end();
}

Target resolve_target(Target requested, const char* journal_stream, const char* invocation_id) {
  if (requested != Target::automatic) return requested;
  const bool systemd = (journal_stream != nullptr && *journal_stream != '\0') ||
                       (invocation_id != nullptr && *invocation_id != '\0');
  return systemd ? Target::journal : Target::stderr_text;
}

void init(const Options& options) {
  // Validate every level before changing anything.
  (void)parse_level(options.default_level);
  for (const auto& [component, level] : options.component_levels) {
    try {
      (void)parse_level(level);
    } catch (const std::invalid_argument& e) {
      throw std::invalid_argument("component '" + component + "': " + e.what());
    }
  }
  if (options.override_level) (void)parse_level(*options.override_level);

  auto& s = state();
  std::lock_guard lock(s.mutex);
  s.options = options;
  s.sink = make_sink(options);
  for (auto& [name, logger] : s.loggers) {
    logger->sinks().assign(1, s.sink);
    logger->set_level(level_for(s.options, name));
  }
}

std::shared_ptr<spdlog::logger> get(std::string_view component) {
  auto& s = state();
  std::lock_guard lock(s.mutex);
  if (auto it = s.loggers.find(component); it != s.loggers.end()) return it->second;
  if (!s.sink) s.sink = make_sink(s.options);
  auto logger = std::make_shared<spdlog::logger>(std::string(component), s.sink);
  logger->set_level(level_for(s.options, component));
  logger->flush_on(spdlog::level::warn);
  s.loggers.emplace(std::string(component), logger);
  return logger;
}

Scope::Scope(std::string key, std::string value) : key_(std::move(key)) {
  if (auto it = t_context.find(key_); it != t_context.end()) previous_ = it->second;
  t_context[key_] = std::move(value);
}

Scope::~Scope() {
  if (previous_) {
    t_context[key_] = *previous_;
  } else {
    t_context.erase(key_);
  }
}

const std::map<std::string, std::string>& context() { return t_context; }

}  // namespace fettle::log
