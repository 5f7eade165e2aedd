#pragma once
// Schema-driven reading of TOML tables into plain structs (private to fettle::config).
//
// Every read marks its key as known; when a TableReader finishes, every key it did
// not read is reported as unknown (with a "did you mean" hint). Every error names
// file:line:column, the key, the bad value and what is allowed.
#include <array>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <initializer_list>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <toml++/toml.h>

#include "fettle/config/diagnostics.hpp"

namespace fettle::config::detail {

enum class Need { optional, required };

/// Collects diagnostics for one file.
class Report {
 public:
  explicit Report(std::string file) : file_(std::move(file)) {}
  void add(const toml::source_region& where, std::string key, std::string message);
  void add_file(std::string message);
  [[nodiscard]] const std::string& file() const { return file_; }
  [[nodiscard]] const std::vector<Diagnostic>& diagnostics() const { return items_; }
  [[nodiscard]] bool empty() const { return items_.empty(); }

 private:
  std::string file_;
  std::vector<Diagnostic> items_;
};

template <class T>
struct Range {
  T min;
  T max;
};

/// Reads one TOML table. Call finish() (or let the destructor do it) to report unknown keys.
class TableReader {
 public:
  TableReader(const toml::table& table, std::string path, Report& report, std::filesystem::path base_dir);
  ~TableReader();
  TableReader(TableReader&& other) noexcept;
  TableReader(const TableReader&) = delete;
  TableReader& operator=(const TableReader&) = delete;
  TableReader& operator=(TableReader&&) = delete;

  [[nodiscard]] bool has(std::string_view key) const;
  [[nodiscard]] std::string key_path(std::string_view key) const;
  [[nodiscard]] const toml::source_region& where() const { return table_->source(); }
  Report& report() { return *report_; }
  /// Reports a problem with a key (at the key's value, or at the table if absent).
  void error(std::string_view key, std::string message);

  void integer(std::string_view key, int& out, Range<long long> range, Need need = Need::optional);
  void number(std::string_view key, double& out, Range<double> range, Need need = Need::optional);
  void boolean(std::string_view key, bool& out, Need need = Need::optional);
  /// One line of text (no control character but tab), at most kMaxStringBytes.
  void string(std::string_view key, std::string& out, Need need = Need::optional, bool allow_empty = false);
  /// A token that goes on a wire: 1 to max_chars letters, digits, '_', '-', '.'.
  void ident(std::string_view key, std::string& out, std::size_t max_chars, Need need = Need::optional);
  /// A string that must be one of `allowed`.
  void choice(std::string_view key, std::string& out, const std::vector<std::string>& allowed,
              Need need = Need::optional);
  /// A string mapped to an enum value.
  template <class E>
  void enumeration(std::string_view key, E& out, std::initializer_list<std::pair<std::string_view, E>> values,
                   Need need = Need::optional) {
    std::vector<std::string> names;
    for (const auto& [name, value] : values) names.emplace_back(name);
    std::string s;
    for (const auto& [name, value] : values)
      if (value == out) s = std::string(name);
    choice(key, s, names, need);
    for (const auto& [name, value] : values)
      if (name == s) out = value;
  }
  void ipv4(std::string_view key, std::string& out, Need need = Need::optional);
  void port(std::string_view key, int& out, Need need = Need::optional, bool allow_zero = false);
  /// A path; relative paths are resolved against the directory of the file being read.
  void path(std::string_view key, std::filesystem::path& out, Need need = Need::optional, bool must_exist = false);
  void vec3(std::string_view key, std::array<double, 3>& out, Range<double> range, Need need = Need::optional);
  void numbers(std::string_view key, std::vector<double>& out, Range<double> range, std::size_t min_count,
               std::size_t max_count, Need need = Need::optional);
  /// A table of string values, each checked by `valid` (which returns an error message or "").
  void string_map(std::string_view key, std::map<std::string, std::string>& out,
                  const std::function<std::string(const std::string&)>& valid, Need need = Need::optional);

  /// A sub-table; nullopt (and an error if required) when absent or not a table.
  std::optional<TableReader> table(std::string_view key, Need need = Need::optional);
  /// An array of tables; calls `each` for every element with its reader.
  void tables(std::string_view key, const std::function<void(TableReader&, std::size_t)>& each,
              Need need = Need::optional);

  void finish();

 private:
  const toml::node* lookup(std::string_view key, Need need);
  void type_error(std::string_view key, const toml::node& node, std::string_view expected);

  const toml::table* table_;
  std::string path_;
  Report* report_;
  std::filesystem::path base_dir_;
  std::set<std::string, std::less<>> known_;
  bool finished_ = false;
};

/// Describes a node's value for an error message, e.g. `string "502"`.
std::string describe(const toml::node& node);

/// Limits on what a configuration file may be (docs/security.md): its size, and how deep keys
/// (dotted parts) and arrays / inline tables may nest.
inline constexpr std::uintmax_t kMaxConfigBytes = 4U << 20;
inline constexpr int kMaxNesting = 64;
inline constexpr std::size_t kMaxStringBytes = 4096;  ///< any string value
inline constexpr std::size_t kMaxPathBytes = 4096;    ///< PATH_MAX

struct NestingProblem {
  int line = 0, column = 0;
  std::string what;
};
/// The first place a TOML text nests deeper than `limit` (dotted parts of a key or header, or
/// open arrays and inline tables), found without parsing it; strings and comments are skipped.
std::optional<NestingProblem> too_deeply_nested(std::string_view text, int limit);

/// Parses a file; on a syntax error, records it and returns nullopt. Refuses (recorded, nullopt)
/// anything but a regular file, files over kMaxConfigBytes and nesting beyond kMaxNesting.
std::optional<toml::table> parse_file(const std::filesystem::path& file, Report& report);

}  // namespace fettle::config::detail
