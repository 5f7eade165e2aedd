// Robot controller link: asynchronous client of docs/robot-protocol.md on Boost.Asio.
#include <algorithm>
#include <array>
#include <cctype>
#include <chrono>
#include <deque>
#include <optional>
#include <utility>
#include <vector>

#include <boost/asio/connect.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/write.hpp>
#include <spdlog/spdlog.h>

#include "fettle/core/log.hpp"
#include "fettle/drivers/robot_link.hpp"
#include "fettle/drivers/robot_protocol.hpp"

namespace fettle::drivers {

namespace asio = boost::asio;
using asio::ip::tcp;
using Ms = std::chrono::milliseconds;
namespace proto = robot;

std::string_view to_string(RobotState s) {
  switch (s) {
    case RobotState::disconnected: return "disconnected";
    case RobotState::connecting: return "connecting";
    case RobotState::ready: return "ready";
    case RobotState::uploading: return "uploading";
    case RobotState::uploaded: return "uploaded";
    case RobotState::running: return "running";
    case RobotState::stopping: return "stopping";
    case RobotState::faulted: return "faulted";
  }
  return "?";
}

RobotLinkOptions RobotLinkOptions::from_config(const config::RobotSection& s) {
  RobotLinkOptions o;
  o.address = s.address;
  o.port = s.port;
  o.cell_id = s.cell_id;
  o.connect_timeout_ms = s.reply_timeout_ms;
  o.reply_timeout_ms = s.reply_timeout_ms;
  o.ping_period_ms = s.ping_period_ms;
  o.missed_pings = s.missed_pings;
  o.chunk_points = s.chunk_points;
  o.run_timeout_ms = s.run_timeout_ms;
  o.reconnect_initial_ms = s.reconnect_initial_ms;
  o.reconnect_max_ms = s.reconnect_max_ms;
  return o;
}

namespace {

std::string lower(std::string_view s) {
  std::string out(s);
  std::transform(out.begin(), out.end(), out.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return out;
}

Error err(std::string code, std::string message, ErrorKind kind) {
  return Error{std::move(code), std::move(message), kind};
}

}  // namespace

struct RobotLink::Impl : std::enable_shared_from_this<Impl> {
  enum class Req { hello, traj, chunk, end, run, stop, reset };

  struct Pending {
    Req req;
    int ref;  ///< seq of the line the reply must refer to
  };

  Impl(asio::io_context& io, RobotLinkOptions o)
      : io_(io), opts_(std::move(o)), socket_(io), reply_timer_(io), ping_timer_(io), run_timer_(io),
        reconnect_timer_(io), log_(log::get("robot")) {
    opts_.chunk_points = std::max(1, opts_.chunk_points);
    opts_.missed_pings = std::max(1, opts_.missed_pings);
    backoff_ms_ = opts_.reconnect_initial_ms;
  }

  asio::io_context& io_;
  RobotLinkOptions opts_;
  tcp::socket socket_;
  asio::steady_timer reply_timer_, ping_timer_, run_timer_, reconnect_timer_;
  std::shared_ptr<spdlog::logger> log_;

  RobotState state_ = RobotState::disconnected;
  Error last_error_;
  std::string robot_id_;
  int connections_ = 0;
  bool active_ = false;  ///< start() called and not shut down
  unsigned generation_ = 0;  ///< bumps on every close: stale handlers check it
  int backoff_ms_ = 100;
  unsigned reply_token_ = 0;

  // wire
  std::array<char, 1024> read_buf_{};
  proto::LineSplitter splitter_;
  std::deque<std::string> write_queue_;
  bool writing_ = false;
  int seq_out_ = 0;       ///< last seq sent
  int seq_in_ = 0;        ///< last seq received
  int missed_ = 0;        ///< PINGs sent without a PONG since

  // requests
  std::optional<Pending> pending_;
  Handler op_done_;    ///< upload / run / reset
  Handler stop_done_;
  std::optional<RobotState> state_before_stop_;

