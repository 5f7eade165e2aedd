#pragma once
// Helpers for the spindle tests: run an io_context until something holds.
#include <chrono>
#include <functional>
#include <optional>

#include <boost/asio/io_context.hpp>

#include "fettle/core/result.hpp"

namespace fettle::test {

/// Runs `io` until `done()` is true or `timeout` passes; returns done().
inline bool run_until(boost::asio::io_context& io, const std::function<bool()>& done,
                      std::chrono::milliseconds timeout = std::chrono::milliseconds(3000)) {
  const auto end = std::chrono::steady_clock::now() + timeout;
  while (!done() && std::chrono::steady_clock::now() < end) {
    if (io.stopped()) io.restart();
    io.run_for(std::chrono::milliseconds(5));
  }
  return done();
}

/// Runs `io` for a fixed time (to let the simulated drive move).
inline void run_for(boost::asio::io_context& io, std::chrono::milliseconds d) {
  run_until(io, [] { return false; }, d);
}

/// Captures the Status an asynchronous call completes with.
struct Completion {
  std::optional<Status> status;
  std::function<void(Status)> handler() {
    return [this](Status s) { status = std::move(s); };
  }
  bool done() const { return status.has_value(); }
};

/// Starts `call(handler)` and runs `io` until it completes (or timeout); returns the Status.
inline Status await(boost::asio::io_context& io, const std::function<void(std::function<void(Status)>)>& call,
                    std::chrono::milliseconds timeout = std::chrono::milliseconds(5000)) {
  Completion c;
  call(c.handler());
  if (!run_until(io, [&] { return c.done(); }, timeout))
    return Error{"test.no_completion", "the operation did not complete within the test's time limit"};
  return *c.status;
}

}  // namespace fettle::test
