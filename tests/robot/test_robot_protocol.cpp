// The robot line protocol's pure functions: grammar, limits, number formats, CRC and
// the worked example of docs/robot-protocol.md.
#include <gtest/gtest.h>

#include <fstream>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "fettle/drivers/robot_protocol.hpp"

namespace proto = fettle::drivers::robot;
using proto::Verb;

namespace {

fettle::TrajectoryPoint point(double x, double y, double z, fettle::Quat q, double speed, double rpm, int seg,
                              fettle::MoveKind kind) {
  fettle::TrajectoryPoint p;
  p.T_base_tool.position_mm = fettle::Vec3(x, y, z);
  p.T_base_tool.orientation = q;
  p.speed_mm_s = speed;
  p.spindle_rpm = rpm;
  p.segment = seg;
  p.kind = kind;
  return p;
}

std::string error_code(std::string_view line) {
  auto r = proto::parse_line(line);
  return r ? std::string("ok") : r.error().code;
}

}  // namespace

TEST(RobotCrc, StandardCheckValue) {
  // The catalogue check value of CRC-32/ISO-HDLC.
  EXPECT_EQ(proto::crc32("123456789"), 0xCBF43926u);
  EXPECT_EQ(proto::crc_hex(proto::crc32("123456789")), "CBF43926");
  EXPECT_EQ(proto::crc32(""), 0u);
  EXPECT_EQ(proto::crc32("The quick brown fox jumps over the lazy dog"), 0x414FA339u);
}

TEST(RobotCrc, IncrementalEqualsWhole) {
  EXPECT_EQ(proto::crc32("56789", proto::crc32("1234")), 0xCBF43926u);
}

TEST(RobotProtocol, ParsesEveryMessage) {
  struct Case {
    std::string line;
    Verb verb;
    std::size_t fields;
  };
  const std::vector<Case> cases = {
      {"1 HELLO 1 cell-01 3000", Verb::hello, 3},
      {"2 TRAJ 7 120 6 1A2B3C4D", Verb::traj, 4},
      {"3 CHUNK 1 0 20", Verb::chunk, 3},
      {"4 P 0 100.000 -20.500 300.000 50.000 9000 1 G", Verb::p, 8},
      {"5 Q 0 0.000000 1.000000 0.000000 -0.000001", Verb::q, 5},
      {"6 END 7", Verb::end, 1},
      {"7 RUN 7", Verb::run, 1},
      {"8 STOP", Verb::stop, 0},
      {"9 RESET", Verb::reset, 0},
      {"10 PING", Verb::ping, 0},
      {"1 ACK 1 1 IRB-6700", Verb::ack, 3},
      {"2 ACK 2", Verb::ack, 1},
      {"3 NAK 5 QUAT point 0 not unit", Verb::nak, 2},
      {"4 PONG 10", Verb::pong, 1},
      {"5 PROG 7 2 40", Verb::prog, 3},
      {"6 DONE 7 120", Verb::done, 2},
      {"7 FAULT 7 COLLISION axis 3 torque", Verb::fault, 2},
      {"99999 FAULT 0 ESTOP", Verb::fault, 2},
  };
  for (const auto& c : cases) {
    auto r = proto::parse_line(c.line);
    ASSERT_TRUE(r.ok()) << c.line << ": " << r.error().message;
    EXPECT_EQ(r->verb, c.verb) << c.line;
    EXPECT_EQ(r->fields.size(), c.fields) << c.line;
    EXPECT_EQ(proto::verb_name(r->verb), c.line.substr(c.line.find(' ') + 1, proto::verb_name(c.verb).size()));
  }
  auto nak = proto::parse_line("3 NAK 5 QUAT point 0 not unit");
  EXPECT_EQ(nak->text, "point 0 not unit");
  EXPECT_EQ(nak->fields[1], "QUAT");
  EXPECT_EQ(proto::parse_line("7 FAULT 7 COLLISION")->text, "");
}