  // upload
  std::vector<std::pair<std::string, std::string>> payloads_;
  int traj_id_ = 0;
  int next_traj_id_ = 1;
  int chunk_ = 0;  ///< chunks acknowledged so far
  int chunks_ = 0;

  StateHandler on_state_;
  ProgressHandler on_progress_;

  // ---- state --------------------------------------------------------------------
  void set_state(RobotState s, const Error& cause = {}) {
    if (!cause.code.empty()) last_error_ = cause;
    if (s == state_ && cause.code.empty()) return;
    log_->debug("robot link: {} -> {}{}{}", to_string(state_), to_string(s), cause.code.empty() ? "" : ": ",
                cause.message);
    state_ = s;
    if (on_state_) on_state_(s, cause);
  }

  bool connected() const {
    return state_ != RobotState::disconnected && state_ != RobotState::connecting;
  }

  static void complete(Handler& h, Status s) {
    if (!h) return;
    auto f = std::move(h);
    h = nullptr;
    f(std::move(s));
  }

  // ---- connection ---------------------------------------------------------------
  void start() {
    if (active_) return;
    active_ = true;
    connect();
  }

  void connect() {
    if (!active_) return;
    ++generation_;
    set_state(RobotState::connecting);
    boost::system::error_code ec;
    const auto addr = asio::ip::make_address(opts_.address, ec);
    if (ec) {
      link_down(err("robot.address", "robot address '" + opts_.address + "' is not an IP address: check [robot] address", ErrorKind::config));
      return;
    }
    socket_ = tcp::socket(io_);
    splitter_ = proto::LineSplitter{};
    write_queue_.clear();
    writing_ = false;
    seq_out_ = 0;
    seq_in_ = 0;
    missed_ = 0;
    const unsigned gen = generation_;
    arm_reply_timer(opts_.connect_timeout_ms, "connect to and HELLO from the robot at " + endpoint_text());
    socket_.async_connect(tcp::endpoint(addr, static_cast<unsigned short>(opts_.port)),
                          [self = shared_from_this(), gen](const boost::system::error_code& e) {
                            if (gen != self->generation_) return;
                            self->on_connected(e);
                          });
  }

  std::string endpoint_text() const { return opts_.address + ":" + std::to_string(opts_.port); }

  void on_connected(const boost::system::error_code& ec) {
    if (ec) {
      link_down(err("robot.connect_failed", "cannot connect to the robot controller at " + endpoint_text() + ": " +
                                                ec.message() + " (is the robot program running and listening?)", ErrorKind::unavailable));
      return;
    }
    boost::system::error_code ignored;
    socket_.set_option(tcp::no_delay(true), ignored);
    read();
    const int watchdog_ms = std::min(99999, opts_.ping_period_ms * opts_.missed_pings);
    pending_ = Pending{Req::hello, send("HELLO " + std::to_string(proto::kProtocolVersion) + " " + opts_.cell_id +
                                        " " + std::to_string(watchdog_ms))};
  }

  /// Closes the connection after a fault: every pending handler fails with `cause`,
  /// state disconnected, then a reconnect after the backoff.
  void link_down(const Error& cause) {
    log_->warn("robot link down: {}", cause.message);
    close_socket();
    set_state(RobotState::disconnected, cause);
    fail_all(cause);
    if (active_ && opts_.reconnect) {
      const int delay = backoff_ms_;
      backoff_ms_ = std::min(opts_.reconnect_max_ms, std::max(1, backoff_ms_ * 2));
      const unsigned gen = generation_;
      reconnect_timer_.expires_after(Ms(delay));
      reconnect_timer_.async_wait([self = shared_from_this(), gen](const boost::system::error_code& e) {
        if (e || gen != self->generation_) return;
        self->connect();
      });
    }
  }

  void close_socket() {
    ++generation_;
    boost::system::error_code ignored;
    socket_.shutdown(tcp::socket::shutdown_both, ignored);
    socket_.close(ignored);
    cancel_reply_timer();
    ping_timer_.cancel();
    run_timer_.cancel();
    reconnect_timer_.cancel();
    write_queue_.clear();
    writing_ = false;
    pending_.reset();
    state_before_stop_.reset();
    payloads_.clear();
  }

