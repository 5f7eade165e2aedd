// Robot controller conformance: the rules of docs/robot-protocol.md checked over TCP.
#include "fettle/drivers/robot_conformance.hpp"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <optional>
#include <thread>
#include <utility>

#include "fettle/drivers/robot_protocol.hpp"

namespace fettle::drivers::robot {

std::string_view name(ConformanceRule::Outcome o) {
  switch (o) {
    case ConformanceRule::Outcome::pass: return "PASS";
    case ConformanceRule::Outcome::fail: return "FAIL";
    case ConformanceRule::Outcome::skipped: return "SKIP";
  }
  return "?";
}

namespace {

using Clock = std::chrono::steady_clock;
using std::chrono::milliseconds;

/// A rule's failure: what was expected and what came.
struct Failed {
  std::string detail;
};

/// One TCP connection to the robot, blocking with timeouts. Numbers its own lines and checks
/// the robot's numbering (1, 2, 3, ... per connection, docs section 2.1) on every line it reads.
class Client {
 public:
  explicit Client(const ConformanceOptions& o) : o_(o) {}
  Client(const Client&) = delete;
  Client& operator=(const Client&) = delete;
  ~Client() { close(); }

  /// A new connection: both sides count their lines from 1 again. Unless `second_client`, a robot
  /// that still holds the previous rule's connection (it answers NAK 0 BUSY at once) is tried
  /// again until the reply timeout.
  void connect(bool second_client = false) {
    const auto end = Clock::now() + milliseconds(o_.reply_timeout_ms);
    while (true) {
      open();
      if (second_client) return;
      std::string raw;
      const auto got = read_line(raw, milliseconds(50));
      if (got == Got::timeout) return;  // no BUSY: the robot is ours
      const bool busy = got == Got::closed || raw.find(" NAK 0 BUSY") != std::string::npos;
      if (!busy) throw Failed{"the robot sent '" + raw + "' on connecting, before any line of ours"};
      if (Clock::now() >= end) throw Failed{"the robot stayed busy (NAK 0 BUSY) for " + ms()};
      std::this_thread::sleep_for(milliseconds(50));
    }
  }

