#pragma once
// The local control socket of fettled: a Unix-domain stream socket speaking JSON lines
// (docs/daemon-control.md). No TCP listener exists anywhere.
//
//   request  (one JSON object per line):  {"cmd":"status"}  {"cmd":"cycles","limit":20}
//                                         {"cmd":"maintenance","on":true}   (optional "id" is echoed)
//   reply    (one JSON object per line):  {"ok":true,...}
//                                         {"ok":false,"error":"what, where, what to do","code":"control.x"}
//
// The daemon implements control::Handler; the Server calls it on the io_context's thread
// (the daemon's event loop), one request at a time, so the handler needs no locking. The
// Server owns the maintenance flag and refuses reset/hold/unhold/dry_cycle unless it is on.
//
//   fettle::daemon::control::Server server{io, handler, {.socket_path = cfg.control.socket}};
//   if (auto st = server.start(); !st) { log(st.error().message); return exit_code::failure; }
//   io.run();
//
// The CLI side is control::Client (blocking, with timeouts; no event loop needed).
#include <chrono>
#include <cstddef>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include <boost/asio/io_context.hpp>
#include <nlohmann/json.hpp>

#include "fettle/core/result.hpp"

namespace fettle::daemon::control {

using json = nlohmann::json;

/// Error codes of the protocol itself (handlers may return their own codes).
namespace code {
inline constexpr const char* bad_json = "control.bad_json";              ///< not a JSON object
inline constexpr const char* line_too_long = "control.line_too_long";    ///< > max_line_bytes without '\n'
inline constexpr const char* unknown_command = "control.unknown_command";
inline constexpr const char* bad_argument = "control.bad_argument";      ///< e.g. "limit" not a positive integer
inline constexpr const char* maintenance_required = "control.maintenance_required";
inline constexpr const char* too_many_clients = "control.too_many_clients";
inline constexpr const char* handler_failed = "control.handler_failed";  ///< the handler threw (a bug)
// Client side only:
inline constexpr const char* not_running = "control.not_running";        ///< no socket / connection refused
inline constexpr const char* permission_denied = "control.permission_denied";
inline constexpr const char* timeout = "control.timeout";
inline constexpr const char* io = "control.io";
}  // namespace code

/// What the daemon answers. Every method runs on the event loop's thread and must not block
/// (start long work, e.g. a dry cycle, and return at once). A returned Error is sent as
/// {"ok":false,"error":message,"code":code}; an exception becomes control.handler_failed.
class Handler {
 public:
  virtual ~Handler() = default;

  /// The daemon's state as a JSON object; its fields are merged into the reply next to
  /// "ok" and "maintenance". Suggested fields (the CLI prints these first, then any others):
  /// "state" (PackML state name), "state_code" (int), "fault" {code,message} or null,
  /// "cycle_id" (current or null), "cycles_total", "last_result", "uptime_s", "version".
  virtual json status() = 0;

  /// The last finished cycle's summary (an object, e.g. id, started, result, duration_s,
  /// record dir), or null when there is none. Sent as {"ok":true,"cycle":...}.
  virtual Result<json> last_cycle() = 0;

  /// The newest `limit` cycles, newest first, as a JSON array of the same summaries.
  /// Sent as {"ok":true,"cycles":[...]}.
  virtual Result<json> cycles(std::size_t limit) = 0;

  /// PackML Reset / Hold / Unhold. Only called in maintenance mode. The object returned is
  /// merged into the reply (e.g. {"state":"Resetting"}); return an Error to refuse.
  virtual Result<json> reset() = 0;
  virtual Result<json> hold() = 0;
  virtual Result<json> unhold() = 0;

  /// Starts one dry cycle (no grinding). Only called in maintenance mode; returns at once
  /// (e.g. {"cycle_id":"..."}), the result shows later in last_cycle/cycles.
  virtual Result<json> dry_cycle() = 0;

  /// A new wheel of the named tool is fitted (a tool.worn fault asks for it). Only called in
  /// maintenance mode. Default: refused (a daemon that predicts no wear).
  virtual Result<json> tool_changed(const std::string& tool) {
    return Error{"control.unsupported", "this daemon keeps no wheel wear; nothing to reset for '" + tool + "'"};
  }

