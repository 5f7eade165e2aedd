#pragma once
// What the control socket tests share: a temp dir, a handler with known answers (the
// daemon's side of the interface, not a mock of a protocol: the socket and JSON lines are
// real), and a fixture running the Server on an io_context thread.
#include <stdlib.h>
#include <sys/stat.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <future>
#include <optional>
#include <stdexcept>
#include <string>
#include <system_error>
#include <thread>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <gtest/gtest.h>

#include "fettle/daemon/control.hpp"
#include "test_systemd_support.hpp"  // TempDir

namespace fettle::test {

/// Answers like a daemon in Idle with five finished cycles. Runs on the loop thread.
class FakeHandler : public daemon::control::Handler {
 public:
  using json = daemon::control::json;
  std::atomic<int> status_calls{0};
  std::atomic<int> commands{0};  ///< reset/hold/unhold/dry_cycle calls
  std::atomic<bool> throw_on_status{false};
  std::atomic<bool> no_cycles{false};
  std::atomic<bool> refuse_maintenance{false};

  json status() override {
    ++status_calls;
    if (throw_on_status) throw std::runtime_error("status exploded");
    return json{{"state", "Idle"},   {"state_code", 4},     {"fault", nullptr},  {"cycle_id", nullptr},
                {"cycles_total", 5}, {"last_result", "OK"}, {"uptime_s", 3725.0}, {"version", "test"}};
  }
  static json cycle(int i) {
    return json{{"id", "c-000" + std::to_string(i)},
                {"started", "2024-05-0" + std::to_string(i) + "T10:00:00Z"},
                {"result", i == 3 ? "NOK" : "OK"},
                {"duration_s", 40.0 + i},
                {"regions", json::array({json{{"name", "riser"}, {"share_over_0_3_mm", 0.01}}})}};
  }
  Result<json> last_cycle() override {
    if (no_cycles) return Error{"records.unreadable", "journal /var/lib/fettle/journal: unreadable; check the disk"};
    return cycle(5);
  }
  Result<json> cycles(std::size_t limit) override {
    if (no_cycles) return Error{"records.unreadable", "journal /var/lib/fettle/journal: unreadable; check the disk"};
    json a = json::array();
    for (int i = 5; i >= 1 && a.size() < limit; --i) a.push_back(cycle(i));
    return a;
  }
  Result<json> reset() override {
    ++commands;
    return json{{"state", "Resetting"}};
  }
  Result<json> hold() override {
    ++commands;
    return json{{"state", "Holding"}};
  }
  Result<json> unhold() override {
    ++commands;
    return json{{"state", "Unholding"}};
  }
  Result<json> dry_cycle() override {
    ++commands;
    return json{{"cycle_id", "dry-1"}};
  }
  std::string tool_changed_name;  ///< the last tool_changed's tool
  Result<json> tool_changed(const std::string& tool) override {
    ++commands;
    if (tool != "flat-16") return Error{"fettled.unknown_tool", "no recipe has a tool '" + tool + "' (tools: flat-16)"};
    tool_changed_name = tool;
    return json{{"tool", tool}, {"wear_mm", 0.0}};
  }
  Status maintenance_changing(bool on) override {
    if (on && refuse_maintenance) return Error{"packml.busy", "cannot enter maintenance during Execute; hold first"};
    return {};
  }
};

/// A Server on a temp-dir socket, its io_context run by a thread once start() succeeds.
class ControlFixture : public ::testing::Test {
 protected:
  ControlFixture() {
    options.socket_path = dir.path() / "fettled.sock";
    options.idle_timeout = std::chrono::milliseconds{0};
  }
  ~ControlFixture() override { reset_server(); }

  daemon::control::Server& server() {
    if (!server_) server_.emplace(io, handler, options);
    return *server_;
  }
  const std::filesystem::path& socket() const { return options.socket_path; }

  ::testing::AssertionResult start() {
    const auto st = server().start();
    if (!st) return ::testing::AssertionFailure() << st.error().code << ": " << st.error().message;
    thread_ = std::thread([this] { io.run(); });
    return ::testing::AssertionSuccess();
  }
  void stop_loop() {
    work_.reset();
    io.stop();
    if (thread_.joinable()) thread_.join();
  }
  void reset_server() {
    stop_loop();
    server_.reset();
    io.restart();
    io.poll();  // let the closed connections' handlers finish
  }
  /// Connected clients, asked on the loop's thread.
  std::size_t client_count() {
    std::promise<std::size_t> p;
    auto f = p.get_future();
    boost::asio::post(io, [&] { p.set_value(server().client_count()); });
    return f.get();
  }

  TempDir dir;
  FakeHandler handler;
  daemon::control::ServerOptions options;
  boost::asio::io_context io;

 private:
  std::optional<boost::asio::executor_work_guard<boost::asio::io_context::executor_type>> work_{
      boost::asio::make_work_guard(io)};
  std::optional<daemon::control::Server> server_;
  std::thread thread_;
};

}  // namespace fettle::test