  void open() {
    close();
    seq_ = robot_seq_ = 0;
    buffer_.clear();
    closed_by_robot_ = false;
    fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    if (fd_ < 0) throw Failed{std::string("socket: ") + std::strerror(errno)};
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_port = htons(static_cast<std::uint16_t>(o_.port));
    if (::inet_pton(AF_INET, o_.address.c_str(), &a.sin_addr) != 1)
      throw Failed{"'" + o_.address + "' is not an IPv4 address"};
    if (::connect(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 && errno != EINPROGRESS)
      throw Failed{"cannot connect to " + peer() + ": " + std::strerror(errno)};
    pollfd p{fd_, POLLOUT, 0};
    if (::poll(&p, 1, o_.reply_timeout_ms) != 1) throw Failed{"no TCP connection to " + peer() + " within " + ms()};
    int err = 0;
    socklen_t len = sizeof err;
    ::getsockopt(fd_, SOL_SOCKET, SO_ERROR, &err, &len);
    if (err != 0) throw Failed{"cannot connect to " + peer() + ": " + std::strerror(err)};
    int one = 1;
    ::setsockopt(fd_, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
  }

  void close() {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
  }

  /// Sends `payload` with the next sequence number, LF-terminated.
  int send(const std::string& payload, const std::string& terminator = "\n") {
    seq_ = next_seq(seq_);
    send_raw(format_line(seq_, payload) + terminator);
    return seq_;
  }
  /// Sends `payload` with sequence number `seq` (the client's count moves on to it).
  void send_as(int seq, const std::string& payload) {
    seq_ = seq;
    send_raw(format_line(seq, payload) + "\n");
  }
  void send_raw(const std::string& bytes) {
    std::size_t done = 0;
    while (done < bytes.size()) {
      const auto n = ::send(fd_, bytes.data() + done, bytes.size() - done, MSG_NOSIGNAL);
      if (n > 0) {
        done += static_cast<std::size_t>(n);
        continue;
      }
      if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
        pollfd p{fd_, POLLOUT, 0};
        if (::poll(&p, 1, o_.reply_timeout_ms) == 1) continue;
      }
      throw Failed{"sending to the robot failed: " + std::string(n < 0 ? std::strerror(errno) : "closed")};
    }
  }
  [[nodiscard]] int seq() const { return seq_; }

  /// The robot's next line, parsed; a failure when none comes within the timeout, the robot
  /// closes, the line does not parse or its sequence number is not the next one.
  Line expect_line(const std::string& expecting) {
    std::string raw;
    const auto got = read_line(raw);
    if (got == Got::timeout) throw Failed{"expected " + expecting + ", got nothing within " + ms()};
    if (got == Got::closed) throw Failed{"expected " + expecting + ", the robot closed the connection"};
    auto line = parse_line(raw);
    if (!line) throw Failed{"expected " + expecting + ", got '" + raw + "' (" + line.error().message + ")"};
    const int want = next_seq(robot_seq_);
    if (line->seq != want)
      throw Failed{"the robot numbered its line '" + raw + "' " + std::to_string(line->seq) + ", expected " +
                   std::to_string(want) + " (each side counts its own lines from 1 per connection)"};
    robot_seq_ = line->seq;
    last_raw_ = raw;
    return *line;
  }

  /// Expects `ACK ref` (more fields allowed).
  Line expect_ack(int ref) {
    const auto l = expect_line("ACK " + std::to_string(ref));
    if (l.verb != Verb::ack || l.fields.empty() || l.fields[0] != std::to_string(ref))
      throw Failed{"expected ACK " + std::to_string(ref) + ", got '" + last_raw_ + "'"};
    return l;
  }
  /// Expects `NAK ref code [text]`.
  void expect_nak(int ref, std::string_view code) {
    const std::string want = "NAK " + std::to_string(ref) + " " + std::string(code);
    const auto l = expect_line(want);
    if (l.verb != Verb::nak || l.fields.size() < 2 || l.fields[0] != std::to_string(ref) || l.fields[1] != code)
      throw Failed{"expected " + want + ", got '" + last_raw_ + "'"};
  }
  /// Sends PING and expects `PONG <its sequence number>`.
  void ping() {
    const int s = send("PING");
    const auto l = expect_line("PONG " + std::to_string(s));
    if (l.verb != Verb::pong || l.fields.empty() || l.fields[0] != std::to_string(s))
      throw Failed{"expected PONG " + std::to_string(s) + ", got '" + last_raw_ + "'"};
  }
  /// Expects the robot to close the connection (lines before it are ignored).
  void expect_close(const std::string& why) {
    const auto end = Clock::now() + milliseconds(o_.reply_timeout_ms);
    std::string raw;
    while (Clock::now() < end) {
      const auto got = read_line(raw, std::chrono::duration_cast<milliseconds>(end - Clock::now()));
      if (got == Got::closed) return;
      if (got == Got::timeout) break;
    }
    throw Failed{"the robot should close the connection " + why + ", it stayed open for " + ms()};
  }

  /// Connects and says HELLO (retrying while the robot still holds the previous rule's client).
  void hello(int watchdog_ms = 3000) {
    connect();
    const int s = send("HELLO 1 " + o_.cell_id + " " + std::to_string(watchdog_ms));
    const auto l = expect_line("ACK " + std::to_string(s) + " 1 ROBOT_ID");
    if (l.verb != Verb::ack || l.fields.size() != 3 || l.fields[0] != std::to_string(s) || l.fields[1] != "1")
      throw Failed{"expected ACK " + std::to_string(s) + " 1 ROBOT_ID to HELLO, got '" + last_raw_ + "'"};
  }

  [[nodiscard]] std::string ms() const { return std::to_string(o_.reply_timeout_ms) + " ms"; }
  [[nodiscard]] std::string peer() const { return o_.address + ":" + std::to_string(o_.port); }

 private:
  enum class Got { line, timeout, closed };

  Got read_line(std::string& out, std::optional<milliseconds> timeout = std::nullopt) {
    const auto end = Clock::now() + timeout.value_or(milliseconds(o_.reply_timeout_ms));
    while (true) {
      if (const auto nl = buffer_.find('\n'); nl != std::string::npos) {
        out = buffer_.substr(0, nl);
        buffer_.erase(0, nl + 1);
        if (!out.empty() && out.back() == '\r') out.pop_back();
        if (out.empty()) continue;  // empty lines are ignored
        return Got::line;
      }
      if (closed_by_robot_) return Got::closed;
      const auto left = std::chrono::duration_cast<milliseconds>(end - Clock::now()).count();
      if (left <= 0) return Got::timeout;
      pollfd p{fd_, POLLIN, 0};
      if (::poll(&p, 1, static_cast<int>(left)) != 1) return Got::timeout;
      char chunk[512];
      const auto n = ::recv(fd_, chunk, sizeof chunk, 0);
      if (n > 0) {
        buffer_.append(chunk, static_cast<std::size_t>(n));
      } else if (n == 0 || (errno != EAGAIN && errno != EINTR)) {
        closed_by_robot_ = true;
      }
    }
  }

  const ConformanceOptions& o_;
  int fd_ = -1;
  int seq_ = 0;
  int robot_seq_ = 0;
  std::string buffer_;
  std::string last_raw_;
  bool closed_by_robot_ = false;
};

/// The rules' trajectory: three points 5 mm apart along +x from `point_mm`, tool down, segments
/// 0, 1, 0 (a segment id that comes back), spindle off.
std::vector<std::pair<std::string, std::string>> trajectory_lines(const ConformanceOptions& o) {
  std::vector<std::pair<std::string, std::string>> lines;
  const int segments[] = {0, 1, 0};
  const MoveKind kinds[] = {MoveKind::approach, MoveKind::grind, MoveKind::retract};
  for (int i = 0; i < 3; ++i) {
    TrajectoryPoint p;
    p.T_base_tool.position_mm = o.point_mm + Vec3(5.0 * i, 0.0, 0.0);
    p.T_base_tool.orientation = Quat(0.0, 1.0, 0.0, 0.0);
    p.speed_mm_s = o.speed_mm_s;
    p.segment = segments[i];
    p.kind = kinds[i];
    lines.push_back(format_point(p, i));
  }
  return lines;
}

/// TRAJ (one chunk per point), every chunk, END: the upload, acknowledged; returns the id.
int upload(Client& c, const ConformanceOptions& o, int id, const std::string& terminator = "\n") {
  const auto lines = trajectory_lines(o);
  const auto crc = crc_hex(crc32(canonical_text(lines)));
  const int n = static_cast<int>(lines.size());
  c.expect_ack(c.send("TRAJ " + std::to_string(id) + " " + std::to_string(n) + " " + std::to_string(n) + " " + crc));
  for (int i = 0; i < n; ++i) {
    const int chunk = c.send("CHUNK " + std::to_string(i + 1) + " " + std::to_string(i) + " 1", terminator);
    c.send(lines[static_cast<std::size_t>(i)].first, terminator);
    c.send(lines[static_cast<std::size_t>(i)].second, terminator);
    c.expect_ack(chunk);
  }
  c.expect_ack(c.send("END " + std::to_string(id), terminator));
  return id;
}

struct Rule {
  const char* id;
  const char* section;
  const char* rule;
  bool motion;
  std::function<void(Client&, const ConformanceOptions&)> check;
};

std::vector<Rule> rules() {
  using O = ConformanceOptions;
  return {
      {"hello", "4.1", "HELLO is answered ACK <ref> 1 <robot_id>, the robot's first line numbered 1", false,
       [](Client& c, const O&) { c.hello(); }},
      {"hello.first", "4.1", "before HELLO any other line gets NAK <its seq> STATE, and the connection stays", false,
       [](Client& c, const O& o) {
         c.connect();
         c.expect_nak(c.send("PING"), nak::state);
         const int s = c.send("HELLO 1 " + o.cell_id + " 3000");
         c.expect_ack(s);
       }},
      {"hello.twice", "6", "a second HELLO gets NAK <seq> STATE, and the connection stays", false,
       [](Client& c, const O& o) {
         c.hello();
         c.expect_nak(c.send("HELLO 1 " + o.cell_id + " 3000"), nak::state);
         c.ping();
       }},
      {"hello.version", "6", "HELLO with a version the robot does not speak gets NAK <seq> VERSION, then it closes",
       false,
       [](Client& c, const O& o) {
         c.connect();
         c.expect_nak(c.send("HELLO 2 " + o.cell_id + " 3000"), nak::version);
         c.expect_close("after NAK VERSION");
       }},
      {"ping", "4.6", "PING gets PONG <ref>", false,
       [](Client& c, const O&) {
         c.hello();
         c.ping();
       }},
      {"seq.zero", "2.1", "sequence number 0 is a syntax error: NAK 0 SYNTAX, then the robot closes", false,
       [](Client& c, const O&) {
         c.hello();
         c.send_raw("0 PING\n");
         c.expect_nak(0, nak::syntax);
         c.expect_close("after NAK SYNTAX");
       }},
      {"seq.skip", "2.1", "a skipped sequence number gets NAK <that seq> SEQ, then the robot closes", false,
       [](Client& c, const O&) {
         c.hello();
         c.send_as(c.seq() + 2, "PING");
         c.expect_nak(c.seq(), nak::seq);
         c.expect_close("after NAK SEQ");
       }},
      {"verb.unknown", "6", "an unknown verb gets NAK 0 SYNTAX, then the robot closes", false,
       [](Client& c, const O&) {
         c.hello();
         c.send("JUMP 1");
         c.expect_nak(0, nak::syntax);
         c.expect_close("after NAK SYNTAX");
       }},
      {"text.only_nak_fault", "2",
       "free text may follow only NAK and FAULT: after the fields of another verb it gets NAK 0 SYNTAX, then the "
       "robot closes",
       false,
       [](Client& c, const O&) {
         c.hello();
         c.send("PING are you there");
         c.expect_nak(0, nak::syntax);
         c.expect_close("after NAK SYNTAX");
       }},
      {"field.range", "6", "a field out of its range (HELLO watchdog_ms 5) gets NAK 0 SYNTAX, then the robot closes",
       false,
       [](Client& c, const O& o) {
         c.connect();
         c.send("HELLO 1 " + o.cell_id + " 5");
         c.expect_nak(0, nak::syntax);
         c.expect_close("after NAK SYNTAX");
       }},
      {"chunk.count_zero", "6", "CHUNK with count 0 gets NAK 0 SYNTAX, then the robot closes", false,
       [](Client& c, const O&) {
         c.hello();
         c.expect_ack(c.send("TRAJ 1 1 1 00000000"));
         c.send("CHUNK 1 0 0");
         c.expect_nak(0, nak::syntax);
         c.expect_close("after NAK SYNTAX");
       }},
      {"upload.without_traj", "6", "CHUNK, P and Q without TRAJ get NAK <seq> STATE each, and the connection stays",
       false,
       [](Client& c, const O& o) {
         c.hello();
         const auto lines = trajectory_lines(o);
         c.expect_nak(c.send("CHUNK 1 0 1"), nak::state);
         c.expect_nak(c.send(lines[0].first), nak::state);
         c.expect_nak(c.send(lines[0].second), nak::state);
         c.ping();
       }},
      {"upload.p_past_chunk", "4.2",
       "a P line after its chunk's last point (before the next CHUNK) gets NAK <seq> ORDER and the upload is "
       "discarded: END then gets NAK <seq> STATE",
       false,
       [](Client& c, const O& o) {
         c.hello();
         const auto lines = trajectory_lines(o);
         c.expect_ack(c.send("TRAJ 1 3 3 " + crc_hex(crc32(canonical_text(lines)))));
         const int chunk = c.send("CHUNK 1 0 1");
         c.send(lines[0].first);
         c.send(lines[0].second);
         c.expect_ack(chunk);
         c.expect_nak(c.send(lines[1].first), nak::order);
         c.expect_nak(c.send("END 1"), nak::state);
       }},
      {"upload.crc", "5", "END with a CRC that does not match gets NAK <seq> CRC", false,
       [](Client& c, const O& o) {
         c.hello();
         const auto lines = trajectory_lines(o);
         const auto good = crc32(canonical_text(lines));
         c.expect_ack(c.send("TRAJ 1 3 1 " + crc_hex(good ^ 1U)));
         const int chunk = c.send("CHUNK 1 0 3");
         for (const auto& [p, q] : lines) c.send(p), c.send(q);
         c.expect_ack(chunk);
         c.expect_nak(c.send("END 1"), nak::crc);
       }},
      {"upload.crlf", "1, 5", "lines ending in CR LF are accepted, and the CR is no part of the CRC's canonical text",
       false, [](Client& c, const O& o) {
         c.hello();
         upload(c, o, 1, "\r\n");
       }},
      {"line.empty", "1", "empty lines are ignored", false,
       [](Client& c, const O&) {
         c.hello();
         c.send_raw("\n\n");
         c.ping();
       }},
      {"line.bad_byte", "1", "a byte outside 0x20..0x7E gets NAK 0 SYNTAX, then the robot closes", false,
       [](Client& c, const O&) {
         c.hello();
         c.send_raw(std::to_string(c.seq() + 1) + " PI\x01NG\n");
         c.expect_nak(0, nak::syntax);
         c.expect_close("after NAK SYNTAX");
       }},
      {"line.too_long", "1", "more than 80 characters without LF make the robot close the connection", false,
       [](Client& c, const O&) {
         c.hello();
         c.send_raw(std::string(120, 'A'));
         c.expect_close("after 120 characters without LF");
       }},
      {"stop.idle", "4.5", "STOP with nothing running gets ACK", false,
       [](Client& c, const O&) {
         c.hello();
         c.expect_ack(c.send("STOP"));
       }},
      {"reset.not_faulted", "4.4",
       "RESET when not faulted gets ACK and discards the stored trajectory: RUN then gets NAK <seq> STATE", false,
       [](Client& c, const O& o) {
         c.hello();
         const int id = upload(c, o, 4);
         c.expect_ack(c.send("RESET"));
         c.expect_nak(c.send("RUN " + std::to_string(id)), nak::state);
       }},
      {"run.id", "6", "RUN with an id that is not the stored trajectory's gets NAK <seq> ID", false,
       [](Client& c, const O& o) {
         c.hello();
         upload(c, o, 5);
         c.expect_nak(c.send("RUN 6"), nak::id);
       }},
      {"busy", "1",
       "a second client gets NAK 0 BUSY as that connection's line 1 and is closed; the first is served on", false,
       [](Client& c, const O& o) {
         c.hello();
         Client second(o);
         second.connect(true);
         second.expect_nak(0, nak::busy);
         second.expect_close("after NAK BUSY");
         c.ping();
       }},
      {"watchdog", "8",
       "after watchdog_ms without a line the robot stops, sends FAULT 0 WATCHDOG and closes the connection", false,
       [](Client& c, const O&) {
         c.hello(200);
         const auto l = c.expect_line("FAULT 0 WATCHDOG within 200 ms + the reply timeout");
         if (l.verb != Verb::fault || l.fields.size() < 2 || l.fields[0] != "0" || l.fields[1] != "WATCHDOG")
           throw Failed{"expected FAULT 0 WATCHDOG"};
         c.expect_close("after its watchdog expired");
       }},
      {"run.done", "4.3", "an uploaded trajectory runs: ACK, PROG <id> 0 0, ..., DONE <id> <points>; RUN again works",
       true,
       [](Client& c, const O& o) {
         c.hello();
         const int id = upload(c, o, 7);
         for (int run = 0; run < 2; ++run) {
           c.expect_ack(c.send("RUN " + std::to_string(id)));
           Line l = c.expect_line("PROG " + std::to_string(id) + " 0 0");
           if (l.verb != Verb::prog || l.fields != std::vector<std::string>{std::to_string(id), "0", "0"})
             throw Failed{"expected PROG " + std::to_string(id) + " 0 0 first"};
           do l = c.expect_line("DONE " + std::to_string(id) + " 3");
           while (l.verb == Verb::prog);
           if (l.verb != Verb::done || l.fields != std::vector<std::string>{std::to_string(id), "3"})
             throw Failed{"expected DONE " + std::to_string(id) + " 3"};
         }
       }},
      {"run.prog", "3",
       "PROG comes whenever a point's segment differs from the previous point's, also for a segment id that "
       "comes back (segments 0, 1, 0: PROG at points 0, 1 and 2)",
       true,
       [](Client& c, const O& o) {
         c.hello();
         const int id = upload(c, o, 8);
         c.expect_ack(c.send("RUN " + std::to_string(id)));
         const std::vector<std::vector<std::string>> want{{"8", "0", "0"}, {"8", "1", "1"}, {"8", "0", "2"}};
         for (const auto& w : want) {
           const auto l = c.expect_line("PROG " + w[0] + " " + w[1] + " " + w[2]);
           if (l.verb != Verb::prog || l.fields != w) throw Failed{"expected PROG " + w[0] + " " + w[1] + " " + w[2]};
         }
         const auto done = c.expect_line("DONE 8 3");
         if (done.verb != Verb::done) throw Failed{"expected DONE 8 3 after the last PROG"};
       }},
  };
}

}  // namespace

std::vector<ConformanceRule> run_conformance(const ConformanceOptions& options,
                                             const std::function<void(const ConformanceRule&)>& on_rule) {
  std::vector<ConformanceRule> out;
  for (const auto& r : rules()) {
    ConformanceRule result{r.id, r.section, r.rule, ConformanceRule::Outcome::pass, {}};
    if (r.motion && !options.motion) {
      result.outcome = ConformanceRule::Outcome::skipped;
      result.detail = "moves the robot: run with --motion";
    } else {
      try {
        Client c(options);
        r.check(c, options);
      } catch (const Failed& f) {
        result.outcome = ConformanceRule::Outcome::fail;
        result.detail = f.detail;
      }
    }
    if (on_rule) on_rule(result);
    out.push_back(std::move(result));
  }
  return out;
}

}  // namespace fettle::drivers::robot
