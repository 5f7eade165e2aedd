#pragma once
// The robot controller line protocol (docs/robot-protocol.md): pure parsing and
// formatting shared by the client (fettle::drivers::RobotLink) and the simulated
// robot (fettle::sim::RobotSim). No I/O here; every function is total on any input
// (garbage and oversize input give an Error, never undefined behaviour).
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "fettle/core/result.hpp"
#include "fettle/core/trajectory.hpp"

namespace fettle::drivers::robot {

inline constexpr int kProtocolVersion = 1;
inline constexpr std::size_t kMaxLineChars = 80;  ///< without the LF (and optional CR) terminator
inline constexpr int kMaxSeq = 99999;             ///< sequence numbers run 1..99999, then wrap to 1
inline constexpr int kMaxId = 99999;              ///< trajectory ids 1..99999
inline constexpr int kMaxPoints = 99999;          ///< point indices 0..99998
inline constexpr int kMaxSegment = 9999;
inline constexpr int kMaxRpm = 99999;
inline constexpr double kMaxCoordMm = 99999.999;
inline constexpr double kMaxSpeedMmS = 9999.999;
inline constexpr double kQuatNormTolerance = 1e-4;  ///< | |q| - 1 | allowed on the wire
inline constexpr std::size_t kMaxIdentChars = 32;   ///< cell id, robot id

enum class Verb {
  // fettle -> robot
  hello, traj, chunk, p, q, end, run, stop, reset, ping,
  // robot -> fettle
  ack, nak, pong, prog, done, fault,
};

/// The verb as written on the wire ("HELLO", "P", ...).
std::string_view verb_name(Verb v);

/// One parsed line: `SEQ VERB field... [text]`.
struct Line {
  int seq = 0;
  Verb verb = Verb::ping;
  std::vector<std::string> fields;  ///< the verb's fixed fields, syntax-checked
  std::string text;                 ///< free text (NAK and FAULT only), may be empty
};

/// Parses one line (without its LF; a trailing CR is tolerated). Checks length,
/// characters (printable ASCII), the sequence number, the verb and the syntax of
/// every field. Error codes: robot.too_long, robot.bad_char, robot.syntax.
Result<Line> parse_line(std::string_view line);

/// Formats `SEQ PAYLOAD` (no terminator). `payload` starts with the verb.
std::string format_line(int seq, std::string_view payload);

/// The sequence number after `seq` (99999 wraps to 1).
int next_seq(int seq);

/// Splits a byte stream into lines. Empty lines are dropped; a line longer than
/// kMaxLineChars (+ an optional CR) is an error (robot.too_long) and the splitter
/// must then be discarded with its connection.
class LineSplitter {
 public:
  /// Appends bytes and moves every complete line into `lines`.
  Status feed(std::string_view bytes, std::vector<std::string>& lines);
  [[nodiscard]] std::size_t pending() const { return partial_.size(); }

 private:
  std::string partial_;
};

// ---- numbers on the wire --------------------------------------------------------

/// Fixed-point text with `decimals` digits, never "-0.000"; e.g. fixed(12.5, 3) = "12.500".
std::string fixed(double value, int decimals);
/// Parses a field checked by parse_line (or any decimal text); nullopt on garbage.
std::optional<double> to_double(std::string_view s);
std::optional<int> to_int(std::string_view s);
/// A NAK or FAULT code as the grammar allows it: an upper-case letter, then up to 15 of A-Z 0-9 _.
bool is_code(std::string_view s);

// ---- points -----------------------------------------------------------------

/// One-letter move kind: A approach, G grind, F air (free) move, R retract.
char kind_letter(MoveKind k);
std::optional<MoveKind> kind_from_letter(char c);

/// Checks that a point can be sent (finite, ranges of the wire format, quaternion
/// not degenerate). Error code robot.invalid_point naming the point index.
Status check_point(const TrajectoryPoint& p, int index);

/// The P and Q payloads of point `index` (without sequence numbers), e.g.
///   "P 0 100.000 -20.500 300.000 50.000 9000 1 G"
///   "Q 0 0.000000 1.000000 0.000000 0.000000"
/// The quaternion is normalised before formatting. Call check_point first.
std::pair<std::string, std::string> format_point(const TrajectoryPoint& p, int index);

/// Rebuilds a point from its parsed P and Q lines (indices must match).
Result<TrajectoryPoint> point_from_lines(const Line& p, const Line& q);

// ---- CRC ----------------------------------------------------------------------

/// CRC-32/ISO-HDLC (the zlib/Ethernet CRC: poly 0x04C11DB7 reflected, init and
/// xorout 0xFFFFFFFF). crc32("123456789") == 0xCBF43926. Continue with `crc32(b, crc32(a))`.
std::uint32_t crc32(std::string_view data, std::uint32_t previous = 0);

/// The canonical text the trajectory CRC covers: for every point in order, its P
/// payload, LF, its Q payload, LF (payloads as sent, without sequence numbers).
std::string canonical_text(const std::vector<std::pair<std::string, std::string>>& payloads);

/// 8 upper-case hex digits, e.g. "CBF43926".
std::string crc_hex(std::uint32_t crc);

// ---- NAK codes (docs/robot-protocol.md, "NAK codes") -------------------------------
namespace nak {
inline constexpr std::string_view syntax = "SYNTAX";      ///< unparseable line (then the robot closes)
inline constexpr std::string_view seq = "SEQ";            ///< sequence number not the expected one (then closes)
inline constexpr std::string_view version = "VERSION";    ///< protocol version not supported
inline constexpr std::string_view cell = "CELL";          ///< cell id not the one the robot program expects
inline constexpr std::string_view busy = "BUSY";          ///< another client is connected
inline constexpr std::string_view state = "STATE";        ///< message not allowed in the robot's state
inline constexpr std::string_view id = "ID";              ///< unknown trajectory id
inline constexpr std::string_view order = "ORDER";        ///< chunk or point out of order
inline constexpr std::string_view count = "COUNT";        ///< point or chunk count wrong
inline constexpr std::string_view crc = "CRC";            ///< trajectory CRC mismatch
inline constexpr std::string_view quat = "QUAT";          ///< quaternion not unit
inline constexpr std::string_view envelope = "ENVELOPE";  ///< position outside the robot's envelope
inline constexpr std::string_view speed = "SPEED";        ///< speed above the robot's limit
inline constexpr std::string_view spindle = "SPINDLE";    ///< spindle speed above the limit
inline constexpr std::string_view faulted = "FAULTED";    ///< robot in fault: send RESET first
}  // namespace nak

}  // namespace fettle::drivers::robot
