// CANopen frame codecs (CiA 301 NMT, SDO expedited, EMCY, heartbeat) and CiA 402 states.
#include <cstdio>
#include <string>

#include "fettle/drivers/canopen.hpp"

namespace fettle::canopen {

namespace {

std::string hex(std::uint32_t v, int digits) {
  char buf[16];
  std::snprintf(buf, sizeof buf, "0x%0*X", digits, v);
  return buf;
}

void put_le(CanFrame& f, std::size_t at, std::uint32_t v, std::size_t n) {
  for (std::size_t i = 0; i < n; ++i) f.data[at + i] = static_cast<std::uint8_t>(v >> (8 * i));
}

std::uint32_t get_le(const CanFrame& f, std::size_t at, std::size_t n) {
  std::uint32_t v = 0;
  for (std::size_t i = 0; i < n; ++i) v |= static_cast<std::uint32_t>(f.data[at + i]) << (8 * i);
  return v;
}

CanFrame sdo_frame(std::uint32_t id, std::uint8_t cmd, std::uint16_t index, std::uint8_t sub) {
  CanFrame f;
  f.id = id;
  f.len = 8;
  f.data[0] = cmd;
  put_le(f, 1, index, 2);
  f.data[3] = sub;
  return f;
}

std::uint8_t expedited_bits(std::uint8_t size) {
  // n (bytes not holding data) in bits 2-3, e (expedited) and s (size indicated).
  return static_cast<std::uint8_t>(((4U - size) << 2) | 0x03U);
}

}  // namespace

CanFrame CanFrame::make(std::uint32_t id, std::initializer_list<std::uint8_t> bytes) {
  CanFrame f;
  f.id = id;
  for (auto b : bytes) {
    if (f.len == 8) break;
    f.data[f.len++] = b;
  }
  return f;
}

std::string to_string(const CanFrame& f) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f.extended ? "%08X [%u]" : "%03X [%u]", f.id, static_cast<unsigned>(f.len));
  std::string s = buf;
  if (f.rtr) s += " RTR";
  if (f.error) s += " ERROR";
  for (std::size_t i = 0; i < f.len && i < 8; ++i) {
    std::snprintf(buf, sizeof buf, " %02X", static_cast<unsigned>(f.data[i]));
    s += buf;
  }
  return s;
}

CanFrame nmt_frame(NmtCommand cmd, std::uint8_t node_id) {
  return CanFrame::make(kNmtId, {static_cast<std::uint8_t>(cmd), node_id});
}

CanFrame heartbeat_frame(std::uint8_t node_id, NmtState state) {
  return CanFrame::make(kHeartbeatBase + node_id, {static_cast<std::uint8_t>(state)});
}

std::string to_string(NmtState s) {
  switch (s) {
    case NmtState::boot_up: return "boot-up";
    case NmtState::stopped: return "stopped";
    case NmtState::operational: return "operational";
    case NmtState::pre_operational: return "pre-operational";
  }
  return "unknown (" + hex(static_cast<std::uint32_t>(s), 2) + ")";
}

CanFrame sdo_download_request(std::uint8_t node_id, std::uint16_t index, std::uint8_t sub, std::uint32_t value,
                              std::uint8_t size) {
  if (size < 1 || size > 4) size = 4;
  auto f = sdo_frame(kSdoRxBase + node_id, static_cast<std::uint8_t>(0x20U | expedited_bits(size)), index, sub);
  put_le(f, 4, value, size);
  return f;
}

CanFrame sdo_upload_request(std::uint8_t node_id, std::uint16_t index, std::uint8_t sub) {
  return sdo_frame(kSdoRxBase + node_id, 0x40, index, sub);
}

CanFrame sdo_download_response(std::uint8_t node_id, std::uint16_t index, std::uint8_t sub) {
  return sdo_frame(kSdoTxBase + node_id, 0x60, index, sub);
}

CanFrame sdo_upload_response(std::uint8_t node_id, std::uint16_t index, std::uint8_t sub, std::uint32_t value,
                             std::uint8_t size) {
  if (size < 1 || size > 4) size = 4;
  auto f = sdo_frame(kSdoTxBase + node_id, static_cast<std::uint8_t>(0x40U | expedited_bits(size)), index, sub);
  put_le(f, 4, value, size);
  return f;
}

