// The control socket server (see control.hpp and docs/daemon-control.md).
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <cstring>
#include <exception>
#include <set>
#include <string>
#include <utility>

#include <boost/asio/local/stream_protocol.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/write.hpp>

#include "fettle/core/log.hpp"
#include "fettle/daemon/control.hpp"

namespace fettle::daemon::control {

namespace asio = boost::asio;
using local = asio::local::stream_protocol;

namespace {

json error_reply(const std::string& code, const std::string& message) {
  return json{{"ok", false}, {"error", message}, {"code", code}};
}

json error_reply(const Error& e) { return error_reply(e.code, e.message); }

std::string errno_text(int e) { return std::strerror(e); }

std::string mode_text(unsigned mode) {
  char buf[8];
  std::snprintf(buf, sizeof buf, "%04o", mode & 07777U);
  return buf;
}

/// True if something accepts connections on the Unix socket `path`.
bool socket_is_live(const std::filesystem::path& path) {
  const int fd = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
  if (fd < 0) return false;
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  std::strncpy(addr.sun_path, path.c_str(), sizeof(addr.sun_path) - 1);
  const int r = ::connect(fd, reinterpret_cast<const sockaddr*>(&addr), sizeof addr);
  const int e = errno;
  ::close(fd);
  // EAGAIN: the listener's backlog is full, so it is alive.
  return r == 0 || e == EAGAIN || e == EINPROGRESS;
}

/// A stalled client must not grow our memory: at most this many reply bytes queued.
constexpr std::size_t max_pending_output = 4U * 1024U * 1024U;

}  // namespace

namespace {
void append_reply(std::string& out, const json& r) {
  out += r.dump(-1, ' ', false, json::error_handler_t::replace);
  out += '\n';
}
}  // namespace

LineProtocol::LineProtocol(Handle handle, std::size_t max_line_bytes)
    : handle_(std::move(handle)), max_line_bytes_(max_line_bytes) {}

bool LineProtocol::consume(std::string_view data, std::string& out, std::size_t max_output) {
  const std::size_t max = max_line_bytes_;
  while (!data.empty()) {
    const auto nl = data.find('\n');
    const std::string_view part = data.substr(0, nl);
    if (discarding_) {
      if (nl != std::string_view::npos) discarding_ = false;
    } else if (line_.size() + part.size() > max) {
      append_reply(out, error_reply(code::line_too_long,
                                    "request line longer than " + std::to_string(max) +
                                        " bytes: ignored up to the next newline; send one JSON object "
                                        "per line, e.g. {\"cmd\":\"status\"}"));
      line_.clear();
      discarding_ = nl == std::string_view::npos;
    } else {
      line_.append(part);
      if (nl != std::string_view::npos) {
        handle_line(out);
        line_.clear();
      }
    }
    if (nl == std::string_view::npos) break;
    data.remove_prefix(nl + 1);
    if (out.size() > max_output) return false;
  }
  return true;
}

void LineProtocol::handle_line(std::string& out) {
  std::string_view text = line_;
  if (!text.empty() && text.back() == '\r') text.remove_suffix(1);
  if (text.find_first_not_of(" \t") == std::string_view::npos) return;  // blank line: ignore
  json request = json::parse(text, nullptr, false);
  if (request.is_discarded()) {
    append_reply(out, error_reply(code::bad_json, "request is not valid JSON: send one JSON object per line, e.g. "
                                                  "{\"cmd\":\"status\"}"));
    return;
  }
  append_reply(out, handle_(request));
}

struct Connection;

struct Server::Impl {
  Impl(asio::io_context& io_, Handler& handler_, ServerOptions options_)
      : io(io_), handler(handler_), options(std::move(options_)), acceptor(io_), maintenance(options.maintenance) {}

