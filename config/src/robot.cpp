// Robot controller link (TCP line protocol): [robot] in the cell file.
#include "fettle/config/robot.hpp"
#include "sections.hpp"

namespace fettle::config::detail {

void read_robot(TableReader& root, RobotSection& r) {
  if (auto t = root.table("robot", Need::required)) {
    t->ipv4("address", r.address, Need::required);
    t->port("port", r.port, Need::required);
    t->string("cell_id", r.cell_id, Need::required);
    t->integer("reply_timeout_ms", r.reply_timeout_ms, kTimeoutMs);
    t->integer("ping_period_ms", r.ping_period_ms, {10, 60000});
    t->integer("missed_pings", r.missed_pings, {1, 100});
    t->integer("chunk_points", r.chunk_points, {1, 1000});
    t->integer("run_timeout_ms", r.run_timeout_ms, kTimeoutMs);
  }
}

}  // namespace fettle::config::detail
