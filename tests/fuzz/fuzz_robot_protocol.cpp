// Fuzz target: the robot line protocol as both sides see it (drivers/robot_protocol.hpp).
// The bytes are a TCP stream from a peer: split into lines, parse every line, and for every
// line that parses check that the parse is stable (formatting the fields back and parsing
// again gives the same line). Consecutive P/Q lines are rebuilt into a trajectory point,
// which must pass check_point and format back to the same payloads: whatever the robot
// accepts, Fettle formats identically (the CRC both sides compute depends on it).
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "fettle/drivers/robot_protocol.hpp"
#include "fuzz_input.hpp"

namespace robot = fettle::drivers::robot;

namespace {

std::string payload_of(const robot::Line& l) {
  std::string s(robot::verb_name(l.verb));
  for (const auto& f : l.fields) s += " " + f;
  if (!l.text.empty()) s += " " + l.text;
  return s;
}

void check_point_round_trip(const robot::Line& p, const robot::Line& q) {
  auto point = robot::point_from_lines(p, q);
  if (!point) return;
  const int index = *robot::to_int(p.fields[0]);
  // A quaternion that is not unit is the robot's NAK QUAT; Fettle normalises before sending.
  const double norm = point->T_base_tool.orientation.norm();
  if (norm < 0.5 || norm > 2.0) return;
  auto status = robot::check_point(*point, index);
  FUZZ_CHECK(status.ok());
  const auto [pl, ql] = robot::format_point(*point, index);
  FUZZ_CHECK(robot::parse_line(robot::format_line(1, pl)).ok());
  FUZZ_CHECK(robot::parse_line(robot::format_line(1, ql)).ok());
  // Exactly unit quaternions (as Fettle sends) must survive formatting unchanged.
  // (Negative zero, "-0.000", is accepted on input but never sent: docs/robot-protocol.md.)
  if (norm == 1.0 && payload_of(p).find("-0.000") == std::string::npos) FUZZ_CHECK(pl == payload_of(p));
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fettle::fuzz::ByteReader in(data, size);
  const std::string_view stream = in.rest();

  // Split the stream in pieces of varying size, as TCP reads would deliver it.
  robot::LineSplitter splitter;
  std::vector<std::string> lines;
  std::size_t pos = 0;
  std::size_t piece = 1;
  bool broken = false;
  while (pos < stream.size() && !broken) {
    const auto chunk = stream.substr(pos, piece);
    pos += chunk.size();
    piece = piece * 3 % 61 + 1;
    auto status = splitter.feed(chunk, lines);
    if (!status) {
      FUZZ_CHECK(status.error().code == "robot.too_long");
      broken = true;  // the connection is dropped
    }
    FUZZ_CHECK(splitter.pending() <= robot::kMaxLineChars + 1);
  }

  std::optional<robot::Line> previous;
  for (const auto& text : lines) {
    FUZZ_CHECK(!text.empty() && text.size() <= robot::kMaxLineChars + 1);
    auto line = robot::parse_line(text);
    if (!line) {
      const auto& code = line.error().code;
      FUZZ_CHECK(code == "robot.too_long" || code == "robot.bad_char" || code == "robot.syntax");
      FUZZ_CHECK(!line.error().message.empty());
      previous.reset();
      continue;
    }
    FUZZ_CHECK(line->seq >= 1 && line->seq <= robot::kMaxSeq);
    FUZZ_CHECK(robot::next_seq(line->seq) >= 1 && robot::next_seq(line->seq) <= robot::kMaxSeq);
    // Parsing what we would format from the parsed line gives the same line.
    auto again = robot::parse_line(robot::format_line(line->seq, payload_of(*line)));
    FUZZ_CHECK(again.ok());
    FUZZ_CHECK(again->verb == line->verb && again->fields == line->fields && again->text == line->text);
    for (const auto& f : line->fields) (void)robot::to_double(f);
    if (previous && previous->verb == robot::Verb::p && line->verb == robot::Verb::q)
      check_point_round_trip(*previous, *line);
    previous = std::move(line.value());
  }
  (void)robot::crc_hex(robot::crc32(stream));
  return 0;
}