  void fail_all(const Error& cause) {
    complete(op_done_, cause);
    complete(stop_done_, cause);
  }

  void shutdown() {
    active_ = false;
    close_socket();
    const Error cause = err("robot.shutdown", "the robot link was shut down", ErrorKind::cancelled);
    set_state(RobotState::disconnected, cause);
    fail_all(cause);
  }

  // ---- wire ---------------------------------------------------------------------
  /// Sends one payload as a line; returns its sequence number.
  int send(const std::string& payload) {
    seq_out_ = proto::next_seq(seq_out_);
    std::string line = proto::format_line(seq_out_, payload);
    log_->trace("robot <- {}", line);
    line += '\n';
    enqueue(std::move(line));
    return seq_out_;
  }

  void enqueue(std::string bytes) {
    write_queue_.push_back(std::move(bytes));
    if (!writing_) write_next();
  }

  void write_next() {
    if (write_queue_.empty()) {
      writing_ = false;
      return;
    }
    writing_ = true;
    const unsigned gen = generation_;
    asio::async_write(socket_, asio::buffer(write_queue_.front()),
                      [self = shared_from_this(), gen](const boost::system::error_code& ec, std::size_t) {
                        if (gen != self->generation_) return;
                        if (ec) {
                          self->link_down(err("robot.connection_lost", "writing to the robot failed: " + ec.message(), ErrorKind::link_lost));
                          return;
                        }
                        self->write_queue_.pop_front();
                        self->write_next();
                      });
  }

  void read() {
    const unsigned gen = generation_;
    socket_.async_read_some(asio::buffer(read_buf_),
                            [self = shared_from_this(), gen](const boost::system::error_code& ec, std::size_t n) {
                              if (gen != self->generation_) return;
                              self->on_read(ec, n);
                            });
  }

  void on_read(const boost::system::error_code& ec, std::size_t n) {
    if (ec) {
      link_down(err("robot.connection_lost", ec == asio::error::eof
                                                 ? "the robot controller closed the connection"
                                                 : "reading from the robot failed: " + ec.message(), ErrorKind::link_lost));
      return;
    }
    std::vector<std::string> lines;
    const auto st = splitter_.feed(std::string_view(read_buf_.data(), n), lines);
    const unsigned gen = generation_;
    for (const auto& l : lines) {
      handle_line(l);
      if (gen != generation_) return;  // the line closed the connection
    }
    if (!st) {
      link_down(err("robot.protocol", "robot sent garbage: " + st.error().message, ErrorKind::link_lost));
      return;
    }
    read();
  }

  void handle_line(const std::string& text) {
    log_->trace("robot -> {}", text);
    auto parsed = proto::parse_line(text);
    if (!parsed) {
      link_down(err("robot.protocol", "robot sent an invalid line (" + parsed.error().message + ")", ErrorKind::link_lost));
      return;
    }
    const auto& line = *parsed;
    if (line.seq != proto::next_seq(seq_in_)) {
      link_down(err("robot.seq", "robot line has sequence number " + std::to_string(line.seq) + ", expected " +
                                     std::to_string(proto::next_seq(seq_in_)) + " (a line was lost)", ErrorKind::link_lost));
      return;
    }
    seq_in_ = line.seq;
    switch (line.verb) {
      case proto::Verb::pong: missed_ = 0; return;
      case proto::Verb::ack: on_ack(line); return;
      case proto::Verb::nak: on_nak(line); return;
      case proto::Verb::prog: on_prog(line); return;
      case proto::Verb::done: on_done(line); return;
      case proto::Verb::fault: on_fault(line); return;
      default:
        link_down(err("robot.protocol", "robot sent " + std::string(proto::verb_name(line.verb)) +
                                            ", which only fettle may send", ErrorKind::link_lost));
        return;
    }
  }