TEST(RobotProtocol, RejectsMalformedLines) {
  const std::vector<std::string> bad = {
      "",                                               // empty
      "PING",                                           // no sequence number
      "0 PING",                                         // seq 0
      "100000 PING",                                    // seq too large
      "01 PING",                                        // leading zero
      "1",                                              // no verb
      "1 ping",                                         // lower case
      "1 JUMP",                                         // unknown verb
      "1  PING",                                        // double space
      "1 PING ",                                        // trailing space
      "1 PING 3",                                       // extra field
      "1 RUN",                                          // missing field
      "1 RUN 0",                                        // id 0
      "1 RUN 1.0",                                      // not an integer
      "1 HELLO 1 cell/01 1000",                         // bad identifier character
      "1 HELLO 1 cell 5",                               // watchdog below 10 ms
      "1 TRAJ 1 10 2 1a2b3c4d",                         // lower-case hex
      "1 TRAJ 1 10 2 1A2B3C4",                          // 7 hex digits
      "1 P 0 100.00 0.000 0.000 10.000 0 0 G",          // 2 decimals
      "1 P 0 100 0.000 0.000 10.000 0 0 G",             // no decimals
      "1 P 0 +100.000 0.000 0.000 10.000 0 0 G",        // plus sign
      "1 P 0 100000.000 0.000 0.000 10.000 0 0 G",      // 6 integer digits
      "1 P 0 1.000 0.000 0.000 -10.000 0 0 G",          // negative speed
      "1 P 0 1.000 0.000 0.000 10.000 0 0 X",           // unknown kind
      "1 P 0 1.000 0.000 0.000 10.000 0 10000 G",       // segment too large
      "1 Q 0 1.0000000 0.000000 0.000000 0.000000",     // 7 decimals
      "1 Q 0 10.000000 0.000000 0.000000 0.000000",     // two integer digits
      "1 NAK 3 crc mismatch",                           // lower-case code
      "1 NAK 3",                                        // missing code
      "1 FAULT 1 TOOLONGCODE_1234567",                  // code of 19 characters
  };
  for (const auto& l : bad) EXPECT_EQ(error_code(l), "robot.syntax") << "'" << l << "'";
}

TEST(RobotProtocol, RejectsControlAndNonAsciiBytes) {
  EXPECT_EQ(error_code(std::string("1 PI\0NG", 7)), "robot.bad_char");
  EXPECT_EQ(error_code("1 PING\t"), "robot.bad_char");
  EXPECT_EQ(error_code("1 NAK 0 STATE caf\xc3\xa9"), "robot.bad_char");
  EXPECT_EQ(error_code("1 PING\r"), "ok");  // a CR terminator is tolerated
}

TEST(RobotProtocol, LineLengthBoundary) {
  const std::string head = "12345 NAK 0 STATE ";
  const std::string at_limit = head + std::string(proto::kMaxLineChars - head.size(), 'x');
  ASSERT_EQ(at_limit.size(), 80u);
  EXPECT_EQ(error_code(at_limit), "ok");
  EXPECT_EQ(error_code(at_limit + "\r"), "ok");
  EXPECT_EQ(error_code(at_limit + "x"), "robot.too_long");
}

TEST(RobotLineSplitter, SplitsAcrossReadsAndDropsEmptyLines) {
  proto::LineSplitter s;
  std::vector<std::string> lines;
  ASSERT_TRUE(s.feed("1 PI", lines).ok());
  EXPECT_TRUE(lines.empty());
  ASSERT_TRUE(s.feed("NG\r\n\n2 PING\n3 ST", lines).ok());
  ASSERT_EQ(lines.size(), 2u);
  EXPECT_EQ(lines[0], "1 PING");
  EXPECT_EQ(lines[1], "2 PING");
  EXPECT_EQ(s.pending(), 4u);
}

TEST(RobotLineSplitter, AcceptsEightyCharactersAndRejectsEightyOne) {
  const std::string eighty(80, 'a');
  {
    proto::LineSplitter s;
    std::vector<std::string> lines;
    EXPECT_TRUE(s.feed(eighty + "\r\n", lines).ok());
    ASSERT_EQ(lines.size(), 1u);
    EXPECT_EQ(lines[0].size(), 80u);
  }
  {
    proto::LineSplitter s;
    std::vector<std::string> lines;
    auto st = s.feed(eighty + "a\n", lines);
    ASSERT_FALSE(st.ok());
    EXPECT_EQ(st.error().code, "robot.too_long");
  }
  {
    // Oversize input without any line feed, arriving in small pieces, is caught early.
    proto::LineSplitter s;
    std::vector<std::string> lines;
    fettle::Status st;
    int fed = 0;
    while (st.ok() && fed < 1000) {
      st = s.feed("xxxxxxxxxx", lines);
      fed += 10;
    }
    EXPECT_FALSE(st.ok());
    EXPECT_LE(fed, 90);
  }
}

