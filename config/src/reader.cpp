#include "reader.hpp"

#include <arpa/inet.h>

#include <algorithm>
#include <cmath>
#include <cctype>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <sstream>

namespace fettle::config {

std::string Diagnostic::to_string() const {
  std::ostringstream s;
  s << file;
  if (line > 0) s << ':' << line << ':' << column;
  s << ": ";
  if (!key.empty()) s << "key '" << key << "': ";
  s << message;
  return s.str();
}

namespace {
std::string join(const std::vector<Diagnostic>& d) {
  std::string out;
  for (const auto& x : d) out += (out.empty() ? "" : "\n") + x.to_string();
  return out;
}
}  // namespace

ConfigError::ConfigError(std::vector<Diagnostic> diagnostics)
    : UserError(join(diagnostics)), diagnostics_(std::move(diagnostics)) {}

}  // namespace fettle::config

namespace fettle::config::detail {
namespace {

std::size_t edit_distance(std::string_view a, std::string_view b) {
  std::vector<std::size_t> prev(b.size() + 1), cur(b.size() + 1);
  for (std::size_t j = 0; j <= b.size(); ++j) prev[j] = j;
  for (std::size_t i = 1; i <= a.size(); ++i) {
    cur[0] = i;
    for (std::size_t j = 1; j <= b.size(); ++j) {
      const std::size_t sub = prev[j - 1] + (a[i - 1] == b[j - 1] ? 0 : 1);
      cur[j] = std::min({prev[j] + 1, cur[j - 1] + 1, sub});
    }
    std::swap(prev, cur);
  }
  return prev[b.size()];
}

std::string join_names(const std::vector<std::string>& names) {
  std::string out;
  for (const auto& n : names) out += (out.empty() ? "" : ", ") + n;
  return out;
}

template <class T>
std::string num(T v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

}  // namespace

void Report::add(const toml::source_region& where, std::string key, std::string message) {
  items_.push_back(Diagnostic{file_, static_cast<int>(where.begin.line), static_cast<int>(where.begin.column),
                              std::move(key), std::move(message)});
}

void Report::add_file(std::string message) { items_.push_back(Diagnostic{file_, 0, 0, "", std::move(message)}); }

std::string describe(const toml::node& node) {
  switch (node.type()) {
    case toml::node_type::string:
      return "string \"" + std::string(*node.value<std::string_view>()) + "\"";
    case toml::node_type::integer:
      return "integer " + num(*node.value<int64_t>());
    case toml::node_type::floating_point:
      return "float " + num(*node.value<double>());
    case toml::node_type::boolean:
      return std::string("boolean ") + (*node.value<bool>() ? "true" : "false");
    case toml::node_type::table:
      return "a table";
    case toml::node_type::array:
      return "an array";
    case toml::node_type::date:
      return "a date";
    case toml::node_type::time:
      return "a time";
    case toml::node_type::date_time:
      return "a date-time";
    default:
      return "nothing";
  }
}

std::optional<NestingProblem> too_deeply_nested(std::string_view text, int limit) {
  int line = 1, column = 0;
  std::vector<char> brackets;  // open [ and { (arrays and inline tables, headers too)
  bool key = true;             // in a key: a line's start outside brackets, after { or , in an inline table
  bool header = false;         // in a [table] or [[array]] header
  int dots = 0;                // dotted parts so far in this key or header
  for (std::size_t i = 0; i < text.size(); ++i) {
    const char ch = text[i];
    ++column;
    if (ch == '\n') {
      ++line, column = 0;
      key = brackets.empty();
      header = false;
      dots = 0;
      continue;
    }
    if (ch == '#') {  // comment to the end of the line
      while (i + 1 < text.size() && text[i + 1] != '\n') ++i;
      continue;
    }
    if (ch == '"' || ch == '\'') {  // strings, multi-line ones too (""" and ''')
      const bool multi = text.substr(i, 3) == std::string(3, ch);
      const std::string close = multi ? std::string(3, ch) : std::string(1, ch);
      std::size_t j = i + close.size();
      while (j < text.size() && text.substr(j, close.size()) != close) {
        if (ch == '"' && text[j] == '\\') ++j;  // escapes in basic strings only
        if (j < text.size() && text[j] == '\n') {
          if (!multi) break;  // an unterminated string: the parser says so
          ++line, column = 0;
        }
        ++j;
      }
      i = std::min(text.size(), j + close.size()) - 1;
      continue;
    }
    if (ch == '[' || ch == '{') {
      if (ch == '[' && key && brackets.empty()) header = true, dots = 0;
      brackets.push_back(ch);
      if (static_cast<int>(brackets.size()) > limit)
        return NestingProblem{line, column, "arrays and inline tables nested deeper than " + std::to_string(limit)};
      key = ch == '{';
      continue;
    }
    if (ch == ']' || ch == '}') {
      if (!brackets.empty()) brackets.pop_back();
      if (header && brackets.empty()) header = false;
      key = false;
      continue;
    }
    if (ch == ',' && !brackets.empty() && brackets.back() == '{') {
      key = true, dots = 0;
      continue;
    }
    if (ch == '=' && !header) {
      key = false, dots = 0;
      continue;
    }
    if (ch == '.' && (key || header) && ++dots + 1 > limit)
      return NestingProblem{line, column, "a key or table header of more than " + std::to_string(limit) + " dotted parts"};
  }
  return std::nullopt;
}

std::optional<toml::table> parse_file(const std::filesystem::path& file, Report& report) {
  std::error_code ec;
  // Only regular files: a FIFO or a device would block or never end (issue 40, item 4).
  if (!std::filesystem::is_regular_file(file, ec)) {
    report.add_file(std::filesystem::exists(file, ec) ? "not a regular file (a FIFO, device or directory?): " +
                                                            file.string()
                                                      : "no such file");
    return std::nullopt;
  }
  if (const auto size = std::filesystem::file_size(file, ec); !ec && size > kMaxConfigBytes) {
    report.add_file("is " + std::to_string(size) + " bytes: a configuration file is at most " +
                    std::to_string(kMaxConfigBytes) + " bytes");
    return std::nullopt;
  }
  std::ifstream in(file, std::ios::binary);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (!in && !in.eof()) {
    report.add_file("cannot be read");
    return std::nullopt;
  }
  // The parser recurses per level: a header of 50 000 dotted parts overflows the stack, so the
  // depth is checked on the text first (docs/security.md; tests ConfigBadInput.AHeaderOfFiftyThousand*,
  // ConfigNesting.*).
  if (const auto deep = too_deeply_nested(text, kMaxNesting)) {
    report.add(toml::source_region{{static_cast<toml::source_index>(deep->line), static_cast<toml::source_index>(deep->column)},
                                   {},
                                   {}},
               "", deep->what + ": refused before parsing");
    return std::nullopt;
  }
  try {
    return toml::parse(text, file.string());
  } catch (const toml::parse_error& e) {
    report.add(e.source(), "", "TOML syntax error: " + std::string(e.description()));
    return std::nullopt;
  }
}

TableReader::TableReader(const toml::table& table, std::string path, Report& report, std::filesystem::path base_dir)
    : table_(&table), path_(std::move(path)), report_(&report), base_dir_(std::move(base_dir)) {}

TableReader::TableReader(TableReader&& other) noexcept
    : table_(other.table_),
      path_(std::move(other.path_)),
      report_(other.report_),
      base_dir_(std::move(other.base_dir_)),
      known_(std::move(other.known_)),
      finished_(other.finished_) {
  other.finished_ = true;
}

TableReader::~TableReader() { finish(); }

bool TableReader::has(std::string_view key) const { return table_->contains(key); }

std::string TableReader::key_path(std::string_view key) const {
  return path_.empty() ? std::string(key) : path_ + "." + std::string(key);
}

void TableReader::error(std::string_view key, std::string message) {
  const toml::node* node = table_->get(key);
  report_->add(node != nullptr ? node->source() : table_->source(), key_path(key), std::move(message));
}

const toml::node* TableReader::lookup(std::string_view key, Need need) {
  known_.emplace(key);
  const toml::node* node = table_->get(key);
  if (node == nullptr && need == Need::required) {
    report_->add(table_->source(), key_path(key),
                 "missing; this key is required" + (path_.empty() ? std::string() : " in [" + path_ + "]"));
  }
  return node;
}

void TableReader::type_error(std::string_view key, const toml::node& node, std::string_view expected) {
  report_->add(node.source(), key_path(key), "must be " + std::string(expected) + ", got " + describe(node));
}

void TableReader::integer(std::string_view key, int& out, Range<long long> range, Need need) {
  const toml::node* node = lookup(key, need);
  if (node == nullptr) return;
  const auto v = node->value_exact<int64_t>();
  if (!v) return type_error(key, *node, "an integer");
  if (*v < range.min || *v > range.max) {
    report_->add(node->source(), key_path(key),
                 "value " + num(*v) + " is out of range (allowed " + num(range.min) + " to " + num(range.max) + ")");
    return;
  }
  out = static_cast<int>(*v);
}

void TableReader::number(std::string_view key, double& out, Range<double> range, Need need) {
  const toml::node* node = lookup(key, need);
  if (node == nullptr) return;
  std::optional<double> v;
  if (node->is_floating_point()) v = node->value_exact<double>();
  if (node->is_integer()) v = static_cast<double>(*node->value_exact<int64_t>());
  if (!v) return type_error(key, *node, "a number");
  if (!std::isfinite(*v) || *v < range.min || *v > range.max) {
    report_->add(node->source(), key_path(key),
                 "value " + num(*v) + " is out of range (allowed " + num(range.min) + " to " + num(range.max) + ")");
    return;
  }
  out = *v;
}

void TableReader::boolean(std::string_view key, bool& out, Need need) {
  const toml::node* node = lookup(key, need);
  if (node == nullptr) return;
  const auto v = node->value_exact<bool>();
  if (!v) return type_error(key, *node, "true or false");
  out = *v;
}

void TableReader::string(std::string_view key, std::string& out, Need need, bool allow_empty) {
  const toml::node* node = lookup(key, need);
  if (node == nullptr) return;
  const auto v = node->value_exact<std::string>();
  if (!v) return type_error(key, *node, "a string");
  if (!allow_empty && v->empty()) {
    report_->add(node->source(), key_path(key), "must not be empty");
    return;
  }
  // One line of text: a NUL ends it early where it meets C, a newline starts a second line
  // where it meets a line protocol (issue 40, item 9; docs/security.md "Limits").
  if (const auto bad = std::find_if(v->begin(), v->end(), [](char c) { return static_cast<unsigned char>(c) < 0x20 && c != '\t'; });
      bad != v->end()) {
    char hex[8];
    std::snprintf(hex, sizeof hex, "0x%02x", static_cast<unsigned>(static_cast<unsigned char>(*bad)));
    report_->add(node->source(), key_path(key),
                 std::string("contains a control character (") + hex + " at byte " + std::to_string(bad - v->begin()) +
                     "): a value here is one line of text");
    return;
  }
  if (v->size() > kMaxStringBytes) {
    report_->add(node->source(), key_path(key),
                 "is " + std::to_string(v->size()) + " bytes long (at most " + std::to_string(kMaxStringBytes) + ")");
    return;
  }
  out = *v;
}

void TableReader::ident(std::string_view key, std::string& out, std::size_t max_chars, Need need) {
  std::string v;
  const std::size_t before = report_->diagnostics().size();
  string(key, v, need);
  if (report_->diagnostics().size() != before || v.empty()) return;
  const bool ok = v.size() <= max_chars && std::all_of(v.begin(), v.end(), [](char c) {
                    return std::isalnum(static_cast<unsigned char>(c)) != 0 || c == '_' || c == '-' || c == '.';
                  });
  if (!ok) {
    error(key, "\"" + v + "\" is not an identifier: 1 to " + std::to_string(max_chars) +
                   " letters, digits, '_', '-' or '.' (it goes on a wire as one token)");
    return;
  }
  out = v;
}

void TableReader::choice(std::string_view key, std::string& out, const std::vector<std::string>& allowed, Need need) {
  const toml::node* node = lookup(key, need);
  if (node == nullptr) return;
  const auto v = node->value_exact<std::string>();
  if (!v) return type_error(key, *node, "one of: " + join_names(allowed));
  if (std::find(allowed.begin(), allowed.end(), *v) == allowed.end()) {
    report_->add(node->source(), key_path(key), "\"" + *v + "\" is not allowed (allowed: " + join_names(allowed) + ")");
    return;
  }
  out = *v;
}

void TableReader::ipv4(std::string_view key, std::string& out, Need need) {
  const toml::node* node = lookup(key, need);
  if (node == nullptr) return;
  const auto v = node->value_exact<std::string>();
  if (!v) return type_error(key, *node, "an IPv4 address string such as \"192.168.10.20\"");
  if (std::any_of(v->begin(), v->end(), [](char c) { return static_cast<unsigned char>(c) < 0x20; })) {
    std::string ignored;
    string(key, ignored, need);  // says which control character, and where
    return;
  }
  in_addr addr{};
  if (::inet_pton(AF_INET, v->c_str(), &addr) != 1) {
    report_->add(node->source(), key_path(key),
                 "\"" + *v + "\" is not an IPv4 address (expected four numbers 0-255 such as \"192.168.10.20\")");
    return;
  }
  out = *v;
}

void TableReader::port(std::string_view key, int& out, Need need, bool allow_zero) {
  integer(key, out, {allow_zero ? 0 : 1, 65535}, need);
}

void TableReader::path(std::string_view key, std::filesystem::path& out, Need need, bool must_exist) {
  std::string s;
  string(key, s, need);
  if (s.empty()) return;
  std::filesystem::path p(s);
  if (p.is_relative()) p = base_dir_ / p;
  p = p.lexically_normal();
  std::error_code ec;
  if (p.string().size() > kMaxPathBytes) {
    error(key, "is " + std::to_string(p.string().size()) + " bytes long as a path (at most " +
                   std::to_string(kMaxPathBytes) + ")");
    return;
  }
  if (must_exist && !std::filesystem::exists(p, ec)) {
    error(key, "file \"" + p.string() + "\" does not exist");
    return;
  }
  // a file that must exist is read: a FIFO would block, a device never end
  if (must_exist && !std::filesystem::is_regular_file(p, ec)) {
    error(key, "\"" + p.string() + "\" is not a regular file (a FIFO, device or directory?)");
    return;
  }
  out = p;
}

void TableReader::vec3(std::string_view key, std::array<double, 3>& out, Range<double> range, Need need) {
  std::vector<double> v(out.begin(), out.end());
  const std::size_t before = report_->diagnostics().size();
  numbers(key, v, range, 3, 3, need);
  if (report_->diagnostics().size() == before && v.size() == 3) std::copy(v.begin(), v.end(), out.begin());
}

void TableReader::numbers(std::string_view key, std::vector<double>& out, Range<double> range, std::size_t min_count,
                          std::size_t max_count, Need need) {
  const toml::node* node = lookup(key, need);
  if (node == nullptr) return;
  const toml::array* arr = node->as_array();
  const std::string expected = min_count == max_count
                                   ? "an array of " + num(min_count) + " numbers"
                                   : "an array of " + num(min_count) + " to " + num(max_count) + " numbers";
  if (arr == nullptr) return type_error(key, *node, expected);
  if (arr->size() < min_count || arr->size() > max_count) {
    report_->add(node->source(), key_path(key), "must be " + expected + ", got " + num(arr->size()));
    return;
  }
  std::vector<double> values;
  bool ok = true;
  for (std::size_t i = 0; i < arr->size(); ++i) {
    const toml::node& e = *arr->get(i);
    std::optional<double> v;
    if (e.is_floating_point()) v = e.value_exact<double>();
    if (e.is_integer()) v = static_cast<double>(*e.value_exact<int64_t>());
    const std::string item = key_path(key) + "[" + num(i) + "]";
    if (!v) {
      report_->add(e.source(), item, "must be a number, got " + describe(e));
      ok = false;
    } else if (!std::isfinite(*v) || *v < range.min || *v > range.max) {
      report_->add(e.source(), item,
                   "value " + num(*v) + " is out of range (allowed " + num(range.min) + " to " + num(range.max) + ")");
      ok = false;
    } else {
      values.push_back(*v);
    }
  }
  if (ok) out = std::move(values);
}

void TableReader::string_map(std::string_view key, std::map<std::string, std::string>& out,
                             const std::function<std::string(const std::string&)>& valid, Need need) {
  const toml::node* node = lookup(key, need);
  if (node == nullptr) return;
  const toml::table* t = node->as_table();
  if (t == nullptr) return type_error(key, *node, "a table");
  for (const auto& [k, v] : *t) {
    const std::string item = key_path(key) + "." + std::string(k.str());
    const auto s = v.value_exact<std::string>();
    if (!s) {
      report_->add(v.source(), item, "must be a string, got " + describe(v));
      continue;
    }
    if (std::string msg = valid(*s); !msg.empty()) {
      report_->add(v.source(), item, msg);
      continue;
    }
    out[std::string(k.str())] = *s;
  }
}

std::optional<TableReader> TableReader::table(std::string_view key, Need need) {
  const toml::node* node = lookup(key, need);
  if (node == nullptr) return std::nullopt;
  const toml::table* t = node->as_table();
  if (t == nullptr) {
    type_error(key, *node, "a table");
    return std::nullopt;
  }
  return TableReader(*t, key_path(key), *report_, base_dir_);
}

void TableReader::tables(std::string_view key, const std::function<void(TableReader&, std::size_t)>& each, Need need) {
  const toml::node* node = lookup(key, need);
  if (node == nullptr) return;
  const toml::array* arr = node->as_array();
  if (arr == nullptr) return type_error(key, *node, "an array of tables ([[" + key_path(key) + "]])");
  for (std::size_t i = 0; i < arr->size(); ++i) {
    const toml::node& e = *arr->get(i);
    const toml::table* t = e.as_table();
    const std::string item = key_path(key) + "[" + num(i) + "]";
    if (t == nullptr) {
      report_->add(e.source(), item, "must be a table, got " + describe(e));
      continue;
    }
    TableReader r(*t, item, *report_, base_dir_);
    each(r, i);
  }
}

void TableReader::finish() {
  if (finished_) return;
  finished_ = true;
  std::vector<std::string> allowed(known_.begin(), known_.end());
  for (const auto& [k, v] : *table_) {
    const std::string_view name = k.str();
    if (known_.contains(name)) continue;
    std::string message = "unknown key";
    std::string best;
    std::size_t best_d = 3;  // suggest only close matches
    for (const auto& a : allowed) {
      const std::size_t d = edit_distance(name, a);
      if (d < best_d) {
        best_d = d;
        best = a;
      }
    }
    if (!best.empty()) message += " (did you mean '" + best + "'?)";
    message += allowed.empty() ? "; this table takes no keys" : "; allowed here: " + join_names(allowed);
    // Report at the key itself where toml++ knows it, else at its value.
    const toml::source_region& where = k.source().begin.line > 0 ? k.source() : v.source();
    report_->add(where, key_path(name), message);
  }
}

}  // namespace fettle::config::detail