  asio::io_context& io;
  Handler& handler;
  ServerOptions options;
  local::acceptor acceptor;
  bool maintenance = false;
  bool running = false;
  dev_t socket_dev = 0;
  ino_t socket_ino = 0;
  std::set<std::shared_ptr<Connection>> connections;
  std::shared_ptr<bool> alive = std::make_shared<bool>(true);  ///< expires with the Impl (for pending accepts)

  void accept();
  json handle(const json& request);
  void remove_socket_file();
};

/// The peer is root or runs as the daemon's own user (SO_PEERCRED).
bool privileged(local::socket& socket) {
  ucred cred{};
  socklen_t len = sizeof cred;
  if (::getsockopt(socket.native_handle(), SOL_SOCKET, SO_PEERCRED, &cred, &len) != 0) return false;
  return cred.uid == 0 || cred.uid == ::geteuid();
}

/// One client: reads lines, answers each, one batch at a time (no reading while a reply
/// is being written, so a client that does not read its replies only stalls itself).
struct Connection : std::enable_shared_from_this<Connection> {
  Connection(Server::Impl& server_, local::socket socket_)
      : server(&server_),
        socket(std::move(socket_)),
        write_timer(server_.io),
        idle_timer(server_.io),
        request_timer(server_.io) {}

  Server::Impl* server;  // null once closed
  local::socket socket;
  asio::steady_timer write_timer;
  asio::steady_timer idle_timer;
  asio::steady_timer request_timer;  ///< armed while a request line is incomplete (and at connect)
  bool request_pending = false;
  std::chrono::steady_clock::time_point last_activity = std::chrono::steady_clock::now();
  std::array<char, 4096> chunk{};
  LineProtocol protocol{[s = server](const json& request) { return s->handle(request); }, server->options.max_line_bytes};
  std::string out;
  bool closed = false;

  void start() {
    arm_idle();
    arm_request();  // the first request is due within request_timeout of connecting
    read();
  }

  void arm_request() {
    if (server->options.request_timeout.count() <= 0 || request_pending) return;
    request_pending = true;
    request_timer.expires_after(server->options.request_timeout);
    request_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (ec || self->closed || !self->request_pending) return;
      log::get("control")->warn("control: closing a client whose request was not complete within {} ms",
                                self->server->options.request_timeout.count());
      self->close();
    });
  }

  /// After a chunk: a line left incomplete must be finished within request_timeout.
  void track_request(std::string_view data) {
    if (data.empty()) return;
    if (data.back() == '\n') {
      request_pending = false;
      request_timer.cancel();
    } else {
      arm_request();
    }
  }

  /// How long nothing came (for the privileged slot), when no reply is pending.
  [[nodiscard]] std::chrono::steady_clock::duration idle_for() const {
    return std::chrono::steady_clock::now() - last_activity;
  }

  void arm_idle() {
    if (server->options.idle_timeout.count() <= 0) return;
    idle_timer.expires_after(server->options.idle_timeout);
    idle_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (ec || self->closed) return;
      log::get("control")->info("control: closing a client idle for {} ms", self->server->options.idle_timeout.count());
      self->close();
    });
  }

  void read() {
    socket.async_read_some(asio::buffer(chunk),
                           [self = shared_from_this()](const boost::system::error_code& ec, std::size_t n) {
                             if (self->closed) return;
                             if (ec) {
                               self->close();
                               return;
                             }
                             self->arm_idle();
                             self->last_activity = std::chrono::steady_clock::now();
                             self->track_request(std::string_view{self->chunk.data(), n});
                             self->consume(std::string_view{self->chunk.data(), n});
                             if (self->closed) return;
                             if (self->out.empty())
                               self->read();
                             else
                               self->write();
                           });
  }

  void consume(std::string_view data) {
    if (!protocol.consume(data, out, max_pending_output)) {
      log::get("control")->warn("control: a client queued more than {} bytes of replies; closing it",
                                max_pending_output);
      close();
    }
  }

  void write() {
    auto data = std::make_shared<std::string>(std::move(out));
    out.clear();
    write_timer.expires_after(server->options.write_timeout);
    write_timer.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (ec || self->closed) return;
      log::get("control")->warn("control: a client did not read its reply within {} ms; closing it",
                                self->server->options.write_timeout.count());
      self->close();
    });
    asio::async_write(socket, asio::buffer(*data),
                      [self = shared_from_this(), data](const boost::system::error_code& ec, std::size_t) {
                        if (self->closed) return;
                        self->write_timer.cancel();
                        if (ec) {
                          self->close();
                          return;
                        }
                        self->read();
                      });
  }

  void close() {
    if (closed) return;
    closed = true;
    boost::system::error_code ec;
    socket.shutdown(local::socket::shutdown_both, ec);
    socket.close(ec);
    write_timer.cancel();
    idle_timer.cancel();
    request_timer.cancel();
    if (server != nullptr) {
      auto* s = server;
      server = nullptr;
      s->connections.erase(shared_from_this());
    }
  }
};

