// The simulated robot controller (robot side of docs/robot-protocol.md).
#include "fettle/sim/robot.hpp"

#include <array>
#include <chrono>
#include <cmath>
#include <deque>
#include <optional>
#include <utility>
#include <vector>

#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/write.hpp>
#include <spdlog/spdlog.h>

#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/drivers/robot_protocol.hpp"
#include "../cloexec.hpp"

namespace fettle::sim {

namespace asio = boost::asio;
using asio::ip::tcp;
using Clock = std::chrono::steady_clock;
namespace proto = drivers::robot;
using proto::Verb;

struct RobotSim::Impl : std::enable_shared_from_this<Impl> {
  struct Session;

  Impl(asio::io_context& io, RobotSimOptions o)
      : io_(io), opts_(std::move(o)), acceptor_(io), log_(log::get("sim.robot")) {}

  asio::io_context& io_;
  RobotSimOptions opts_;
  tcp::acceptor acceptor_;
  std::shared_ptr<spdlog::logger> log_;
  RobotSimStats stats_;
  ExecutedHandler on_executed_;
  ExecutedHandler on_arrived_;
  SettleHandler on_settle_;
  std::shared_ptr<Session> active_;
  std::vector<std::weak_ptr<Session>> sessions_;
  int port_ = 0;
  bool open_ = false;
  std::optional<Vec3> tcp_mm_;  ///< where the simulated tool is

  void start() {
    boost::system::error_code ec;
    const auto addr = asio::ip::make_address(opts_.address, ec);
    if (ec) throw DeviceError("simulated robot: '" + opts_.address + "' is not an IP address");
    const tcp::endpoint ep(addr, static_cast<unsigned short>(opts_.port));
    acceptor_ = tcp::acceptor(io_);
    acceptor_.open(ep.protocol(), ec);
    if (!ec) detail::set_cloexec(acceptor_.native_handle());
    if (!ec) acceptor_.set_option(tcp::acceptor::reuse_address(true), ec);
    if (!ec) acceptor_.bind(ep, ec);
    if (!ec) acceptor_.listen(asio::socket_base::max_listen_connections, ec);
    if (ec)
      throw DeviceError("simulated robot: cannot listen on " + opts_.address + ":" + std::to_string(opts_.port) +
                        ": " + ec.message());
    port_ = acceptor_.local_endpoint().port();
    open_ = true;
    log_->info("simulated robot '{}' listening on {}:{}", opts_.robot_id, opts_.address, port_);
    accept();
  }

  void accept() {
    acceptor_.async_accept([self = shared_from_this()](const boost::system::error_code& ec, tcp::socket socket) {
      if (!self->open_) return;
      if (ec) {
        self->log_->warn("simulated robot: accept failed: {}", ec.message());
      } else {
        detail::set_cloexec(socket.native_handle());
        self->on_accept(std::move(socket));
      }
      self->accept();
    });
  }

  void on_accept(tcp::socket socket);
  void close();
  void drop_client();
};

// ---- one client connection ----------------------------------------------------------
struct RobotSim::Impl::Session : std::enable_shared_from_this<Session> {
  enum class St { greeting, ready, receiving, discarding, uploaded, running, faulted };

  Session(std::shared_ptr<Impl> server, tcp::socket socket)
      : server_(std::move(server)), socket_(std::move(socket)), write_timer_(socket_.get_executor()),
        watchdog_(socket_.get_executor()), exec_timer_(socket_.get_executor()) {
    boost::system::error_code ec;
    const auto ep = socket_.remote_endpoint(ec);
    peer_ = ec ? "?" : ep.address().to_string() + ":" + std::to_string(ep.port());
  }

  std::shared_ptr<Impl> server_;
  tcp::socket socket_;
  asio::steady_timer write_timer_, watchdog_, exec_timer_;
  std::string peer_;
  std::array<char, 1024> buf_{};
  proto::LineSplitter splitter_;
  struct Out {
    std::string bytes;
    Clock::time_point due;
  };
  std::deque<Out> outq_;
  bool writing_ = false;
  bool closed_ = false;
  bool close_after_flush_ = false;
  std::string close_reason_;
  int seq_in_ = 0, seq_out_ = 0;
  int watchdog_ms_ = 10000;  ///< until HELLO sets it
  St st_ = St::greeting;
  unsigned exec_token_ = 0;