TEST(RobotProtocol, FixedNeverWritesNegativeZero) {
  EXPECT_EQ(proto::fixed(-0.0001, 3), "0.000");
  EXPECT_EQ(proto::fixed(-0.0, 6), "0.000000");
  EXPECT_EQ(proto::fixed(-0.0006, 3), "-0.001");
  EXPECT_EQ(proto::fixed(12.3456, 3), "12.346");
  EXPECT_EQ(proto::fixed(0.70710678, 6), "0.707107");
}

TEST(RobotProtocol, WorstCasePointLinesFitTheLimit) {
  const auto q = fettle::Quat(-0.5, -0.5, -0.5, -0.5);
  const auto p = point(-99999.999, -99999.999, -99999.999, q, 9999.999, 99999, 9999, fettle::MoveKind::retract);
  ASSERT_TRUE(proto::check_point(p, proto::kMaxPoints - 1).ok());
  const auto [pl, ql] = proto::format_point(p, proto::kMaxPoints - 1);
  const auto pline = proto::format_line(proto::kMaxSeq, pl);
  const auto qline = proto::format_line(proto::kMaxSeq, ql);
  EXPECT_EQ(pline.size(), 68u) << pline;  // the budget in docs/robot-protocol.md
  EXPECT_EQ(qline.size(), 53u) << qline;
  EXPECT_TRUE(proto::parse_line(pline).ok()) << pline;
  EXPECT_TRUE(proto::parse_line(qline).ok()) << qline;
}

TEST(RobotProtocol, PointRoundTripsWithinWireResolution) {
  const fettle::Quat q = fettle::Quat(Eigen::AngleAxisd(0.3, fettle::Vec3(1, 2, 3).normalized()));
  const auto p = point(123.4564, -56.7891, 789.0, q, 42.5, 8999.6, 3, fettle::MoveKind::approach);
  const auto [pl, ql] = proto::format_point(p, 17);
  auto P = proto::parse_line(proto::format_line(1, pl));
  auto Q = proto::parse_line(proto::format_line(2, ql));
  ASSERT_TRUE(P.ok() && Q.ok());
  auto back = proto::point_from_lines(*P, *Q);
  ASSERT_TRUE(back.ok()) << back.error().message;
  EXPECT_LE((back->T_base_tool.position_mm - p.T_base_tool.position_mm).cwiseAbs().maxCoeff(), 0.0005);
  EXPECT_LE((back->T_base_tool.orientation.coeffs() - q.coeffs()).cwiseAbs().maxCoeff(), 5e-7);
  EXPECT_NEAR(back->T_base_tool.orientation.norm(), 1.0, proto::kQuatNormTolerance);
  EXPECT_EQ(back->spindle_rpm, 9000);
  EXPECT_EQ(back->segment, 3);
  EXPECT_EQ(back->kind, fettle::MoveKind::approach);
  EXPECT_DOUBLE_EQ(back->speed_mm_s, 42.5);

  // P and Q of different points do not make a point.
  auto Q2 = proto::parse_line("3 Q 18 1.000000 0.000000 0.000000 0.000000");
  EXPECT_FALSE(proto::point_from_lines(*P, *Q2).ok());
}

TEST(RobotProtocol, CheckPointNamesTheProblem) {
  const auto id = fettle::Quat::Identity();
  EXPECT_TRUE(proto::check_point(point(0, 0, 0, id, 10, 0, 0, fettle::MoveKind::grind), 0).ok());
  auto nan = proto::check_point(point(std::nan(""), 0, 0, id, 10, 0, 0, fettle::MoveKind::grind), 4);
  ASSERT_FALSE(nan.ok());
  EXPECT_EQ(nan.error().code, "robot.invalid_point");
  EXPECT_NE(nan.error().message.find("point 4"), std::string::npos);
  EXPECT_FALSE(proto::check_point(point(100000, 0, 0, id, 10, 0, 0, fettle::MoveKind::grind), 0).ok());
  EXPECT_FALSE(proto::check_point(point(0, 0, 0, id, 10000, 0, 0, fettle::MoveKind::grind), 0).ok());
  EXPECT_FALSE(proto::check_point(point(0, 0, 0, id, 10, 100000, 0, fettle::MoveKind::grind), 0).ok());
  EXPECT_FALSE(proto::check_point(point(0, 0, 0, id, 10, 0, 10000, fettle::MoveKind::grind), 0).ok());
  EXPECT_FALSE(proto::check_point(point(0, 0, 0, fettle::Quat(0, 0, 0, 0), 10, 0, 0, fettle::MoveKind::grind), 0).ok());
}

