#pragma once
// fettled as a systemd service (systemd/fettled.service, docs/service.md):
// sd_notify messages, the watchdog pinged from the event loop, signal hooks, root refusal.
//
//   boost::asio::io_context io;
//   if (auto st = service::check_user(args.allow_root); !st) { std::cerr << st.error().message; return 1; }
//   service::Signals signals{io, [&](int sig) { service::notify_stopping(); daemon.stop(); }};
//   service::Watchdog watchdog{io};          // pings WATCHDOG=1 at half WatchdogSec, if enabled
//   watchdog.start();
//   ... configure ...
//   service::notify_ready("Idle");           // READY=1 + STATUS=Idle
//   service::notify_status("Execute: cycle 42");   // on every state change
//   io.run();
//
// Every notify function is a no-op (returns false) outside systemd, i.e. when
// NOTIFY_SOCKET is not set. Because the watchdog timer runs on the event loop, a stuck
// loop stops the pings and systemd restarts the service.
#include <chrono>
#include <functional>
#include <initializer_list>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include <boost/asio/io_context.hpp>

#include "fettle/core/result.hpp"

namespace fettle::daemon::service {

/// True when systemd (or a test) gave us a notification socket (NOTIFY_SOCKET).
bool under_systemd();

/// Sends a raw sd_notify state string, e.g. "READY=1\nSTATUS=Idle". False if not sent
/// (outside systemd or the send failed).
bool notify(std::string_view state);
bool notify_ready(std::string_view status = {});  ///< READY=1 (+ STATUS=status if not empty)
bool notify_status(std::string_view status);      ///< STATUS=...
bool notify_watchdog();                           ///< WATCHDOG=1
bool notify_stopping(std::string_view status = {});  ///< STOPPING=1 (+ STATUS=...)

/// The watchdog interval systemd expects pings within (WatchdogSec=, via sd_watchdog_enabled:
/// WATCHDOG_USEC and WATCHDOG_PID); nullopt when the watchdog is off.
std::optional<std::chrono::microseconds> watchdog_interval();

/// Pings WATCHDOG=1 from the event loop every interval/2 (the first ping at once).
class Watchdog {
 public:
  /// interval: nullopt = ask systemd (watchdog_interval()); a value forces it (tests).
  explicit Watchdog(boost::asio::io_context& io, std::optional<std::chrono::microseconds> interval = std::nullopt);
  ~Watchdog();
  Watchdog(const Watchdog&) = delete;
  Watchdog& operator=(const Watchdog&) = delete;

  /// Starts pinging; false (and does nothing) when the watchdog is off.
  bool start();
  void stop();
  [[nodiscard]] bool enabled() const;
  [[nodiscard]] std::optional<std::chrono::microseconds> interval() const;
  [[nodiscard]] std::chrono::microseconds ping_period() const;  ///< interval / 2 (0 when off)
  [[nodiscard]] std::size_t pings() const;                      ///< pings sent so far

 private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

/// SIGTERM and SIGINT (and any others asked for) delivered on the event loop: `on_signal`
/// runs on the loop's thread with the signal number, every time one arrives.
class Signals {
 public:
  Signals(boost::asio::io_context& io, std::function<void(int)> on_signal,
          std::initializer_list<int> signals = {});  ///< empty = {SIGTERM, SIGINT}
  ~Signals();
  Signals(const Signals&) = delete;
  Signals& operator=(const Signals&) = delete;
  void cancel();

 private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

/// Refuses to run as root (effective uid 0) unless `allow_root`: an Error (code
/// "service.root") telling to run as the fettle user (systemd unit) or pass --allow-root.
Status check_user(bool allow_root);
/// Same with the uid given (for tests).
Status check_user(bool allow_root, unsigned effective_uid);

}  // namespace fettle::daemon::service
