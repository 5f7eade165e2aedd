// Robot controller link (TCP line protocol): [robot] in the cell file.
#include "fettle/config/robot.hpp"
#include "sections.hpp"

#include <string>

namespace fettle::config::detail {

void read_robot(TableReader& root, RobotSection& r) {
  if (auto t = root.table("robot", Need::required)) {
    t->ipv4("address", r.address, Need::required);
    t->port("port", r.port, Need::required);
    // the protocol's ident (docs/robot-protocol.md): one token of at most 32 characters
    t->ident("cell_id", r.cell_id, 32, Need::required);
    t->integer("reply_timeout_ms", r.reply_timeout_ms, kTimeoutMs);
    t->integer("ping_period_ms", r.ping_period_ms, {10, 60000});
    t->integer("missed_pings", r.missed_pings, {1, 100});
    t->integer("chunk_points", r.chunk_points, {1, 1000});
    t->integer("run_timeout_ms", r.run_timeout_ms, kTimeoutMs);
    t->integer("reconnect_initial_ms", r.reconnect_initial_ms, {10, 60000});
    t->integer("reconnect_max_ms", r.reconnect_max_ms, {10, 600000});
    if (r.reconnect_max_ms < r.reconnect_initial_ms)
      t->error("reconnect_max_ms", "reconnect_max_ms (" + std::to_string(r.reconnect_max_ms) +
                                       ") must be at least reconnect_initial_ms (" +
                                       std::to_string(r.reconnect_initial_ms) + ")");
  }
}

}  // namespace fettle::config::detail