  // ---- timers -------------------------------------------------------------------
  void arm_reply_timer(int ms, std::string what) {
    const unsigned gen = generation_;
    const unsigned token = ++reply_token_;
    reply_timer_.expires_after(Ms(ms));
    reply_timer_.async_wait([self = shared_from_this(), gen, token, ms, what = std::move(what)](const boost::system::error_code& e) {
      // The token catches an expiry already queued when the reply arrived.
      if (e || gen != self->generation_ || token != self->reply_token_) return;
      self->link_down(err("robot.reply_timeout",
                          "no reply from the robot within " + std::to_string(ms) + " ms waiting for " + what, ErrorKind::link_lost));
    });
  }

  void cancel_reply_timer() {
    ++reply_token_;
    reply_timer_.cancel();
  }

  void await(Req r, int ref, std::string what) {
    pending_ = Pending{r, ref};
    arm_reply_timer(opts_.reply_timeout_ms, std::move(what));
  }

  void schedule_ping() {
    const unsigned gen = generation_;
    ping_timer_.expires_after(Ms(opts_.ping_period_ms));
    ping_timer_.async_wait([self = shared_from_this(), gen](const boost::system::error_code& e) {
      if (e || gen != self->generation_) return;
      if (self->missed_ >= self->opts_.missed_pings) {
        self->link_down(err("robot.ping_timeout", "robot did not answer " + std::to_string(self->missed_) +
                                                      " PINGs in a row (period " +
                                                      std::to_string(self->opts_.ping_period_ms) + " ms)", ErrorKind::link_lost));
        return;
      }
      ++self->missed_;
      self->send("PING");
      self->schedule_ping();
    });
  }

  // ---- replies ------------------------------------------------------------------
  bool matches(const proto::Line& line) const {
    return pending_ && proto::to_int(line.fields[0]).value_or(-1) == pending_->ref;
  }

  void on_ack(const proto::Line& line) {
    if (!matches(line)) {
      log_->debug("robot: ignoring ACK {} (no request waits for it)", line.fields[0]);
      return;
    }
    const Req r = pending_->req;
    pending_.reset();
    cancel_reply_timer();
    switch (r) {
      case Req::hello:
        if (line.fields.size() != 3) {
          link_down(err("robot.protocol", "robot's HELLO ACK lacks its protocol version and robot id", ErrorKind::link_lost));
          return;
        }
        if (*proto::to_int(line.fields[1]) != proto::kProtocolVersion) {
          link_down(err("robot.version", "robot speaks protocol version " + line.fields[1] + ", fettle speaks " +
                                             std::to_string(proto::kProtocolVersion), ErrorKind::unavailable));
          return;
        }
        robot_id_ = line.fields[2];
        ++connections_;
        backoff_ms_ = opts_.reconnect_initial_ms;
        log_->info("robot link up: robot '{}' at {}", robot_id_, endpoint_text());
        set_state(RobotState::ready);
        schedule_ping();
        return;
      case Req::traj:
        send_chunk();
        return;
      case Req::chunk:
        ++chunk_;
        if (chunk_ < chunks_) {
          send_chunk();
        } else {
          await(Req::end, send("END " + std::to_string(traj_id_)), "the ACK of END (trajectory CRC check)");
        }
        return;
      case Req::end:
        payloads_.clear();
        set_state(RobotState::uploaded);
        complete(op_done_, {});
        return;
      case Req::run: {
        set_state(RobotState::running);
        const unsigned gen = generation_;
        run_timer_.expires_after(Ms(opts_.run_timeout_ms));
        run_timer_.async_wait([self = shared_from_this(), gen](const boost::system::error_code& e) {
          if (e || gen != self->generation_ || self->state_ != RobotState::running) return;
          const Error cause = err("robot.run_timeout", "trajectory " + std::to_string(self->traj_id_) +
                                                           " did not finish within " +
                                                           std::to_string(self->opts_.run_timeout_ms) +
                                                           " ms; sent STOP", ErrorKind::timeout);
          self->last_error_ = cause;
          complete(self->op_done_, cause);
          self->stop(nullptr);
        });
        return;
      }
      case Req::stop: {
        const auto before = state_before_stop_.value_or(RobotState::ready);
        state_before_stop_.reset();
        set_state(before == RobotState::faulted ? RobotState::faulted : RobotState::ready);
        complete(stop_done_, {});
        return;
      }
      case Req::reset:
        set_state(RobotState::ready);
        complete(op_done_, {});
        return;
    }
  }

