#pragma once
// Test helper: runs an io_context on a thread (as the daemon will) and records the PLC
// link's events, so tests can wait for a specific event with a deadline.
#include <gtest/gtest.h>

#include <chrono>
#include <condition_variable>
#include <functional>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>

#include "fettle/drivers/plc_link.hpp"

namespace fettle::test {

namespace plc = drivers::plc;

class EventLog {
 public:
  EventLog() : work_(boost::asio::make_work_guard(io_)), thread_([this] { io_.run(); }) {}
  ~EventLog() {
    work_.reset();
    io_.stop();
    thread_.join();
  }
  EventLog(const EventLog&) = delete;
  EventLog& operator=(const EventLog&) = delete;

  boost::asio::any_io_executor executor() { return io_.get_executor(); }
  plc::Link::Handler handler() {
    return [this](const plc::Event& e) {
      EXPECT_TRUE(io_.get_executor().running_in_this_thread()) << "event delivered off the executor";
      std::lock_guard lock(mutex_);
      events_.push_back(e);
      cv_.notify_all();
    };
  }

  /// Waits for the next event (from the current read position on) of type T satisfying
  /// `pred`; events before it are skipped. Returns it, or nothing after `timeout`.
  template <class T>
  std::optional<T> wait_for(
      std::chrono::milliseconds timeout, const std::function<bool(const T&)>& pred = [](const T&) { return true; }) {
    std::unique_lock lock(mutex_);
    std::optional<T> found;
    cv_.wait_for(lock, timeout, [&] {
      for (; cursor_ < events_.size(); ++cursor_) {
        if (const auto* e = std::get_if<T>(&events_[cursor_]); e != nullptr && pred(*e)) {
          found = *e;
          ++cursor_;
          return true;
        }
      }
      return false;
    });
    return found;
  }

  /// The first event of type T ever received (whatever the read position), waiting up to `timeout`.
  template <class T>
  std::optional<T> first(std::chrono::milliseconds timeout) {
    std::unique_lock lock(mutex_);
    std::optional<T> found;
    cv_.wait_for(lock, timeout, [&] {
      for (const auto& e : events_)
        if (const auto* t = std::get_if<T>(&e)) {
          found = *t;
          return true;
        }
      return false;
    });
    return found;
  }

  /// Every event so far of type T.
  template <class T>
  std::vector<T> all() {
    std::lock_guard lock(mutex_);
    std::vector<T> out;
    for (const auto& e : events_)
      if (const auto* t = std::get_if<T>(&e)) out.push_back(*t);
    return out;
  }

  /// Events after the read position, for failure messages.
  std::string dump() {
    std::lock_guard lock(mutex_);
    std::string s;
    for (const auto& e : events_) s += "  " + plc::describe(e) + "\n";
    return s;
  }

  /// Moves the read position to the end (later waits see only newer events).
  void skip_all() {
    std::lock_guard lock(mutex_);
    cursor_ = events_.size();
  }

 private:
  boost::asio::io_context io_;
  boost::asio::executor_work_guard<boost::asio::io_context::executor_type> work_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::vector<plc::Event> events_;
  std::size_t cursor_ = 0;
};

/// Short timings so fault tests stay fast.
inline plc::LinkOptions fast_options(int port) {
  plc::LinkOptions o;
  o.address = "127.0.0.1";
  o.port = port;
  o.response_timeout_ms = 150;
  o.poll_period_ms = 10;
  o.heartbeat_timeout_ms = 300;
  o.reconnect_initial_ms = 20;
  o.reconnect_max_ms = 160;
  o.limits.slide_positions = 2;
  return o;
}

}  // namespace fettle::test