  // upload
  int up_id_ = 0, up_points_ = 0, up_chunks_ = 0;
  std::string up_crc_;
  int next_chunk_ = 1, chunk_ref_ = 0, chunk_left_ = 0, next_idx_ = 0;
  std::optional<proto::Line> pending_p_;
  std::string pending_p_text_;
  std::vector<std::pair<std::string, std::string>> payloads_;
  std::vector<TrajectoryPoint> points_;

  // stored and executing
  int id_ = 0;
  std::vector<TrajectoryPoint> stored_;
  std::size_t exec_idx_ = 0;
  int exec_segment_ = -1;
  std::vector<TrajectoryPoint> executed_;

  spdlog::logger& log() { return *server_->log_; }
  RobotFaults& faults() { return server_->opts_.faults; }

  void begin() {
    boost::system::error_code ignored;
    socket_.set_option(tcp::no_delay(true), ignored);
    arm_watchdog();
    read();
  }

  // ---- output -------------------------------------------------------------------
  void send(const std::string& payload, bool is_reply) {
    if (closed_) return;
    seq_out_ = proto::next_seq(seq_out_);
    std::string line = proto::format_line(seq_out_, payload);
    if (is_reply && faults().garbage_reply) {
      faults().garbage_reply = false;
      log().warn("simulated robot: fault injection: garbage instead of '{}'", line);
      line = "\x01\x02 garbage \xff\xfe";
    } else if (is_reply && faults().oversize_reply) {
      faults().oversize_reply = false;
      log().warn("simulated robot: fault injection: oversize line instead of '{}'", line);
      line = std::to_string(seq_out_) + " NAK 0 STATE " + std::string(200, 'X');
    }
    log().trace("sim robot -> {}", line);
    line += '\n';
    const int delay = is_reply ? faults().reply_delay_ms : 0;
    outq_.push_back(Out{std::move(line), Clock::now() + std::chrono::milliseconds(delay)});
    flush();
  }

  void reply_ack(int ref, const std::string& extra = {}) {
    send("ACK " + std::to_string(ref) + (extra.empty() ? "" : " " + extra), true);
  }

  void nak(int ref, std::string_view code, const std::string& text) {
    ++server_->stats_.naks;
    std::string payload = "NAK " + std::to_string(ref) + " " + std::string(code);
    if (!text.empty()) payload += " " + text;
    // Keep the line within the limit: 5 digits of sequence number and a space.
    if (payload.size() > proto::kMaxLineChars - 6) payload.resize(proto::kMaxLineChars - 6);
    while (!payload.empty() && payload.back() == ' ') payload.pop_back();
    log().info("simulated robot: NAK {} {}{}{}", ref, code, text.empty() ? "" : ": ", text);
    send(payload, true);
    if (st_ == St::receiving) st_ = St::discarding;
  }

  /// A NAK for a point outside the robot's limits (counted apart: Fettle validates before upload).
  void limit_nak(int ref, std::string_view code, const std::string& text) {
    ++server_->stats_.limit_naks;
    nak(ref, code, text);
  }

  void flush() {
    if (writing_ || closed_) return;
    if (outq_.empty()) {
      if (close_after_flush_) close(close_reason_);
      return;
    }
    writing_ = true;
    const auto now = Clock::now();
    if (outq_.front().due > now) {
      write_timer_.expires_at(outq_.front().due);
      write_timer_.async_wait([self = shared_from_this()](const boost::system::error_code& e) {
        if (e || self->closed_) return;
        self->write_front();
      });
      return;
    }
    write_front();
  }

  void write_front() {
    asio::async_write(socket_, asio::buffer(outq_.front().bytes),
                      [self = shared_from_this()](const boost::system::error_code& ec, std::size_t) {
                        if (self->closed_) return;
                        if (ec) {
                          self->close("write failed: " + ec.message());
                          return;
                        }
                        self->outq_.pop_front();
                        self->writing_ = false;
                        self->flush();
                      });
  }

  void close_after_flush(std::string reason) {
    close_after_flush_ = true;
    close_reason_ = std::move(reason);
    flush();
  }

  void close(const std::string& reason, bool garbage = false) {
    if (closed_) return;
    closed_ = true;
    if (garbage) {
      ++server_->stats_.closed_for_garbage;
      log().warn("simulated robot: closing connection from {}: {}", peer_, reason);
    } else {
      log().info("simulated robot: connection from {} closed: {}", peer_, reason);
    }
    server_->stats_.last_close_reason = reason;
    if (st_ == St::running) halt("connection closed");
    boost::system::error_code ignored;
    socket_.shutdown(tcp::socket::shutdown_both, ignored);
    socket_.close(ignored);
    write_timer_.cancel();
    watchdog_.cancel();
    exec_timer_.cancel();
    if (server_->active_.get() == this) server_->active_.reset();
  }

