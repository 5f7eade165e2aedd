#pragma once
// CANopen (CiA 301) and the drive profile (CiA 402): the pieces of the protocol the spindle
// master and the simulated drive share. Pure functions on frames, no I/O.
// See docs/spindle-canopen.md.
#include <array>
#include <cstdint>
#include <optional>
#include <string>

#include "fettle/core/result.hpp"

namespace fettle::canopen {

/// One classic CAN frame (11-bit or 29-bit identifier, up to 8 data bytes).
struct CanFrame {
  std::uint32_t id = 0;  ///< identifier without flag bits
  std::uint8_t len = 0;  ///< data length 0..8
  std::array<std::uint8_t, 8> data{};
  bool extended = false;  ///< 29-bit identifier
  bool rtr = false;       ///< remote transmission request
  bool error = false;     ///< a SocketCAN error frame (id holds the CAN_ERR_* class bits)

  static CanFrame make(std::uint32_t id, std::initializer_list<std::uint8_t> bytes);
  bool operator==(const CanFrame&) const = default;
};

/// "601 [8] 2B 40 60 00 06 00 00 00" for logs.
std::string to_string(const CanFrame& f);

// ---- COB-IDs (predefined connection set) ----
inline constexpr std::uint32_t kNmtId = 0x000;
inline constexpr std::uint32_t kEmcyBase = 0x080;
inline constexpr std::uint32_t kTpdo1Base = 0x180;
inline constexpr std::uint32_t kSdoTxBase = 0x580;  ///< server → client (drive → master)
inline constexpr std::uint32_t kSdoRxBase = 0x600;  ///< client → server (master → drive)
inline constexpr std::uint32_t kHeartbeatBase = 0x700;

// ---- NMT ----
enum class NmtCommand : std::uint8_t {
  start = 0x01,
  stop = 0x02,
  enter_pre_operational = 0x80,
  reset_node = 0x81,
  reset_communication = 0x82,
};
/// NMT states as sent in heartbeats.
enum class NmtState : std::uint8_t { boot_up = 0x00, stopped = 0x04, operational = 0x05, pre_operational = 0x7F };
CanFrame nmt_frame(NmtCommand cmd, std::uint8_t node_id);  ///< node_id 0 = all nodes
CanFrame heartbeat_frame(std::uint8_t node_id, NmtState state);
std::string to_string(NmtState s);

// ---- SDO (expedited transfers only) ----
/// What an SDO frame says, decoded.
struct SdoMessage {
  enum class Kind {
    download_request,    ///< client: write value (expedited)
    download_response,   ///< server: write acknowledged
    upload_request,      ///< client: read
    upload_response,     ///< server: value (expedited)
    upload_segmented,    ///< server: wants a segmented upload (not supported here)
    abort,               ///< either side: abort with a code
    other,               ///< anything else (segments, block transfers)
  };
  Kind kind = Kind::other;
  std::uint16_t index = 0;
  std::uint8_t subindex = 0;
  std::uint32_t value = 0;  ///< little-endian data, or the abort code
  std::uint8_t size = 0;    ///< bytes of data (1..4) when indicated, 0 if not
};
CanFrame sdo_download_request(std::uint8_t node_id, std::uint16_t index, std::uint8_t sub, std::uint32_t value,
                              std::uint8_t size);
CanFrame sdo_upload_request(std::uint8_t node_id, std::uint16_t index, std::uint8_t sub);
CanFrame sdo_download_response(std::uint8_t node_id, std::uint16_t index, std::uint8_t sub);
CanFrame sdo_upload_response(std::uint8_t node_id, std::uint16_t index, std::uint8_t sub, std::uint32_t value,
                             std::uint8_t size);
/// An abort; `to_server` picks the COB-ID (0x600+node from the client, 0x580+node from the server).
CanFrame sdo_abort(std::uint8_t node_id, bool to_server, std::uint16_t index, std::uint8_t sub, std::uint32_t code);
/// Decodes an SDO frame as seen by the server (`from_client` = true) or by the client.
std::optional<SdoMessage> decode_sdo(const CanFrame& f, bool from_client);

/// SDO abort codes (CiA 301, 7.2.4.3.17).
namespace abort_code {
inline constexpr std::uint32_t toggle_bit = 0x05030000;
inline constexpr std::uint32_t timeout = 0x05040000;
inline constexpr std::uint32_t bad_command = 0x05040001;
inline constexpr std::uint32_t unsupported_access = 0x06010000;
inline constexpr std::uint32_t write_only = 0x06010001;
inline constexpr std::uint32_t read_only = 0x06010002;
inline constexpr std::uint32_t no_object = 0x06020000;
inline constexpr std::uint32_t not_mappable = 0x06040041;
inline constexpr std::uint32_t pdo_too_long = 0x06040042;
inline constexpr std::uint32_t length_mismatch = 0x06070010;
inline constexpr std::uint32_t no_subindex = 0x06090011;
inline constexpr std::uint32_t value_range = 0x06090030;
inline constexpr std::uint32_t general = 0x08000000;
inline constexpr std::uint32_t local_control = 0x08000021;
inline constexpr std::uint32_t device_state = 0x08000022;
}  // namespace abort_code
/// The CiA 301 text of an abort code ("object does not exist in the object dictionary").
std::string abort_code_text(std::uint32_t code);

// ---- EMCY ----
struct Emergency {
  std::uint16_t error_code = 0;     ///< CiA 301/402 error code, 0x0000 = error reset / no error
  std::uint8_t error_register = 0;  ///< object 0x1001
  std::array<std::uint8_t, 5> manufacturer{};
};
CanFrame emcy_frame(std::uint8_t node_id, const Emergency& e);
std::optional<Emergency> decode_emcy(const CanFrame& f);
/// "0x2310 continuous over-current (register 0x03: generic, current)".
std::string describe(const Emergency& e);
/// The text of an emergency error code (CiA 301 classes, CiA 402 specifics).
std::string emcy_code_text(std::uint16_t code);

// ---- CiA 402 ----
namespace od {
inline constexpr std::uint16_t error_register = 0x1001;
inline constexpr std::uint16_t consumer_heartbeat_time = 0x1016;
inline constexpr std::uint16_t producer_heartbeat_time = 0x1017;
inline constexpr std::uint16_t identity = 0x1018;
inline constexpr std::uint16_t tpdo1_communication = 0x1800;
inline constexpr std::uint16_t tpdo1_mapping = 0x1A00;
inline constexpr std::uint16_t controlword = 0x6040;
inline constexpr std::uint16_t statusword = 0x6041;
inline constexpr std::uint16_t vl_target_velocity = 0x6042;
inline constexpr std::uint16_t vl_velocity_actual = 0x6044;
inline constexpr std::uint16_t error_code = 0x603F;  ///< CiA 402: the code of the active fault, 0 = none
inline constexpr std::uint16_t modes_of_operation = 0x6060;
inline constexpr std::uint16_t modes_of_operation_display = 0x6061;
inline constexpr std::uint16_t velocity_actual = 0x606C;
inline constexpr std::uint16_t motor_rated_current = 0x6075;
inline constexpr std::uint16_t current_actual = 0x6078;
inline constexpr std::uint16_t target_velocity = 0x60FF;
}  // namespace od

/// CiA 301 emergency code "life guard error or heartbeat error": the drive lost its master.
inline constexpr std::uint16_t kHeartbeatErrorCode = 0x8130;

enum class OperationMode : std::int8_t { velocity = 2, profile_velocity = 3 };

/// Drive states of the CiA 402 power state machine.
enum class DriveState {
  not_ready_to_switch_on,
  switch_on_disabled,
  ready_to_switch_on,
  switched_on,
  operation_enabled,
  quick_stop_active,
  fault_reaction_active,
  fault,
  unknown,
};
DriveState decode_statusword(std::uint16_t statusword);
std::string to_string(DriveState s);
/// Statusword bits.
inline constexpr std::uint16_t kStatusTargetReached = 1U << 10;
inline constexpr std::uint16_t kStatusRemote = 1U << 9;
inline constexpr std::uint16_t kStatusWarning = 1U << 7;
/// Statusword of a state (the drive side; with `extra` bits or'ed in).
std::uint16_t statusword_of(DriveState s);

/// Controlword commands.
namespace controlword {
inline constexpr std::uint16_t disable_voltage = 0x0000;
inline constexpr std::uint16_t quick_stop = 0x0002;
inline constexpr std::uint16_t shutdown = 0x0006;
inline constexpr std::uint16_t switch_on = 0x0007;
inline constexpr std::uint16_t enable_operation = 0x000F;
inline constexpr std::uint16_t fault_reset = 0x0080;
}  // namespace controlword

}  // namespace fettle::canopen