  void on_nak(const proto::Line& line) {
    const std::string code = line.fields[1];
    const Error cause = err("robot.nak." + lower(code), "robot refused line " + line.fields[0] + " with " + code +
                                                            (line.text.empty() ? "" : ": " + line.text), ErrorKind::refused);
    if (!pending_) {
      log_->warn("robot: unexpected NAK: {}", cause.message);
      return;
    }
    // A NAK answers the pending request even when it names a line inside it (a point of a chunk).
    const Req r = pending_->req;
    pending_.reset();
    cancel_reply_timer();
    log_->warn("{}", cause.message);
    last_error_ = cause;
    switch (r) {
      case Req::hello: link_down(cause); return;
      case Req::traj:
      case Req::chunk:
      case Req::end:
        payloads_.clear();
        set_state(RobotState::ready, cause);
        complete(op_done_, cause);
        return;
      case Req::run:
        set_state(RobotState::uploaded, cause);
        complete(op_done_, cause);
        return;
      case Req::stop:
        set_state(state_before_stop_.value_or(RobotState::ready), cause);
        state_before_stop_.reset();
        complete(stop_done_, cause);
        return;
      case Req::reset:
        set_state(RobotState::faulted, cause);
        complete(op_done_, cause);
        return;
    }
  }

  void on_prog(const proto::Line& line) {
    if (state_ != RobotState::running) return;
    RobotProgress p{*proto::to_int(line.fields[0]), *proto::to_int(line.fields[1]), *proto::to_int(line.fields[2])};
    if (p.trajectory_id != traj_id_) {
      log_->warn("robot: progress for trajectory {} while {} runs; ignored", p.trajectory_id, traj_id_);
      return;
    }
    if (on_progress_) on_progress_(p);
  }

  void on_done(const proto::Line& line) {
    if (state_ != RobotState::running || *proto::to_int(line.fields[0]) != traj_id_) {
      log_->debug("robot: DONE {} ignored in state {}", line.fields[0], to_string(state_));
      return;
    }
    run_timer_.cancel();
    log_->info("robot: trajectory {} done ({} points)", traj_id_, line.fields[1]);
    set_state(RobotState::uploaded);
    complete(op_done_, {});
  }

  void on_fault(const proto::Line& line) {
    const Error cause = err("robot.fault." + lower(line.fields[1]),
                            "robot controller fault " + line.fields[1] +
                                (line.fields[0] != "0" ? " during trajectory " + line.fields[0] : std::string()) +
                                (line.text.empty() ? "" : ": " + line.text) + " (clear it, then reset the link)", ErrorKind::device_fault);
    log_->error("{}", cause.message);
    run_timer_.cancel();
    if (pending_ && pending_->req != Req::stop) {
      pending_.reset();
      cancel_reply_timer();
    }
    if (state_ == RobotState::stopping) state_before_stop_ = RobotState::faulted;
    else set_state(RobotState::faulted, cause);
    last_error_ = cause;
    complete(op_done_, cause);
  }

  // ---- requests -----------------------------------------------------------------
  Status check_idle(std::initializer_list<RobotState> allowed, std::string_view what) const {
    const bool ok = std::find(allowed.begin(), allowed.end(), state_) != allowed.end();
    if (!ok || pending_ || op_done_)
      return Error{"robot.state", std::string("cannot ") + std::string(what) + " while the robot link is " +
                                      std::string(to_string(state_)) + (pending_ ? " (a request is pending)" : ""), ErrorKind::unavailable};
    return {};
  }

  void post_fail(Handler h, Status s) {
    if (!h) return;
    asio::post(io_, [h = std::move(h), s = std::move(s)]() mutable { h(std::move(s)); });
  }