TEST(RobotProtocol, SequenceNumbersWrap) {
  EXPECT_EQ(proto::next_seq(0), 1);
  EXPECT_EQ(proto::next_seq(1), 2);
  EXPECT_EQ(proto::next_seq(99999), 1);
}

TEST(RobotProtocol, SurvivesRandomBytes) {
  std::mt19937 rng(1234);
  std::uniform_int_distribution<int> byte(0, 255), len(0, 120);
  int valid = 0;
  for (int i = 0; i < 20000; ++i) {
    std::string s(static_cast<std::size_t>(len(rng)), ' ');
    for (auto& c : s) c = static_cast<char>(byte(rng));
    if (proto::parse_line(s).ok()) ++valid;
    proto::LineSplitter splitter;
    std::vector<std::string> lines;
    (void)splitter.feed(s, lines);
    for (const auto& l : lines) EXPECT_LE(l.size(), proto::kMaxLineChars + 1);
  }
  EXPECT_EQ(valid, 0);  // random bytes never make a valid line
  // Mutations of a valid line: parse either rejects them or returns consistent fields.
  const std::string base = "12 P 3 100.000 -20.500 300.000 50.000 9000 1 G";
  for (int i = 0; i < 20000; ++i) {
    std::string s = base;
    s[static_cast<std::size_t>(rng() % s.size())] = static_cast<char>(byte(rng));
    auto r = proto::parse_line(s);
    if (r.ok() && r->verb == Verb::p) {
      ASSERT_EQ(r->fields.size(), 8u);
      EXPECT_TRUE(proto::to_double(r->fields[1]).has_value()) << s;
    }
  }
}

// The worked example in docs/robot-protocol.md ("CRC worked example") must match the code.
TEST(RobotProtocol, DocumentWorkedExampleMatchesCode) {
  std::ifstream f(std::string(FETTLE_SOURCE_DIR) + "/docs/robot-protocol.md");
  ASSERT_TRUE(f.good()) << "docs/robot-protocol.md missing";
  std::stringstream ss;
  ss << f.rdbuf();
  const std::string doc = ss.str();
  const auto begin = doc.find("<!-- crc-example-lines -->");
  ASSERT_NE(begin, std::string::npos);
  const auto fence = doc.find("```text\n", begin);
  ASSERT_NE(fence, std::string::npos);
  const auto end = doc.find("```", fence + 8);
  const std::string block = doc.substr(fence + 8, end - fence - 8);  // the wire lines, LF-terminated
  const auto crc_at = doc.find("<!-- crc-example-value -->");
  ASSERT_NE(crc_at, std::string::npos);
  const auto tick = doc.find('`', crc_at);
  const std::string documented_crc = doc.substr(tick + 1, 8);

  // The example trajectory as the doc describes it, formatted by the code.
  const fettle::Quat down(0.0, 1.0, 0.0, 0.0);  // tool axis pointing down (180 deg about x)
  const std::vector<fettle::TrajectoryPoint> pts = {
      point(450.0, -120.25, 310.0, down, 100.0, 0, 0, fettle::MoveKind::approach),
      point(450.0, -80.125, 302.5, down, 25.0, 9000, 1, fettle::MoveKind::grind)};
  std::vector<std::pair<std::string, std::string>> payloads;
  for (int i = 0; i < 2; ++i) payloads.push_back(proto::format_point(pts[static_cast<std::size_t>(i)], i));
  const std::string canonical = proto::canonical_text(payloads);

  // The doc shows the wire lines with sequence numbers; the CRC covers them without.
  std::string doc_canonical;
  std::istringstream lines(block);
  for (std::string l; std::getline(lines, l);) {
    ASSERT_TRUE(proto::parse_line(l).ok()) << l;
    doc_canonical += l.substr(l.find(' ') + 1) + "\n";
  }
  EXPECT_EQ(doc_canonical, canonical);
  EXPECT_EQ(documented_crc, proto::crc_hex(proto::crc32(canonical)));
}
