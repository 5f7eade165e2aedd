// Fuzz target: the control socket's JSON-lines protocol (daemon/control.hpp), exactly what a
// connection does with the bytes a local client sends, without the socket: line framing
// (control::LineProtocol, oversize lines, CR LF, blank lines), JSON parsing and the Server's
// request handling (commands, arguments, maintenance mode, the "id" echo) over a handler that
// answers like fettled does.
//
// Input: byte 0 = the read size the bytes arrive in (1..64), bytes 1-2 = max_line_bytes
// (16..1039), byte 3 bit 0 = maintenance mode at the start; the rest is the stream.
// Invariants: every reply is one line holding a JSON object with a boolean "ok"; a refusal
// carries a non-empty "error" and a "code"; the replies do not depend on how the stream is split into reads; no more replies than lines (+ oversize
// pieces); the handler never sees a refused command.
#include <algorithm>
#include <cstdint>
#include <string>
#include <string_view>

#include <boost/asio/io_context.hpp>

#include "fettle/daemon/control.hpp"
#include "fuzz_input.hpp"

namespace control = fettle::daemon::control;
using control::json;

namespace {

/// Answers like fettled's Runtime: status fields, cycles, PackML commands; counts the calls.
class Handler final : public control::Handler {
 public:
  json status() override {
    ++calls;
    return json{{"state", "Execute"}, {"state_code", 6}, {"fault", nullptr}, {"cycles_total", 3}};
  }
  fettle::Result<json> last_cycle() override {
    ++calls;
    return json{{"id", "20261201-000000-0001"}, {"result", "OK"}};
  }
  fettle::Result<json> cycles(std::size_t limit) override {
    ++calls;
    FUZZ_CHECK(limit > 0);
    json a = json::array();
    for (std::size_t i = 0; i < std::min<std::size_t>(limit, 3); ++i) a.push_back(json{{"id", std::to_string(i)}});
    return a;
  }
  fettle::Result<json> reset() override { return command(); }
  fettle::Result<json> hold() override { return command(); }
  fettle::Result<json> unhold() override { return command(); }
  fettle::Result<json> dry_cycle() override {
    FUZZ_CHECK(maintenance_seen);
    ++calls;
    return fettle::Error{"fettled.busy", "cycle 1 is running; try again when it ends"};
  }
  fettle::Status maintenance_changing(bool on) override {
    maintenance_seen = on;
    return {};
  }

  int calls = 0;
  bool maintenance_seen = false;

 private:
  fettle::Result<json> command() {
    FUZZ_CHECK(maintenance_seen);  // the Server refuses these outside maintenance mode
    ++calls;
    return json{{"state", "Resetting"}};
  }
};

/// Feeds `stream` in reads of `chunk` bytes; returns every reply.
std::string run(std::string_view stream, std::size_t chunk, std::size_t max_line, bool maintenance) {
  boost::asio::io_context io;
  Handler handler;
  handler.maintenance_seen = maintenance;
  control::ServerOptions options;
  options.max_line_bytes = max_line;
  options.maintenance = maintenance;
  control::Server server{io, handler, options};
  control::LineProtocol protocol{[&](const json& r) { return server.handle(r); }, max_line};
  std::string out;
  for (std::size_t at = 0; at < stream.size(); at += chunk)
    if (!protocol.consume(stream.substr(at, chunk), out, std::size_t{1} << 24)) break;
  return out;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fettle::fuzz::ByteReader in(data, size);
  const std::size_t chunk = in.take<std::uint8_t>() % 64U + 1U;
  const std::size_t max_line = in.take<std::uint16_t>() % 1024U + 16U;
  const bool maintenance = in.take_bool();
  const std::string_view stream = in.rest();

  const std::string out = run(stream, chunk, max_line, maintenance);
  FUZZ_CHECK(out.empty() || out.back() == '\n');
  // The split into reads must not matter.
  FUZZ_CHECK(run(stream, stream.size() + 1, max_line, maintenance) == out);

  std::size_t newlines = 0;
  for (char c : stream) newlines += c == '\n' ? 1U : 0U;
  std::size_t replies = 0;
  std::string_view rest = out;
  while (!rest.empty()) {
    const auto nl = rest.find('\n');
    FUZZ_CHECK(nl != std::string_view::npos);
    const json reply = json::parse(rest.substr(0, nl), nullptr, false);
    FUZZ_CHECK(reply.is_object());
    FUZZ_CHECK(reply.contains("ok") && reply["ok"].is_boolean());
    if (!reply["ok"].get<bool>()) {
      FUZZ_CHECK(reply.contains("error") && reply["error"].is_string() && !reply["error"].get<std::string>().empty());
      FUZZ_CHECK(reply.contains("code") && reply["code"].is_string());
    }
    ++replies;
    rest.remove_prefix(nl + 1);
  }
  FUZZ_CHECK(replies <= newlines + stream.size() / max_line + 1);
  return 0;
}