CanFrame sdo_abort(std::uint8_t node_id, bool to_server, std::uint16_t index, std::uint8_t sub, std::uint32_t code) {
  auto f = sdo_frame((to_server ? kSdoRxBase : kSdoTxBase) + node_id, 0x80, index, sub);
  put_le(f, 4, code, 4);
  return f;
}

std::optional<SdoMessage> decode_sdo(const CanFrame& f, bool from_client) {
  if (f.len != 8 || f.rtr || f.error || f.extended) return std::nullopt;
  SdoMessage m;
  const std::uint8_t cmd = f.data[0];
  const unsigned cs = cmd >> 5U;
  m.index = static_cast<std::uint16_t>(get_le(f, 1, 2));
  m.subindex = f.data[3];
  const bool expedited = (cmd & 0x02U) != 0;
  const bool size_indicated = (cmd & 0x01U) != 0;
  const auto size = static_cast<std::uint8_t>(size_indicated ? 4U - ((cmd >> 2U) & 0x03U) : 4U);
  if (cs == 4) {
    m.kind = SdoMessage::Kind::abort;
    m.value = get_le(f, 4, 4);
    return m;
  }
  if (from_client) {
    if (cs == 1) {
      m.kind = expedited ? SdoMessage::Kind::download_request : SdoMessage::Kind::other;
      m.size = expedited && size_indicated ? size : 0;
      if (expedited) m.value = get_le(f, 4, size);
    } else if (cs == 2) {
      m.kind = SdoMessage::Kind::upload_request;
    }
  } else {
    if (cs == 3) {
      m.kind = SdoMessage::Kind::download_response;
    } else if (cs == 2) {
      if (expedited) {
        m.kind = SdoMessage::Kind::upload_response;
        m.size = size_indicated ? size : 0;
        m.value = get_le(f, 4, size);
      } else {
        m.kind = SdoMessage::Kind::upload_segmented;
      }
    }
  }
  return m;
}

std::string abort_code_text(std::uint32_t code) {
  switch (code) {
    case 0x05030000: return "toggle bit not alternated";
    case 0x05040000: return "SDO protocol timed out";
    case 0x05040001: return "client/server command specifier not valid or unknown";
    case 0x05040002: return "invalid block size";
    case 0x05040003: return "invalid sequence number";
    case 0x05040004: return "CRC error";
    case 0x05040005: return "out of memory";
    case 0x06010000: return "unsupported access to an object";
    case 0x06010001: return "attempt to read a write-only object";
    case 0x06010002: return "attempt to write a read-only object";
    case 0x06020000: return "object does not exist in the object dictionary";
    case 0x06040041: return "object cannot be mapped to the PDO";
    case 0x06040042: return "the number and length of the objects to be mapped would exceed PDO length";
    case 0x06040043: return "general parameter incompatibility";
    case 0x06040047: return "general internal incompatibility in the device";
    case 0x06060000: return "access failed due to a hardware error";
    case 0x06070010: return "data type does not match, length of service parameter does not match";
    case 0x06070012: return "data type does not match, length of service parameter too high";
    case 0x06070013: return "data type does not match, length of service parameter too low";
    case 0x06090011: return "sub-index does not exist";
    case 0x06090030: return "invalid value for parameter (download only)";
    case 0x06090031: return "value of parameter written too high (download only)";
    case 0x06090032: return "value of parameter written too low (download only)";
    case 0x06090036: return "maximum value is less than minimum value";
    case 0x060A0023: return "resource not available: SDO connection";
    case 0x08000000: return "general error";
    case 0x08000020: return "data cannot be transferred or stored to the application";
    case 0x08000021: return "data cannot be transferred or stored to the application because of local control";
    case 0x08000022:
      return "data cannot be transferred or stored to the application because of the present device state";
    case 0x08000023: return "object dictionary dynamic generation fails or no object dictionary is present";
    case 0x08000024: return "no data available";
    default: return "unknown abort code";
  }
}

CanFrame emcy_frame(std::uint8_t node_id, const Emergency& e) {
  CanFrame f;
  f.id = kEmcyBase + node_id;
  f.len = 8;
  put_le(f, 0, e.error_code, 2);
  f.data[2] = e.error_register;
  for (std::size_t i = 0; i < 5; ++i) f.data[3 + i] = e.manufacturer[i];
  return f;
}