  void upload(const Trajectory& t, Handler done) {
    if (auto st = check_idle({RobotState::ready, RobotState::uploaded}, "upload a trajectory"); !st)
      return post_fail(std::move(done), st);
    if (t.points.empty()) return post_fail(std::move(done), Error{"robot.invalid_point", "the trajectory has no points", ErrorKind::invalid_request});
    if (t.points.size() > static_cast<std::size_t>(proto::kMaxPoints))
      return post_fail(std::move(done), Error{"robot.invalid_point", "the trajectory has " +
                                                                         std::to_string(t.points.size()) +
                                                                         " points; at most 99999 fit one upload", ErrorKind::invalid_request});
    std::vector<std::pair<std::string, std::string>> payloads;
    payloads.reserve(t.points.size());
    for (std::size_t i = 0; i < t.points.size(); ++i) {
      const int idx = static_cast<int>(i);
      if (auto st = proto::check_point(t.points[i], idx); !st) return post_fail(std::move(done), st);
      payloads.push_back(proto::format_point(t.points[i], idx));
    }
    payloads_ = std::move(payloads);
    traj_id_ = next_traj_id_;
    next_traj_id_ = next_traj_id_ >= proto::kMaxId ? 1 : next_traj_id_ + 1;
    const int n = static_cast<int>(payloads_.size());
    chunks_ = (n + opts_.chunk_points - 1) / opts_.chunk_points;
    chunk_ = 0;
    const auto crc = proto::crc32(proto::canonical_text(payloads_));
    op_done_ = std::move(done);
    set_state(RobotState::uploading);
    log_->info("robot: uploading trajectory {} ({} points, {} chunks, CRC {})", traj_id_, n, chunks_,
               proto::crc_hex(crc));
    await(Req::traj,
          send("TRAJ " + std::to_string(traj_id_) + " " + std::to_string(n) + " " + std::to_string(chunks_) + " " +
               proto::crc_hex(crc)),
          "the ACK of TRAJ");
  }

  void send_chunk() {
    const int n = static_cast<int>(payloads_.size());
    const int first = chunk_ * opts_.chunk_points;
    const int count = std::min(opts_.chunk_points, n - first);
    // The whole chunk goes out in one write so that nothing (a PING) lands inside it.
    seq_out_ = proto::next_seq(seq_out_);
    const int ref = seq_out_;
    std::string bytes = proto::format_line(ref, "CHUNK " + std::to_string(chunk_ + 1) + " " + std::to_string(first) +
                                                    " " + std::to_string(count)) + "\n";
    for (int i = first; i < first + count; ++i) {
      for (const auto* payload : {&payloads_[static_cast<std::size_t>(i)].first, &payloads_[static_cast<std::size_t>(i)].second}) {
        seq_out_ = proto::next_seq(seq_out_);
        bytes += proto::format_line(seq_out_, *payload);
        bytes += '\n';
      }
    }
    log_->debug("robot: chunk {}/{} (points {}..{})", chunk_ + 1, chunks_, first, first + count - 1);
    enqueue(std::move(bytes));
    await(Req::chunk, ref, "the ACK of chunk " + std::to_string(chunk_ + 1) + " of " + std::to_string(chunks_));
  }

  void run(Handler done) {
    if (auto st = check_idle({RobotState::uploaded}, "run a trajectory"); !st) return post_fail(std::move(done), st);
    op_done_ = std::move(done);
    await(Req::run, send("RUN " + std::to_string(traj_id_)), "the ACK of RUN");
  }

