// PLC link (Modbus TCP): [plc] in the cell file.
#include "fettle/config/plc.hpp"
#include "sections.hpp"

namespace fettle::config::detail {

void read_plc(TableReader& root, PlcSection& p) {
  if (auto t = root.table("plc", Need::required)) {
    t->ipv4("address", p.address, Need::required);
    t->port("port", p.port);
    t->integer("unit_id", p.unit_id, {0, 247});
    t->integer("register_base", p.register_base, {0, 65535 - 64});
    t->integer("response_timeout_ms", p.response_timeout_ms, {1, 60000});
    t->integer("poll_period_ms", p.poll_period_ms, {1, 10000});
    t->integer("heartbeat_timeout_ms", p.heartbeat_timeout_ms, {10, 60000});
    t->integer("reconnect_initial_ms", p.reconnect_initial_ms, {1, 60000});
    t->integer("reconnect_max_ms", p.reconnect_max_ms, {1, 600000});
    if (p.reconnect_initial_ms > p.reconnect_max_ms)
      t->error("reconnect_max_ms",
               "must be at least reconnect_initial_ms (" + std::to_string(p.reconnect_initial_ms) + ")");
  }
}

}  // namespace fettle::config::detail