  // ---- input --------------------------------------------------------------------
  void read() {
    socket_.async_read_some(asio::buffer(buf_), [self = shared_from_this()](const boost::system::error_code& ec,
                                                                            std::size_t n) {
      if (self->closed_) return;
      if (ec) {
        self->close(ec == asio::error::eof ? "client closed the connection" : "read failed: " + ec.message());
        return;
      }
      std::vector<std::string> lines;
      const auto st = self->splitter_.feed(std::string_view(self->buf_.data(), n), lines);
      for (const auto& l : lines) {
        if (self->closed_ || self->close_after_flush_) return;
        self->on_line(l);
      }
      if (!st) {
        self->close("oversize input: " + st.error().message, true);
        return;
      }
      if (!self->closed_) self->read();
    });
  }

  void arm_watchdog() {
    watchdog_.expires_after(std::chrono::milliseconds(watchdog_ms_));
    watchdog_.async_wait([self = shared_from_this()](const boost::system::error_code& e) {
      if (e || self->closed_) return;
      // Motion stops first; the FAULT tells a client that is still listening why the line goes.
      const int running = self->st_ == St::running ? self->id_ : 0;
      if (self->st_ == St::running) self->halt("watchdog");
      self->st_ = St::faulted;
      self->send("FAULT " + std::to_string(running) + " WATCHDOG no line for " + std::to_string(self->watchdog_ms_) +
                     " ms",
                 false);
      self->close_after_flush("watchdog: no line from the client for " + std::to_string(self->watchdog_ms_) + " ms");
    });
  }

  void on_line(const std::string& text) {
    log().trace("sim robot <- {}", text);
    auto parsed = proto::parse_line(text);
    if (!parsed) {
      // Tell the client why (ref 0: its line could not be read), then hang up.
      send("NAK 0 SYNTAX", false);
      close_after_flush("garbage input: " + parsed.error().message);
      ++server_->stats_.closed_for_garbage;
      log().warn("simulated robot: closing connection from {}: {}", peer_, parsed.error().message);
      return;
    }
    const auto& line = *parsed;
    arm_watchdog();
    if (line.seq != proto::next_seq(seq_in_)) {
      nak(line.seq, proto::nak::seq, "expected " + std::to_string(proto::next_seq(seq_in_)));
      close_after_flush("sequence number " + std::to_string(line.seq) + " instead of " +
                        std::to_string(proto::next_seq(seq_in_)));
      return;
    }
    seq_in_ = line.seq;
    if (!faults().nak_verb.empty() && faults().nak_verb == proto::verb_name(line.verb)) {
      faults().nak_verb.clear();
      nak(line.seq, faults().nak_code, "injected");
      if (line.verb == Verb::hello) close_after_flush("HELLO refused (fault injection)");
      return;
    }
    if (st_ == St::greeting && line.verb != Verb::hello) {
      nak(line.seq, proto::nak::state, "send HELLO first");
      return;
    }
    switch (line.verb) {
      case Verb::hello: return on_hello(line);
      case Verb::ping:
        if (!faults().ignore_pings) send("PONG " + std::to_string(line.seq), true);
        return;
      case Verb::traj: return on_traj(line);
      case Verb::chunk: return on_chunk(line);
      case Verb::p: return on_p(line, text);
      case Verb::q: return on_q(line, text);
      case Verb::end: return on_end(line);
      case Verb::run: return on_run(line);
      case Verb::stop: return on_stop(line);
      case Verb::reset: return on_reset(line);
      default: nak(line.seq, proto::nak::state, std::string(proto::verb_name(line.verb)) + " is sent by the robot");
    }
  }

  static int num(const std::string& s) { return proto::to_int(s).value_or(-1); }

