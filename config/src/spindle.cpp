// Grinding spindle drive (CANopen CiA 402): [spindle] in the cell file.
#include "fettle/config/spindle.hpp"
#include "sections.hpp"

namespace fettle::config::detail {

void read_spindle(TableReader& root, SpindleSection& s) {
  if (auto t = root.table("spindle", Need::required)) {
    t->choice("transport", s.transport, {"socketcan", "socketcand", "sim"});
    // a Linux interface name (IFNAMSIZ), sent to socketcand as one token
    t->ident("interface", s.interface, 15);
    t->ipv4("address", s.address);
    t->port("port", s.port);
    t->integer("node_id", s.node_id, {1, 127});
    t->integer("master_node_id", s.master_node_id, {1, 127});
    t->choice("mode", s.mode, {"profile_velocity", "velocity"});
    t->integer("heartbeat_producer_ms", s.heartbeat_producer_ms, {1, 65535});
    t->integer("heartbeat_timeout_ms", s.heartbeat_timeout_ms, {1, 65535});
    t->integer("sdo_timeout_ms", s.sdo_timeout_ms, {1, 60000});
    t->integer("spin_up_timeout_ms", s.spin_up_timeout_ms, kTimeoutMs);
    t->number("at_speed_tolerance_rpm", s.at_speed_tolerance_rpm, {0.1, 10000.0});
    t->number("max_rpm", s.max_rpm, {1.0, 100000.0});
    if (s.master_node_id == s.node_id)
      t->error("master_node_id", "must differ from node_id (" + std::to_string(s.node_id) +
                                     "): the drive monitors the master's heartbeat under this id");
    if (s.heartbeat_timeout_ms <= s.heartbeat_producer_ms)
      t->error("heartbeat_timeout_ms",
               "must be longer than heartbeat_producer_ms (" + std::to_string(s.heartbeat_producer_ms) + ")");
  }
}

}  // namespace fettle::config::detail