void Server::Impl::accept() {
  acceptor.async_accept([this, alive = std::weak_ptr<bool>(alive)](const boost::system::error_code& ec,
                                                                   local::socket socket) {
    if (alive.expired() || !running) return;  // the Server is gone or stopped
    if (ec) {
      if (ec == asio::error::operation_aborted) return;
      log::get("control")->warn("control: accept on {} failed: {}", options.socket_path.string(), ec.message());
      accept();
      return;
    }
    if (connections.size() >= options.max_clients && options.privileged_slot && privileged(socket)) {
      // root or the daemon's own uid: the client idle longest makes room, if one is idle past
      // the request deadline with nothing to write (docs/daemon-control.md; test
      // ControlFixture.AFullServerStillAnswersRootByDroppingItsLongestIdleClient)
      std::shared_ptr<Connection> oldest;
      for (const auto& c : connections)
        if (c->out.empty() && !c->request_pending && c->idle_for() >= options.request_timeout &&
            (!oldest || c->idle_for() > oldest->idle_for()))
          oldest = c;
      if (oldest) {
        log::get("control")->warn("control: {} clients connected; closing the one idle longest ({} s) for a client "
                                  "of root or fettled's own user",
                                  connections.size(),
                                  std::chrono::duration_cast<std::chrono::seconds>(oldest->idle_for()).count());
        oldest->close();
      }
    }
    if (connections.size() >= options.max_clients) {
      // Best effort, non-blocking: the client learns why before we close it.
      const std::string text =
          error_reply(code::too_many_clients, "more than " + std::to_string(options.max_clients) +
                                                  " control clients connected; try again later")
              .dump() +
          "\n";
      boost::system::error_code wec;
      socket.non_blocking(true, wec);
      socket.write_some(asio::buffer(text), wec);
      socket.close(wec);
    } else {
      auto c = std::make_shared<Connection>(*this, std::move(socket));
      connections.insert(c);
      c->start();
    }
    accept();
  });
}

void Server::Impl::remove_socket_file() {
  struct stat st {};
  if (socket_ino != 0 && ::lstat(options.socket_path.c_str(), &st) == 0 && st.st_dev == socket_dev &&
      st.st_ino == socket_ino)
    ::unlink(options.socket_path.c_str());
  socket_ino = 0;
}

