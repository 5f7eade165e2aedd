// sd_notify, the event-loop watchdog, signal hooks and root refusal (see service.hpp).
#include "fettle/daemon/service.hpp"

#include <unistd.h>

#include <csignal>
#include <cstring>
#include <cstdlib>
#include <string>

#include <boost/asio/signal_set.hpp>
#include <boost/asio/steady_timer.hpp>
#include <systemd/sd-daemon.h>

#include "fettle/core/log.hpp"

namespace fettle::daemon::service {

namespace asio = boost::asio;

bool under_systemd() {
  const char* s = std::getenv("NOTIFY_SOCKET");
  return s != nullptr && *s != '\0';
}

bool notify(std::string_view state) {
  if (!under_systemd()) return false;
  const std::string s{state};
  const int r = sd_notify(0, s.c_str());
  if (r < 0) {
    log::get("service")->warn("sd_notify({}) failed: {}", s, std::string{std::strerror(-r)});
    return false;
  }
  return r > 0;
}

bool notify_ready(std::string_view status) {
  std::string s = "READY=1";
  if (!status.empty()) s += "\nSTATUS=" + std::string{status};
  return notify(s);
}

bool notify_status(std::string_view status) { return notify("STATUS=" + std::string{status}); }

bool notify_watchdog() { return notify("WATCHDOG=1"); }

bool notify_stopping(std::string_view status) {
  std::string s = "STOPPING=1";
  if (!status.empty()) s += "\nSTATUS=" + std::string{status};
  return notify(s);
}

std::optional<std::chrono::microseconds> watchdog_interval() {
  uint64_t usec = 0;
  const int r = sd_watchdog_enabled(0, &usec);
  if (r <= 0 || usec == 0) return std::nullopt;
  return std::chrono::microseconds{static_cast<std::chrono::microseconds::rep>(usec)};
}

// ---------------------------------------------------------------------------------------

struct Watchdog::Impl : std::enable_shared_from_this<Impl> {
  explicit Impl(asio::io_context& io) : timer(io) {}
  asio::steady_timer timer;
  std::optional<std::chrono::microseconds> interval;
  std::size_t pings = 0;
  bool running = false;

  void ping_and_arm() {
    if (!running) return;
    if (notify_watchdog()) ++pings;
    timer.expires_after(*interval / 2);
    timer.async_wait([weak = weak_from_this()](const boost::system::error_code& ec) {
      if (ec) return;
      if (auto self = weak.lock()) self->ping_and_arm();
    });
  }
};

Watchdog::Watchdog(asio::io_context& io, std::optional<std::chrono::microseconds> interval)
    : impl_(std::make_shared<Impl>(io)) {
  impl_->interval = interval ? interval : watchdog_interval();
  if (impl_->interval && impl_->interval->count() <= 0) impl_->interval.reset();
}

Watchdog::~Watchdog() { stop(); }

bool Watchdog::start() {
  if (!impl_->interval || impl_->running) return impl_->running;
  impl_->running = true;
  log::get("service")->info("watchdog: pinging systemd every {} ms (WatchdogSec {} ms)",
                            impl_->interval->count() / 2000, impl_->interval->count() / 1000);
  impl_->ping_and_arm();
  return true;
}

void Watchdog::stop() {
  impl_->running = false;
  impl_->timer.cancel();
}

bool Watchdog::enabled() const { return impl_->interval.has_value(); }
std::optional<std::chrono::microseconds> Watchdog::interval() const { return impl_->interval; }
std::chrono::microseconds Watchdog::ping_period() const {
  return impl_->interval ? *impl_->interval / 2 : std::chrono::microseconds{0};
}
std::size_t Watchdog::pings() const { return impl_->pings; }

// ---------------------------------------------------------------------------------------

struct Signals::Impl : std::enable_shared_from_this<Impl> {
  explicit Impl(asio::io_context& io) : set(io) {}
  asio::signal_set set;
  std::function<void(int)> on_signal;

  void wait() {
    set.async_wait([weak = weak_from_this()](const boost::system::error_code& ec, int sig) {
      if (ec) return;
      auto self = weak.lock();
      if (!self) return;
      if (self->on_signal) self->on_signal(sig);
      self->wait();
    });
  }
};

Signals::Signals(asio::io_context& io, std::function<void(int)> on_signal, std::initializer_list<int> signals)
    : impl_(std::make_shared<Impl>(io)) {
  impl_->on_signal = std::move(on_signal);
  if (signals.size() == 0) {
    impl_->set.add(SIGTERM);
    impl_->set.add(SIGINT);
  } else {
    for (int s : signals) impl_->set.add(s);
  }
  impl_->wait();
}

Signals::~Signals() { cancel(); }

void Signals::cancel() {
  boost::system::error_code ec;
  impl_->set.cancel(ec);
  impl_->set.clear(ec);
}

// ---------------------------------------------------------------------------------------

Status check_user(bool allow_root, unsigned effective_uid) {
  if (effective_uid != 0 || allow_root) return {};
  return Error{"service.root",
               "fettled refuses to run as root: run it as its own user (the systemd unit "
               "fettled.service does this; see docs/service.md) or pass --allow-root if you really mean it"};
}

Status check_user(bool allow_root) { return check_user(allow_root, static_cast<unsigned>(::geteuid())); }

}  // namespace fettle::daemon::service