  void on_hello(const proto::Line& l) {
    if (st_ != St::greeting) return nak(l.seq, proto::nak::state, "HELLO already done");
    if (num(l.fields[0]) != proto::kProtocolVersion) {
      nak(l.seq, proto::nak::version, "robot speaks version " + std::to_string(proto::kProtocolVersion));
      return close_after_flush("protocol version " + l.fields[0] + " not supported");
    }
    if (!server_->opts_.expected_cell_id.empty() && l.fields[1] != server_->opts_.expected_cell_id) {
      nak(l.seq, proto::nak::cell, "expected " + server_->opts_.expected_cell_id);
      return close_after_flush("cell id " + l.fields[1] + " is not " + server_->opts_.expected_cell_id);
    }
    watchdog_ms_ = num(l.fields[2]);
    arm_watchdog();
    st_ = St::ready;
    log().info("simulated robot: HELLO from cell '{}' at {} (watchdog {} ms)", l.fields[1], peer_, watchdog_ms_);
    reply_ack(l.seq, std::to_string(proto::kProtocolVersion) + " " + server_->opts_.robot_id);
  }

  void on_traj(const proto::Line& l) {
    if (st_ == St::running) return nak(l.seq, proto::nak::busy, "a trajectory is running");
    if (st_ == St::faulted) return nak(l.seq, proto::nak::faulted, "send RESET first");
    const int points = num(l.fields[1]);
    const int chunks = num(l.fields[2]);
    if (chunks > points) return nak(l.seq, proto::nak::count, "more chunks than points");
    up_id_ = num(l.fields[0]);
    up_points_ = points;
    up_chunks_ = chunks;
    up_crc_ = l.fields[3];
    next_chunk_ = 1;
    chunk_left_ = 0;
    next_idx_ = 0;
    pending_p_.reset();
    payloads_.clear();
    points_.clear();
    stored_.clear();
    st_ = St::receiving;
    reply_ack(l.seq);
  }

  void on_chunk(const proto::Line& l) {
    if (st_ == St::discarding) return;
    if (st_ != St::receiving) return nak(l.seq, proto::nak::state, "no upload in progress (send TRAJ)");
    const int k = num(l.fields[0]);
    if (faults().disconnect_at_chunk > 0 && faults().disconnect_at_chunk == k) {
      faults().disconnect_at_chunk = 0;
      return close("fault injection: disconnect at chunk " + std::to_string(k));
    }
    if (chunk_left_ > 0) return nak(l.seq, proto::nak::order, "previous chunk incomplete");
    if (k != next_chunk_) return nak(l.seq, proto::nak::order, "expected chunk " + std::to_string(next_chunk_));
    if (k > up_chunks_) return nak(l.seq, proto::nak::count, "only " + std::to_string(up_chunks_) + " chunks announced");
    if (num(l.fields[1]) != next_idx_) return nak(l.seq, proto::nak::order, "expected first point " + std::to_string(next_idx_));
    const int count = num(l.fields[2]);
    if (next_idx_ + count > up_points_) return nak(l.seq, proto::nak::count, "chunk goes past the announced points");
    chunk_ref_ = l.seq;
    chunk_left_ = count;
  }

  static std::string payload_of(const std::string& text) {
    const auto sp = text.find(' ');
    std::string s = text.substr(sp + 1);
    if (!s.empty() && s.back() == '\r') s.pop_back();
    return s;
  }

  void on_p(const proto::Line& l, const std::string& text) {
    if (st_ == St::discarding) return;
    if (st_ != St::receiving) return nak(l.seq, proto::nak::state, "no upload in progress (send TRAJ)");
    if (chunk_left_ == 0) return nak(l.seq, proto::nak::order, "P outside a chunk (send CHUNK first)");
    if (pending_p_) return nak(l.seq, proto::nak::order, "Q expected");
    if (num(l.fields[0]) != next_idx_) return nak(l.seq, proto::nak::order, "expected point " + std::to_string(next_idx_));
    const auto& env = server_->opts_.envelope;
    for (std::size_t i = 0; i < 3; ++i) {
      const double v = *proto::to_double(l.fields[i + 1]);
      if (v < env.min_mm[i] || v > env.max_mm[i])
        return limit_nak(l.seq, proto::nak::envelope, std::string("point ") + l.fields[0] + " " + "xyz"[i] + " " +
                                                    l.fields[i + 1] + " mm");
    }
    if (*proto::to_double(l.fields[4]) > env.max_speed_mm_s)
      return limit_nak(l.seq, proto::nak::speed, "point " + l.fields[0] + " " + l.fields[4] + " mm/s");
    if (num(l.fields[5]) > env.max_spindle_rpm)
      return limit_nak(l.seq, proto::nak::spindle, "point " + l.fields[0] + " " + l.fields[5] + " rpm");
    pending_p_ = l;
    pending_p_text_ = payload_of(text);
  }