  /// Maintenance mode is about to change; return an Error to refuse (e.g. entering it
  /// during Execute). The Server keeps the flag. Default: accept.
  virtual Status maintenance_changing(bool on) {
    (void)on;
    return {};
  }
};

struct ServerOptions {
  std::filesystem::path socket_path;            ///< e.g. /run/fettle/fettled.sock ([control] socket)
  unsigned mode = 0660;                         ///< socket file mode (checked after creation)
  std::size_t max_line_bytes = 64 * 1024;       ///< longer request lines get line_too_long
  std::size_t max_clients = 32;                 ///< one more gets too_many_clients and is closed
  std::chrono::milliseconds write_timeout{5000};  ///< a client not reading its replies is dropped
  std::chrono::milliseconds idle_timeout{600000}; ///< a client silent this long is dropped (0 = never)
  /// A request line must be complete this long after its first byte, and the first one this long
  /// after connecting: a client dripping a byte now and then is dropped (0 = never).
  std::chrono::milliseconds request_timeout{5000};
  /// When max_clients are connected, a client of root or of the daemon's own uid still gets in:
  /// the client idle longest (at least request_timeout, no reply pending) is dropped for it.
  bool privileged_slot = true;
  bool maintenance = false;                     ///< initial maintenance mode
};

struct Connection;  // one connected client (server.cpp)

/// The control socket server on an io_context. Not thread-safe: use it from the loop's thread.
/// The io_context must outlive it.
class Server {
 public:
  Server(boost::asio::io_context& io, Handler& handler, ServerOptions options);
  ~Server();  ///< closes every client and removes the socket file
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  /// Creates the socket (mode checked after creation) and starts accepting. Refuses (an
  /// Error, nothing created) if the socket's directory is missing or world-writable (even
  /// with the sticky bit, like /tmp), if a live server already answers on the path, or if
  /// the path exists and is not a socket. A stale socket (nobody listening) is replaced.
  Status start();
  /// Stops accepting, closes clients, removes the socket file. Idempotent.
  void stop();

  [[nodiscard]] bool maintenance() const;
  void set_maintenance(bool on);  ///< without asking the handler (e.g. from the config)
  [[nodiscard]] std::size_t client_count() const;
  [[nodiscard]] const std::filesystem::path& socket_path() const;

  /// Handles one request object as a connected client would (used by the connections;
  /// public for the daemon's own tests). Never throws.
  json handle(const json& request);

 private:
  friend struct Connection;
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// The byte-stream side of one client, without the socket: splits what arrives into request
/// lines (CR LF or LF; at most max_line_bytes, a longer one gets line_too_long and is skipped
/// up to its newline; blank lines are ignored), hands each parsed object to `handle` and
/// appends one reply line per request to `out`. The result does not depend on how the bytes
/// are split into reads. Used by the server's connections, and by the fuzz target.
class LineProtocol {
 public:
  using Handle = std::function<json(const json& request)>;
  LineProtocol(Handle handle, std::size_t max_line_bytes);
  /// Consumes `data`; returns false (and stops) once `out` holds more than `max_output` bytes
  /// (a client that sends requests without reading the replies).
  bool consume(std::string_view data, std::string& out, std::size_t max_output);

 private:
  void handle_line(std::string& out);
  Handle handle_;
  std::size_t max_line_bytes_;
  std::string line_;
  bool discarding_ = false;  ///< inside an oversize line: drop bytes up to the next '\n'
};

/// Blocking client for the CLI and scripts. Errors carry code::not_running with the message
/// "is fettled running? socket X: connection refused" when nobody listens.
class Client {
 public:
  static Result<Client> connect(const std::filesystem::path& socket_path,
                                std::chrono::milliseconds timeout = std::chrono::milliseconds{3000});
  Client(Client&& other) noexcept;
  Client& operator=(Client&& other) noexcept;
  Client(const Client&) = delete;
  Client& operator=(const Client&) = delete;
  ~Client();

  /// Sends one request line and waits for its reply line. The reply may be {"ok":false,...}:
  /// that is still a Result with a value; an Error means the exchange itself failed.
  Result<json> request(const json& request, std::chrono::milliseconds timeout = std::chrono::milliseconds{10000});
  /// Sends raw bytes (for tests of malformed input) and reads one reply line.
  Result<json> request_raw(std::string_view bytes, std::chrono::milliseconds timeout = std::chrono::milliseconds{10000});

  [[nodiscard]] const std::filesystem::path& socket_path() const { return path_; }

 private:
  Client(int fd, std::filesystem::path path) : fd_(fd), path_(std::move(path)) {}
  Result<json> read_reply(std::chrono::milliseconds timeout);
  int fd_ = -1;
  std::filesystem::path path_;
  std::string buffer_;
};

/// The socket a CLI command talks to: `socket` (--socket) if given, else the [control]
/// socket of the cell file `config` (--config), else ControlSection's default
/// (/run/fettle/fettled.sock). Throws config::ConfigError for a bad cell file (setup).
std::filesystem::path socket_for_cli(const std::optional<std::filesystem::path>& socket,
                                     const std::optional<std::filesystem::path>& config);

/// For CLI commands: sends `request` and returns the {"ok":true,...} reply. Throws
/// DeviceError when fettled cannot be reached or does not answer (exit code 3, message
/// "is fettled running? socket X: connection refused"), UserError for permission problems
/// and for an {"ok":false,...} reply ("fettled refused: <error> [<code>]", exit code 1).
json cli_request(const std::filesystem::path& socket, const json& request,
                 std::chrono::milliseconds timeout = std::chrono::milliseconds{10000});

/// A reply value for people: strings bare, null as "-", booleans yes/no, others as JSON.
std::string display_text(const json& value);

/// One request: connects, sends, reads the reply, closes.
Result<json> call(const std::filesystem::path& socket_path, const json& request,
                  std::chrono::milliseconds timeout = std::chrono::milliseconds{10000});

}  // namespace fettle::daemon::control