  void stop(Handler done) {
    if (!connected()) {
      return post_fail(std::move(done), Error{"robot.state", "cannot stop: the robot link is " +
                                                                  std::string(to_string(state_)), ErrorKind::unavailable});
    }
    if (pending_ && pending_->req == Req::hello) {
      return post_fail(std::move(done), Error{"robot.state", "cannot stop while the HELLO is pending", ErrorKind::unavailable});
    }
    if (stop_done_ || (pending_ && pending_->req == Req::stop)) {
      // A STOP is on its way: this caller gets its ACK (or its failure) too; one STOP on the wire.
      stop_done_ = [first = std::move(stop_done_), done = std::move(done)](Status s) mutable {
        if (first) first(s);
        if (done) done(std::move(s));
      };
      return;
    }
    const Error stopped = err("robot.stopped", "stopped on request before the robot finished", ErrorKind::cancelled);
    if (state_ != RobotState::stopping) state_before_stop_ = state_;
    if (pending_) {
      pending_.reset();
      cancel_reply_timer();
    }
    run_timer_.cancel();
    payloads_.clear();
    complete(op_done_, stopped);
    stop_done_ = std::move(done);
    set_state(RobotState::stopping);
    await(Req::stop, send("STOP"), "the ACK of STOP");
  }

  void reset(Handler done) {
    if (auto st = check_idle({RobotState::faulted, RobotState::ready, RobotState::uploaded}, "reset the robot"); !st)
      return post_fail(std::move(done), st);
    op_done_ = std::move(done);
    await(Req::reset, send("RESET"), "the ACK of RESET");
  }
};

RobotLink::RobotLink(asio::io_context& io, RobotLinkOptions options)
    : impl_(std::make_shared<Impl>(io, std::move(options))) {}

RobotLink::~RobotLink() {
  impl_->op_done_ = nullptr;
  impl_->stop_done_ = nullptr;
  impl_->on_state_ = nullptr;
  impl_->on_progress_ = nullptr;
  impl_->active_ = false;
  impl_->close_socket();
}

Status RobotLink::configure() {
  if (lifecycle_ != Lifecycle::unconfigured) return {};
  const auto& o = impl_->opts_;
  auto refuse = [&](const std::string& why) {
    impl_->last_error_ = Error{"robot.config", "[robot] " + why, ErrorKind::config};
    return Status{impl_->last_error_};
  };
  if (o.address.empty()) return refuse("address is empty: set the robot controller's IPv4 address");
  if (o.port <= 0 || o.port > 65535) return refuse("port " + std::to_string(o.port) + " is not 1-65535");
  if (o.connect_timeout_ms <= 0 || o.reply_timeout_ms <= 0 || o.run_timeout_ms <= 0 || o.ping_period_ms <= 0)
    return refuse("connect_timeout_ms, reply_timeout_ms, run_timeout_ms and ping_period_ms must be above 0");
  lifecycle_ = Lifecycle::inactive;
  return {};
}

Status RobotLink::activate() {
  if (lifecycle_ == Lifecycle::active) return {};
  if (lifecycle_ == Lifecycle::unconfigured)
    return Error{"robot.lifecycle", "robot " + impl_->opts_.address + ": activate() before configure()", ErrorKind::unavailable};
  impl_->start();
  lifecycle_ = Lifecycle::active;
  return {};
}

void RobotLink::deactivate() {
  if (lifecycle_ != Lifecycle::active) return;
  impl_->shutdown();
  lifecycle_ = Lifecycle::inactive;
}

void RobotLink::start() { impl_->start(); }
void RobotLink::shutdown() { impl_->shutdown(); }
void RobotLink::upload(const Trajectory& trajectory, Handler done) { impl_->upload(trajectory, std::move(done)); }
void RobotLink::run(Handler done) { impl_->run(std::move(done)); }
void RobotLink::stop(Handler done) { impl_->stop(std::move(done)); }
void RobotLink::reset(Handler done) { impl_->reset(std::move(done)); }
RobotState RobotLink::state() const { return impl_->state_; }
const Error& RobotLink::last_error() const { return impl_->last_error_; }
const std::string& RobotLink::robot_id() const { return impl_->robot_id_; }
int RobotLink::trajectory_id() const { return impl_->traj_id_; }
int RobotLink::connections() const { return impl_->connections_; }
void RobotLink::on_state(StateHandler h) { impl_->on_state_ = std::move(h); }
void RobotLink::on_progress(ProgressHandler h) { impl_->on_progress_ = std::move(h); }

}  // namespace fettle::drivers