  void on_q(const proto::Line& l, const std::string& text) {
    if (st_ == St::discarding) return;
    if (st_ != St::receiving) return nak(l.seq, proto::nak::state, "no upload in progress (send TRAJ)");
    if (!pending_p_) return nak(l.seq, proto::nak::order, "Q without its P line");
    auto pt = proto::point_from_lines(*pending_p_, l);
    if (!pt) return nak(l.seq, proto::nak::order, pt.error().message);
    const double norm = pt->T_base_tool.orientation.coeffs().norm();
    if (std::abs(norm - 1.0) > proto::kQuatNormTolerance)
      return limit_nak(l.seq, proto::nak::quat, "point " + l.fields[0] + " |q| = " + proto::fixed(norm, 6));
    points_.push_back(*pt);
    payloads_.emplace_back(pending_p_text_, payload_of(text));
    pending_p_.reset();
    ++next_idx_;
    if (--chunk_left_ == 0) {
      ++next_chunk_;
      reply_ack(chunk_ref_);
    }
  }

  void on_end(const proto::Line& l) {
    if (st_ != St::receiving) return nak(l.seq, proto::nak::state, "no upload in progress");
    if (num(l.fields[0]) != up_id_) return nak(l.seq, proto::nak::id, "uploading " + std::to_string(up_id_));
    if (next_idx_ != up_points_ || next_chunk_ != up_chunks_ + 1 || chunk_left_ != 0)
      return nak(l.seq, proto::nak::count, "got " + std::to_string(next_idx_) + " of " + std::to_string(up_points_) +
                                               " points");
    const auto crc = proto::crc_hex(proto::crc32(proto::canonical_text(payloads_)));
    if (crc != up_crc_) return nak(l.seq, proto::nak::crc, "computed " + crc + ", announced " + up_crc_);
    id_ = up_id_;
    stored_ = std::move(points_);
    points_.clear();
    payloads_.clear();
    st_ = St::uploaded;
    ++server_->stats_.trajectories_received;
    log().info("simulated robot: trajectory {} received ({} points, CRC {})", id_, stored_.size(), crc);
    reply_ack(l.seq);
  }

  void on_run(const proto::Line& l) {
    if (st_ == St::faulted) return nak(l.seq, proto::nak::faulted, "send RESET first");
    if (st_ == St::running) return nak(l.seq, proto::nak::busy, "already running");
    if (st_ != St::uploaded) return nak(l.seq, proto::nak::state, "no trajectory uploaded");
    if (num(l.fields[0]) != id_) return nak(l.seq, proto::nak::id, "trajectory " + std::to_string(id_) + " is loaded");
    reply_ack(l.seq);
    st_ = St::running;
    ++server_->stats_.runs_started;
    exec_idx_ = 0;
    exec_segment_ = -1;
    executed_.clear();
    if (!server_->tcp_mm_) server_->tcp_mm_ = stored_.front().T_base_tool.position_mm;
    step();
  }

  void step() {
    if (exec_idx_ == stored_.size()) {
      if (server_->on_arrived_) {  // the simulated world sees the robot there before DONE goes out
        Trajectory t;
        t.points = executed_;
        server_->on_arrived_(t);
      }
      if (server_->on_settle_) {
        Trajectory t;
        t.points = executed_;
        const unsigned token = exec_token_;
        std::weak_ptr<Session> weak = shared_from_this();
        auto executor = exec_timer_.get_executor();
        server_->on_settle_(t, [weak, token, executor] {
          asio::post(executor, [weak, token] {
            auto self = weak.lock();
            if (!self || self->closed_ || token != self->exec_token_ || self->st_ != St::running) return;
            self->finish_run();
          });
        });
        return;
      }
      finish_run();
      return;
    }
    if (faults().fault_at_point >= 0 && static_cast<std::size_t>(faults().fault_at_point) == exec_idx_) {
      faults().fault_at_point = -1;
      send("FAULT " + std::to_string(id_) + " " + faults().fault_code + " injected at point " +
               std::to_string(exec_idx_), false);
      log().warn("simulated robot: fault injection: FAULT {} at point {}", faults().fault_code, exec_idx_);
      st_ = St::faulted;
      hand_over();
      stored_.clear();
      return;
    }
    const auto& pt = stored_[exec_idx_];
    if (pt.segment != exec_segment_) {
      exec_segment_ = pt.segment;
      send("PROG " + std::to_string(id_) + " " + std::to_string(pt.segment) + " " + std::to_string(exec_idx_), false);
    }
    const double dist = (pt.T_base_tool.position_mm - *server_->tcp_mm_).norm();
    double seconds = pt.speed_mm_s > 0.0 ? dist / pt.speed_mm_s : 0.0;
    seconds = server_->opts_.speedup > 0.0 ? seconds / server_->opts_.speedup : 0.0;
    const unsigned token = ++exec_token_;
    exec_timer_.expires_after(std::chrono::microseconds(static_cast<long long>(seconds * 1e6)));
    exec_timer_.async_wait([self = shared_from_this(), token](const boost::system::error_code& e) {
      if (e || self->closed_ || token != self->exec_token_ || self->st_ != St::running) return;
      const auto& p = self->stored_[self->exec_idx_];
      self->executed_.push_back(p);
      self->server_->tcp_mm_ = p.T_base_tool.position_mm;
      ++self->exec_idx_;
      self->step();
    });
  }