std::optional<Emergency> decode_emcy(const CanFrame& f) {
  if (f.len < 3 || f.rtr || f.error) return std::nullopt;
  Emergency e;
  e.error_code = static_cast<std::uint16_t>(get_le(f, 0, 2));
  e.error_register = f.data[2];
  for (std::size_t i = 0; i < 5 && 3 + i < f.len; ++i) e.manufacturer[i] = f.data[3 + i];
  return e;
}

std::string emcy_code_text(std::uint16_t code) {
  switch (code) {
    case 0x0000: return "error reset or no error";
    case 0x1000: return "generic error";
    case 0x2310: return "continuous over-current";
    case 0x2320: return "short circuit or earth leakage";
    case 0x3210: return "DC link over-voltage";
    case 0x3220: return "DC link under-voltage";
    case 0x4210: return "excess temperature of the device";
    case 0x4310: return "excess temperature of the drive";
    case 0x5000: return "device hardware";
    case 0x6000: return "device software";
    case 0x7000: return "additional modules";
    case 0x8110: return "CAN overrun (objects lost)";
    case 0x8120: return "CAN in error passive mode";
    case 0x8130: return "life guard error or heartbeat error";
    case 0x8140: return "recovered from bus off";
    case 0x8611: return "following error";
    case 0x9000: return "external error";
    default: break;
  }
  switch (code & 0xF000U) {
    case 0x1000: return "generic error";
    case 0x2000: return "current";
    case 0x3000: return "voltage";
    case 0x4000: return "temperature";
    case 0x5000: return "device hardware";
    case 0x6000: return "device software";
    case 0x7000: return "additional modules";
    case 0x8000: return "monitoring";
    case 0x9000: return "external error";
    case 0xF000: return (code & 0xFF00U) == 0xFF00U ? "device specific" : "additional functions";
    default: return "unknown error code";
  }
}

std::string describe(const Emergency& e) {
  std::string s = hex(e.error_code, 4) + " " + emcy_code_text(e.error_code) + " (error register " +
                   hex(e.error_register, 2);
  static constexpr const char* kBits[8] = {"generic",       "current", "voltage",          "temperature",
                                           "communication", "profile", "reserved", "manufacturer"};
  std::string bits;
  for (unsigned b = 0; b < 8; ++b)
    if ((e.error_register >> b) & 1U) bits += (bits.empty() ? "" : ", ") + std::string(kBits[b]);
  if (!bits.empty()) s += ": " + bits;
  return s + ")";
}

DriveState decode_statusword(std::uint16_t sw) {
  if ((sw & 0x4FU) == 0x00U) return DriveState::not_ready_to_switch_on;
  if ((sw & 0x4FU) == 0x40U) return DriveState::switch_on_disabled;
  if ((sw & 0x6FU) == 0x21U) return DriveState::ready_to_switch_on;
  if ((sw & 0x6FU) == 0x23U) return DriveState::switched_on;
  if ((sw & 0x6FU) == 0x27U) return DriveState::operation_enabled;
  if ((sw & 0x6FU) == 0x07U) return DriveState::quick_stop_active;
  if ((sw & 0x4FU) == 0x0FU) return DriveState::fault_reaction_active;
  if ((sw & 0x4FU) == 0x08U) return DriveState::fault;
  return DriveState::unknown;
}

std::uint16_t statusword_of(DriveState s) {
  switch (s) {
    case DriveState::not_ready_to_switch_on: return 0x0000;
    case DriveState::switch_on_disabled: return 0x0040;
    case DriveState::ready_to_switch_on: return 0x0021;
    case DriveState::switched_on: return 0x0023;
    case DriveState::operation_enabled: return 0x0027;
    case DriveState::quick_stop_active: return 0x0007;
    case DriveState::fault_reaction_active: return 0x000F;
    case DriveState::fault: return 0x0008;
    case DriveState::unknown: return 0x0000;
  }
  return 0;
}

std::string to_string(DriveState s) {
  switch (s) {
    case DriveState::not_ready_to_switch_on: return "not ready to switch on";
    case DriveState::switch_on_disabled: return "switch on disabled";
    case DriveState::ready_to_switch_on: return "ready to switch on";
    case DriveState::switched_on: return "switched on";
    case DriveState::operation_enabled: return "operation enabled";
    case DriveState::quick_stop_active: return "quick stop active";
    case DriveState::fault_reaction_active: return "fault reaction active";
    case DriveState::fault: return "fault";
    case DriveState::unknown: return "unknown";
  }
  return "unknown";
}

}  // namespace fettle::canopen