json Server::Impl::handle(const json& request) {
  json r;
  try {
    if (!request.is_object())
      return error_reply(code::bad_json, "request must be a JSON object like {\"cmd\":\"status\"}");
    const auto cmd_it = request.find("cmd");
    if (cmd_it == request.end() || !cmd_it->is_string())
      return error_reply(code::bad_argument, "request has no \"cmd\" string, e.g. {\"cmd\":\"status\"}");
    const std::string cmd = cmd_it->get<std::string>();

    auto merge = [&](const json& fields) {
      r = json{{"ok", true}};
      if (fields.is_object())
        for (const auto& [k, v] : fields.items())
          if (k != "ok") r[k] = v;
    };
    auto from = [&](Result<json> res, const char* key) {
      if (!res) {
        r = error_reply(res.error());
      } else if (key == nullptr) {
        merge(res.value());
      } else {
        r = json{{"ok", true}, {key, std::move(res.value())}};
      }
    };
    const bool gated =
        cmd == "reset" || cmd == "hold" || cmd == "unhold" || cmd == "dry_cycle" || cmd == "tool_changed";
    if (gated && !maintenance) {
      r = error_reply(code::maintenance_required,
                      "\"" + cmd + "\" is only accepted in maintenance mode; switch it on first with "
                      "{\"cmd\":\"maintenance\",\"on\":true}");
    } else if (cmd == "status") {
      merge(handler.status());
      r["maintenance"] = maintenance;
    } else if (cmd == "last_cycle") {
      from(handler.last_cycle(), "cycle");
    } else if (cmd == "cycles") {
      std::size_t limit = 20;
      if (const auto it = request.find("limit"); it != request.end()) {
        if (!it->is_number_integer() || it->get<long long>() < 1 || it->get<long long>() > 10000)
          return error_reply(code::bad_argument, "\"limit\" must be an integer from 1 to 10000");
        limit = static_cast<std::size_t>(it->get<long long>());
      }
      from(handler.cycles(limit), "cycles");
    } else if (cmd == "reset") {
      from(handler.reset(), nullptr);
    } else if (cmd == "hold") {
      from(handler.hold(), nullptr);
    } else if (cmd == "unhold") {
      from(handler.unhold(), nullptr);
    } else if (cmd == "dry_cycle") {
      from(handler.dry_cycle(), nullptr);
    } else if (cmd == "tool_changed") {
      const auto it = request.find("tool");
      if (it == request.end() || !it->is_string() || it->get<std::string>().empty())
        return error_reply(code::bad_argument,
                           "\"tool\" must name the tool whose wheel is new, e.g. {\"cmd\":\"tool_changed\",\"tool\":\"flat-16\"}");
      from(handler.tool_changed(it->get<std::string>()), nullptr);
    } else if (cmd == "maintenance") {
      const auto it = request.find("on");
      if (it != request.end()) {
        if (!it->is_boolean())
          return error_reply(code::bad_argument, "\"on\" must be true or false, e.g. {\"cmd\":\"maintenance\",\"on\":true}");
        const bool on = it->get<bool>();
        if (on != maintenance) {
          if (auto st = handler.maintenance_changing(on); !st) return error_reply(st.error());
          maintenance = on;
          log::get("control")->info("control: maintenance mode {}", on ? "on" : "off");
        }
      }
      r = json{{"ok", true}, {"maintenance", maintenance}};
    } else {
      r = error_reply(code::unknown_command,
                      "unknown command \"" + cmd +
                          "\"; known: status, last_cycle, cycles, maintenance, reset, hold, unhold, dry_cycle, "
                          "tool_changed");
    }
  } catch (const std::exception& e) {
    log::get("control")->error("control: handling {} failed: {}", request.dump(-1, ' ', false, json::error_handler_t::replace), e.what());
    r = error_reply(code::handler_failed, std::string{"internal error: "} + e.what() + " (please report this)");
  }
  if (request.is_object())
    if (const auto id = request.find("id"); id != request.end()) r["id"] = *id;
  return r;
}

// ---------------------------------------------------------------------------------------

Server::Server(asio::io_context& io, Handler& handler, ServerOptions options)
    : impl_(std::make_unique<Impl>(io, handler, std::move(options))) {}

Server::~Server() { stop(); }