  void finish_run() {
    send("DONE " + std::to_string(id_) + " " + std::to_string(stored_.size()), false);
    ++server_->stats_.trajectories_executed;
    st_ = St::uploaded;
    hand_over();
  }

  void hand_over() {
    if (!server_->on_executed_) return;
    Trajectory t;
    t.part_id = "trajectory " + std::to_string(id_);
    t.points = executed_;
    server_->on_executed_(t);
  }

  /// Stops motion where it is (STOP, RESET or a lost connection).
  void halt(const std::string& why) {
    ++exec_token_;
    exec_timer_.cancel();
    ++server_->stats_.trajectories_halted;
    server_->stats_.last_halt_reason = why;
    log().info("simulated robot: trajectory {} halted after {} of {} points ({})", id_, executed_.size(),
               stored_.size(), why);
    hand_over();
  }

  void on_stop(const proto::Line& l) {
    if (st_ == St::running) halt("STOP");
    stored_.clear();
    if (st_ != St::faulted && st_ != St::greeting) st_ = St::ready;
    reply_ack(l.seq);
  }

  void on_reset(const proto::Line& l) {
    if (st_ == St::running) halt("RESET");
    stored_.clear();
    st_ = St::ready;
    reply_ack(l.seq);
  }
};

void RobotSim::Impl::on_accept(tcp::socket socket) {
  ++stats_.connections;
  auto s = std::make_shared<Session>(shared_from_this(), std::move(socket));
  sessions_.push_back(s);
  std::erase_if(sessions_, [](const auto& w) { return w.expired(); });
  if (active_ && !active_->closed_) {
    log_->warn("simulated robot: refusing a second client from {} (one client at a time)", s->peer_);
    s->send("NAK 0 BUSY another client is connected", false);
    s->close_after_flush("busy");
    return;
  }
  active_ = s;
  log_->info("simulated robot: client connected from {}", s->peer_);
  s->begin();
}

void RobotSim::Impl::close() {
  open_ = false;
  boost::system::error_code ignored;
  acceptor_.close(ignored);
  for (auto& w : sessions_)
    if (auto s = w.lock()) s->close("simulated robot switched off");  // s keeps it alive meanwhile
  sessions_.clear();
  active_.reset();
}

void RobotSim::Impl::drop_client() {
  if (auto s = active_) s->close("dropped by the simulator");
}

RobotSim::RobotSim(asio::io_context& io, RobotSimOptions options)
    : impl_(std::make_shared<Impl>(io, std::move(options))) {}
RobotSim::~RobotSim() {
  impl_->on_executed_ = nullptr;
  impl_->on_arrived_ = nullptr;
  impl_->on_settle_ = nullptr;
  impl_->close();
}
void RobotSim::start() { impl_->start(); }
void RobotSim::close() { impl_->close(); }
void RobotSim::drop_client() { impl_->drop_client(); }
int RobotSim::port() const { return impl_->port_; }
void RobotSim::set_faults(const RobotFaults& faults) { impl_->opts_.faults = faults; }
const RobotFaults& RobotSim::faults() const { return impl_->opts_.faults; }
void RobotSim::on_executed(ExecutedHandler h) { impl_->on_executed_ = std::move(h); }
void RobotSim::on_arrived(ExecutedHandler h) { impl_->on_arrived_ = std::move(h); }
void RobotSim::on_settle(SettleHandler h) { impl_->on_settle_ = std::move(h); }
const RobotSimStats& RobotSim::stats() const { return impl_->stats_; }

}  // namespace fettle::sim
