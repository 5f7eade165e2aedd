// Robot line protocol: parsing and formatting (docs/robot-protocol.md).
#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <cstdio>

#include "fettle/drivers/robot_protocol.hpp"

namespace fettle::drivers::robot {
namespace {

enum class Cls { uint, mm, speed, quat, ident, word, hex8, kind };

struct FieldSpec {
  Cls cls;
  long min = 0;
  long max = 0;
  const char* name = "";
};

struct VerbSpec {
  Verb verb;
  std::string_view name;
  std::vector<FieldSpec> fields;
  std::size_t min_fields;
  bool text;  ///< free text may follow the fields
};

const FieldSpec kRef{Cls::uint, 0, kMaxSeq, "ref"};
const FieldSpec kId{Cls::uint, 1, kMaxId, "id"};
const FieldSpec kIndex{Cls::uint, 0, kMaxPoints - 1, "index"};

const std::vector<VerbSpec>& specs() {
  static const std::vector<VerbSpec> s = {
      {Verb::hello, "HELLO",
       {{Cls::uint, 1, 99, "version"}, {Cls::ident, 0, 0, "cell_id"}, {Cls::uint, 10, 99999, "watchdog_ms"}}, 3, false},
      {Verb::traj, "TRAJ",
       {kId, {Cls::uint, 1, kMaxPoints, "points"}, {Cls::uint, 1, kMaxPoints, "chunks"}, {Cls::hex8, 0, 0, "crc"}},
       4, false},
      {Verb::chunk, "CHUNK",
       {{Cls::uint, 1, kMaxPoints, "chunk"}, kIndex, {Cls::uint, 1, kMaxPoints, "count"}}, 3, false},
      {Verb::p, "P",
       {kIndex, {Cls::mm, 0, 0, "x_mm"}, {Cls::mm, 0, 0, "y_mm"}, {Cls::mm, 0, 0, "z_mm"},
        {Cls::speed, 0, 0, "speed_mm_s"}, {Cls::uint, 0, kMaxRpm, "spindle_rpm"},
        {Cls::uint, 0, kMaxSegment, "segment"}, {Cls::kind, 0, 0, "kind"}},
       8, false},
      {Verb::q, "Q",
       {kIndex, {Cls::quat, 0, 0, "qw"}, {Cls::quat, 0, 0, "qx"}, {Cls::quat, 0, 0, "qy"}, {Cls::quat, 0, 0, "qz"}},
       5, false},
      {Verb::end, "END", {kId}, 1, false},
      {Verb::run, "RUN", {kId}, 1, false},
      {Verb::stop, "STOP", {}, 0, false},
      {Verb::reset, "RESET", {}, 0, false},
      {Verb::ping, "PING", {}, 0, false},
      {Verb::ack, "ACK", {kRef, {Cls::uint, 1, 99, "version"}, {Cls::ident, 0, 0, "robot_id"}}, 1, false},
      {Verb::nak, "NAK", {kRef, {Cls::word, 0, 0, "code"}}, 2, true},
      {Verb::pong, "PONG", {kRef}, 1, false},
      {Verb::prog, "PROG", {kId, {Cls::uint, 0, kMaxSegment, "segment"}, kIndex}, 3, false},
      {Verb::done, "DONE", {kId, {Cls::uint, 0, kMaxPoints, "points"}}, 2, false},
      {Verb::fault, "FAULT", {{Cls::uint, 0, kMaxId, "id"}, {Cls::word, 0, 0, "code"}}, 2, true},
  };
  return s;
}

bool is_digit(char c) { return c >= '0' && c <= '9'; }

// Unsigned decimal without leading zeros, at most 5 digits, within [min, max].
bool check_uint(std::string_view s, long min, long max) {
  if (s.empty() || s.size() > 5 || !std::all_of(s.begin(), s.end(), is_digit)) return false;
  if (s.size() > 1 && s[0] == '0') return false;
  long v = 0;
  for (char c : s) v = v * 10 + (c - '0');
  return v >= min && v <= max;
}

// -?D{1,max_int}.D{decimals}
bool check_fixed(std::string_view s, std::size_t max_int, std::size_t decimals, bool allow_negative) {
  if (!s.empty() && s[0] == '-') {
    if (!allow_negative) return false;
    s.remove_prefix(1);
  }
  const auto dot = s.find('.');
  if (dot == std::string_view::npos || dot == 0 || dot > max_int) return false;
  const auto ip = s.substr(0, dot);
  const auto fp = s.substr(dot + 1);
  if (ip.size() > 1 && ip[0] == '0') return false;
  return fp.size() == decimals && std::all_of(ip.begin(), ip.end(), is_digit) &&
         std::all_of(fp.begin(), fp.end(), is_digit);
}

bool check_field(std::string_view s, const FieldSpec& f) {
  switch (f.cls) {
    case Cls::uint: return check_uint(s, f.min, f.max);
    case Cls::mm: return check_fixed(s, 5, 3, true);
    case Cls::speed: return check_fixed(s, 4, 3, false);
    case Cls::quat: return check_fixed(s, 1, 6, true);
    case Cls::ident:
      return !s.empty() && s.size() <= kMaxIdentChars && std::all_of(s.begin(), s.end(), [](char c) {
        return is_digit(c) || (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || c == '_' || c == '-' || c == '.';
      });
    case Cls::word: return is_code(s);
    case Cls::hex8:
      return s.size() == 8 &&
             std::all_of(s.begin(), s.end(), [](char c) { return is_digit(c) || (c >= 'A' && c <= 'F'); });
    case Cls::kind: return s.size() == 1 && kind_from_letter(s[0]).has_value();
  }
  return false;
}

Error syntax(std::string message) { return Error{"robot.syntax", std::move(message)}; }

std::string quoted(std::string_view s) {
  std::string out = "'";
  out.append(s.substr(0, 24));
  if (s.size() > 24) out += "...";
  return out + "'";
}

}  // namespace

std::string_view verb_name(Verb v) {
  for (const auto& s : specs())
    if (s.verb == v) return s.name;
  return "?";
}

Result<Line> parse_line(std::string_view line) {
  if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
  if (line.size() > kMaxLineChars)
    return Error{"robot.too_long", "line of " + std::to_string(line.size()) + " characters, at most " +
                                       std::to_string(kMaxLineChars) + " allowed"};
  for (std::size_t i = 0; i < line.size(); ++i) {
    const auto c = static_cast<unsigned char>(line[i]);
    if (c < 0x20 || c > 0x7E) {
      std::array<char, 8> hex{};
      std::snprintf(hex.data(), hex.size(), "0x%02X", static_cast<unsigned>(c));
      return Error{"robot.bad_char",
                   "byte " + std::string(hex.data()) + " at column " + std::to_string(i + 1) +
                       " (only printable ASCII 0x20..0x7E is allowed)"};
    }
  }
  if (line.empty()) return syntax("empty line");

  // Tokens separated by single spaces.
  std::vector<std::string_view> tokens;
  std::size_t start = 0;
  while (true) {
    const auto sp = line.find(' ', start);
    tokens.push_back(line.substr(start, sp == std::string_view::npos ? std::string_view::npos : sp - start));
    if (sp == std::string_view::npos) break;
    start = sp + 1;
  }
  if (!check_uint(tokens[0], 1, kMaxSeq))
    return syntax("sequence number " + quoted(tokens[0]) + " is not an integer 1..99999 without leading zeros");
  if (tokens.size() < 2 || tokens[1].empty()) return syntax("missing verb after the sequence number");

  const VerbSpec* spec = nullptr;
  for (const auto& s : specs())
    if (s.name == tokens[1]) spec = &s;
  if (spec == nullptr) return syntax("unknown verb " + quoted(tokens[1]));

  Line out;
  out.seq = *to_int(tokens[0]);
  out.verb = spec->verb;
  const std::size_t given = tokens.size() - 2;
  const std::size_t nfields = spec->text ? std::min(given, spec->fields.size()) : given;
  if (nfields < spec->min_fields || (!spec->text && given > spec->fields.size()))
    return syntax(std::string(spec->name) + " takes " +
                  (spec->min_fields == spec->fields.size() || spec->text
                       ? std::to_string(spec->min_fields)
                       : std::to_string(spec->min_fields) + " to " + std::to_string(spec->fields.size())) +
                  " fields, got " + std::to_string(given));
  for (std::size_t i = 0; i < nfields; ++i) {
    const auto tok = tokens[i + 2];
    if (tok.empty()) return syntax("empty field (two spaces or a trailing space) in " + std::string(spec->name));
    if (!check_field(tok, spec->fields[i]))
      return syntax(std::string(spec->name) + " field " + spec->fields[i].name + " = " + quoted(tok) +
                    " is malformed or out of range");
    out.fields.emplace_back(tok);
  }
  if (spec->text && given > nfields) {
    // Free text: everything after the fields, verbatim.
    std::size_t pos = 0;
    for (std::size_t i = 0; i < nfields + 2; ++i) pos = line.find(' ', pos) + 1;
    out.text = std::string(line.substr(pos));
  }
  return out;
}

std::string format_line(int seq, std::string_view payload) {
  std::string s = std::to_string(seq);
  s += ' ';
  s.append(payload);
  return s;
}

int next_seq(int seq) { return seq >= kMaxSeq || seq < 1 ? 1 : seq + 1; }

Status LineSplitter::feed(std::string_view bytes, std::vector<std::string>& lines) {
  for (char c : bytes) {
    if (c == '\n') {
      if (!partial_.empty() && partial_.back() == '\r') partial_.pop_back();
      if (!partial_.empty()) lines.push_back(std::move(partial_));
      partial_.clear();
      continue;
    }
    partial_.push_back(c);
    // Room for the CR of a CRLF terminator.
    if (partial_.size() > kMaxLineChars + 1 || (partial_.size() == kMaxLineChars + 1 && c != '\r')) {
      const auto n = partial_.size();
      partial_.clear();
      return Error{"robot.too_long", "line longer than " + std::to_string(kMaxLineChars) + " characters (" +
                                         std::to_string(n) + " without a line feed)"};
    }
  }
  return {};
}

std::string fixed(double value, int decimals) {
  std::array<char, 64> buf{};
  const int n = std::snprintf(buf.data(), buf.size(), "%.*f", decimals, value);
  std::string s(buf.data(), n > 0 ? static_cast<std::size_t>(std::min<int>(n, 63)) : 0);
  if (!s.empty() && s[0] == '-' &&
      std::all_of(s.begin() + 1, s.end(), [](char c) { return c == '0' || c == '.'; }))
    s.erase(0, 1);
  return s;
}

std::optional<double> to_double(std::string_view s) {
  double v = 0.0;
  const auto* end = s.data() + s.size();
  const auto [ptr, ec] = std::from_chars(s.data(), end, v);
  if (ec != std::errc{} || ptr != end || !std::isfinite(v)) return std::nullopt;
  return v;
}

bool is_code(std::string_view s) {
  return !s.empty() && s.size() <= 16 && s[0] >= 'A' && s[0] <= 'Z' &&
         std::all_of(s.begin(), s.end(), [](char c) { return (c >= '0' && c <= '9') || (c >= 'A' && c <= 'Z') || c == '_'; });
}

std::optional<int> to_int(std::string_view s) {
  int v = 0;
  const auto* end = s.data() + s.size();
  const auto [ptr, ec] = std::from_chars(s.data(), end, v);
  if (ec != std::errc{} || ptr != end) return std::nullopt;
  return v;
}

char kind_letter(MoveKind k) {
  switch (k) {
    case MoveKind::approach: return 'A';
    case MoveKind::grind: return 'G';
    case MoveKind::air: return 'F';
    case MoveKind::retract: return 'R';
  }
  return '?';
}

std::optional<MoveKind> kind_from_letter(char c) {
  switch (c) {
    case 'A': return MoveKind::approach;
    case 'G': return MoveKind::grind;
    case 'F': return MoveKind::air;
    case 'R': return MoveKind::retract;
    default: return std::nullopt;
  }
}

Status check_point(const TrajectoryPoint& p, int index) {
  const auto bad = [index](const std::string& what) {
    return Status(Error{"robot.invalid_point", "trajectory point " + std::to_string(index) + ": " + what, ErrorKind::invalid_request});
  };
  if (index < 0 || index >= kMaxPoints)
    return bad("index outside 0.." + std::to_string(kMaxPoints - 1) + " (trajectory too long for one upload)");
  for (int i = 0; i < 3; ++i) {
    const double v = p.T_base_tool.position_mm[i];
    if (!std::isfinite(v) || std::abs(v) > kMaxCoordMm)
      return bad(std::string("position ") + "xyz"[i] + " = " + std::to_string(v) + " mm is not within +-99999.999 mm");
  }
  const auto& q = p.T_base_tool.orientation.coeffs();
  if (!q.allFinite() || q.norm() < 0.5 || q.norm() > 2.0)
    return bad("orientation quaternion is not finite or far from unit length (norm " + std::to_string(q.norm()) + ")");
  if (!std::isfinite(p.speed_mm_s) || p.speed_mm_s < 0.0 || p.speed_mm_s > kMaxSpeedMmS)
    return bad("speed " + std::to_string(p.speed_mm_s) + " mm/s is not within 0..9999.999");
  if (!std::isfinite(p.spindle_rpm) || p.spindle_rpm < 0.0 || std::lround(p.spindle_rpm) > kMaxRpm)
    return bad("spindle speed " + std::to_string(p.spindle_rpm) + " rpm is not within 0..99999");
  if (p.segment < 0 || p.segment > kMaxSegment) return bad("segment " + std::to_string(p.segment) + " is not within 0..9999");
  return {};
}

std::pair<std::string, std::string> format_point(const TrajectoryPoint& p, int index) {
  const auto& t = p.T_base_tool.position_mm;
  const Quat q = p.T_base_tool.orientation.normalized();
  const std::string idx = std::to_string(index);
  std::string pl = "P " + idx + " " + fixed(t.x(), 3) + " " + fixed(t.y(), 3) + " " + fixed(t.z(), 3) + " " +
                   fixed(p.speed_mm_s, 3) + " " + std::to_string(std::lround(p.spindle_rpm)) + " " +
                   std::to_string(p.segment) + " " + kind_letter(p.kind);
  std::string ql = "Q " + idx + " " + fixed(q.w(), 6) + " " + fixed(q.x(), 6) + " " + fixed(q.y(), 6) + " " +
                   fixed(q.z(), 6);
  return {std::move(pl), std::move(ql)};
}

Result<TrajectoryPoint> point_from_lines(const Line& p, const Line& q) {
  if (p.verb != Verb::p || q.verb != Verb::q || p.fields.size() != 8 || q.fields.size() != 5)
    return Error{"robot.syntax", "a point is a P line followed by a Q line"};
  if (p.fields[0] != q.fields[0])
    return Error{"robot.order", "Q line index " + q.fields[0] + " does not match P line index " + p.fields[0]};
  TrajectoryPoint out;
  out.T_base_tool.position_mm = Vec3(*to_double(p.fields[1]), *to_double(p.fields[2]), *to_double(p.fields[3]));
  out.speed_mm_s = *to_double(p.fields[4]);
  out.spindle_rpm = *to_int(p.fields[5]);
  out.segment = *to_int(p.fields[6]);
  out.kind = *kind_from_letter(p.fields[7][0]);
  out.T_base_tool.orientation = Quat(*to_double(q.fields[1]), *to_double(q.fields[2]), *to_double(q.fields[3]),
                                     *to_double(q.fields[4]));
  return out;
}

std::uint32_t crc32(std::string_view data, std::uint32_t previous) {
  std::uint32_t crc = ~previous;
  for (char ch : data) {
    crc ^= static_cast<unsigned char>(ch);
    for (int k = 0; k < 8; ++k) crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
  }
  return ~crc;
}

std::string canonical_text(const std::vector<std::pair<std::string, std::string>>& payloads) {
  std::string s;
  for (const auto& [pl, ql] : payloads) {
    s += pl;
    s += '\n';
    s += ql;
    s += '\n';
  }
  return s;
}

std::string crc_hex(std::uint32_t crc) {
  std::array<char, 16> buf{};
  std::snprintf(buf.data(), buf.size(), "%08X", crc);
  return std::string(buf.data(), 8);
}

}  // namespace fettle::drivers::robot