Status Server::start() {
  auto& o = impl_->options;
  const auto& path = o.socket_path;
  const std::string where = "control socket " + path.string();
  if (impl_->running) return {};
  if (path.empty()) return Error{"control.config", "[control] socket is empty: set a path such as /run/fettle/fettled.sock"};
  if (path.native().size() >= sizeof(sockaddr_un::sun_path))
    return Error{"control.config", where + ": path longer than " + std::to_string(sizeof(sockaddr_un::sun_path) - 1) +
                                       " bytes (the Unix socket limit); choose a shorter [control] socket"};
  const std::filesystem::path dir = path.has_parent_path() ? path.parent_path() : std::filesystem::path{"."};
  struct stat st {};
  if (::stat(dir.c_str(), &st) != 0)
    return Error{"control.socket_dir", where + ": directory " + dir.string() + ": " + errno_text(errno) +
                                           "; create it (systemd: RuntimeDirectory=fettle)"};
  if (!S_ISDIR(st.st_mode)) return Error{"control.socket_dir", where + ": " + dir.string() + " is not a directory"};
  if ((st.st_mode & S_IWOTH) != 0)
    return Error{"control.socket_dir", where + ": directory " + dir.string() + " is world-writable (mode " +
                                           mode_text(st.st_mode) +
                                           "), so anyone could replace the socket; use a private directory such as "
                                           "/run/fettle (RuntimeDirectory=fettle)"};
  if (::lstat(path.c_str(), &st) == 0) {
    if (!S_ISSOCK(st.st_mode))
      return Error{"control.socket_exists", where + ": the path exists and is not a socket; remove it or choose another [control] socket"};
    if (socket_is_live(path))
      return Error{"control.socket_in_use", where + ": another server (a running fettled?) already answers there; stop it first"};
    if (::unlink(path.c_str()) != 0)
      return Error{"control.socket_exists", where + ": cannot remove the stale socket: " + errno_text(errno)};
    log::get("control")->info("control: removed a stale socket {}", path.string());
  }

  boost::system::error_code ec;
  auto& acc = impl_->acceptor;
  acc.open(local{}, ec);
  if (!ec) {
    const ::mode_t old = ::umask(static_cast<::mode_t>(~o.mode & 0777U));
    acc.bind(local::endpoint{path.native()}, ec);
    ::umask(old);
  }
  if (ec) {
    acc.close();
    return Error{"control.socket", where + ": cannot create: " + ec.message()};
  }
  if (::chmod(path.c_str(), static_cast<::mode_t>(o.mode)) != 0 || ::lstat(path.c_str(), &st) != 0 ||
      (st.st_mode & 07777U) != (o.mode & 07777U)) {
    const std::string got = mode_text(st.st_mode);
    acc.close();
    ::unlink(path.c_str());
    return Error{"control.socket_mode", where + ": mode is " + got + " after creation, expected " + mode_text(o.mode) +
                                            "; refusing to serve"};
  }
  impl_->socket_dev = st.st_dev;
  impl_->socket_ino = st.st_ino;
  // the kernel's largest backlog (net.core.somaxconn): a burst of connects waits to be
  // accepted (and told too_many_clients) instead of being refused at connect
  acc.listen(asio::socket_base::max_listen_connections, ec);
  if (ec) {
    acc.close();
    impl_->remove_socket_file();
    return Error{"control.socket", where + ": listen failed: " + ec.message()};
  }
  impl_->running = true;
  impl_->accept();
  log::get("control")->info("control: listening on {} (mode {})", path.string(), mode_text(o.mode));
  return {};
}

void Server::stop() {
  if (!impl_) return;
  if (impl_->running) {
    impl_->running = false;
    boost::system::error_code ec;
    impl_->acceptor.close(ec);
  }
  auto conns = std::move(impl_->connections);
  impl_->connections.clear();
  for (const auto& c : conns) {
    c->server = nullptr;
    c->close();
  }
  impl_->remove_socket_file();
}

bool Server::maintenance() const { return impl_->maintenance; }
void Server::set_maintenance(bool on) { impl_->maintenance = on; }
std::size_t Server::client_count() const { return impl_->connections.size(); }
const std::filesystem::path& Server::socket_path() const { return impl_->options.socket_path; }
json Server::handle(const json& request) { return impl_->handle(request); }

}  // namespace fettle::daemon::control
