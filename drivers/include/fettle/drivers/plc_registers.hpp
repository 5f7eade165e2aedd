#pragma once
// The PLC register map (Modbus holding registers) and its pure encoding/decoding.
// docs/plc-interface.md is the specification; this header must match it.
//
// Two blocks, addressed from [plc] register_base:
//   offsets 0..9   written by the PLC, read by Fettle   (the "PLC block")
//   offsets 16..25 written by Fettle, read by the PLC   (the "Fettle block")
// Every value read is range-checked; decoding never guesses: a value outside its
// allowed set is returned as a RangeViolation and the block must not be acted upon.
#include <array>
#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "fettle/drivers/packml.hpp"

namespace fettle::drivers::plc {

/// The map version the PLC must report in register `interface_version`.
/// Version 2 adds the PLC's acknowledges of slide commands and results (registers 8 and 9).
inline constexpr int kInterfaceVersion = 2;

/// Register offsets from register_base.
namespace reg {
// PLC → Fettle
inline constexpr int interface_version = 0;
inline constexpr int plc_heartbeat = 1;
inline constexpr int cycle_request_toggle = 2;
inline constexpr int recipe_id = 3;
inline constexpr int slide_state = 4;
inline constexpr int slide_position = 5;
inline constexpr int packml_command = 6;
inline constexpr int packml_command_toggle = 7;
inline constexpr int slide_command_ack = 8;
inline constexpr int cycle_result_ack = 9;
inline constexpr int plc_block_start = 0;
inline constexpr int plc_block_size = 10;
// Fettle → PLC
inline constexpr int fettle_heartbeat = 16;
inline constexpr int cycle_ack_toggle = 17;
inline constexpr int packml_state = 18;
inline constexpr int slide_target = 19;
inline constexpr int slide_command_toggle = 20;
inline constexpr int cycle_result = 21;
inline constexpr int cycle_result_toggle = 22;
inline constexpr int fault_code = 23;
inline constexpr int fault_latched = 24;
inline constexpr int packml_command_ack = 25;
inline constexpr int fettle_block_start = 16;
inline constexpr int fettle_block_size = 10;
/// Registers a PLC must provide from register_base on.
inline constexpr int map_size = 26;
}  // namespace reg

/// The name of the register at this offset ("plc_heartbeat", ...), or "reserved".
std::string_view register_name(int offset);

enum class SlideStatus : std::uint16_t { unknown = 0, at_home = 1, at_position = 2, moving = 3, fault = 4 };
/// The result of a cycle the PLC requested: every accepted request ends in exactly one (fault:
/// the cycle ended in a fault or an Abort; fault_code holds the fault when one latched).
enum class CycleResult : std::uint16_t { none = 0, ok = 1, nok = 2, regrind = 3, fault = 4 };

std::string_view name(SlideStatus s);
std::string_view name(CycleResult r);

/// What the PLC block says, once it passed every range check.
struct PlcInputs {
  int interface_version = kInterfaceVersion;
  std::uint16_t heartbeat = 0;
  int cycle_request_toggle = 0;  ///< 0/1; a change is a new cycle request
  int recipe_id = 0;             ///< 0 = none; 1..65535 the recipe (plc_recipe_id in the cell file)
  SlideStatus slide_status = SlideStatus::unknown;
  int slide_position = 0;  ///< 0 = home, 1..n photo position (with at_position, or the target while moving)
  packml::Command command = packml::Command::none;
  int command_toggle = 0;  ///< 0/1; a change is a new PackML command
  int slide_command_ack = 0;  ///< 0/1; the PLC copies slide_command_toggle once it has taken the command
  int result_ack = 0;         ///< 0/1; the PLC copies cycle_result_toggle once it has read the result

  bool operator==(const PlcInputs&) const = default;
};

/// What Fettle writes to the PLC block.
struct FettleOutputs {
  std::uint16_t heartbeat = 0;
  int cycle_ack_toggle = 0;  ///< copies cycle_request_toggle when Fettle accepts the request
  packml::State state = packml::State::stopped;
  int slide_target = 0;          ///< 0 = home, 1..n photo position
  int slide_command_toggle = 0;  ///< a change commands the slide to slide_target
  CycleResult result = CycleResult::none;
  int result_toggle = 0;  ///< a change publishes a new result
  std::uint16_t fault_code = 0;
  bool fault_latched = false;  ///< set with a fault; cleared only by a PackML Reset from the PLC
  int command_ack_toggle = 0;  ///< copies packml_command_toggle once Fettle has taken the command

  bool operator==(const FettleOutputs&) const = default;
};

/// Site-specific limits a value is checked against.
struct Limits {
  int slide_positions = 16;  ///< photo positions the slide has ([slide] photo_positions_mm)
};

/// A register holding a value that is not allowed: a fault, never a guess.
struct RangeViolation {
  int offset = 0;       ///< from register_base
  int value = 0;        ///< what was read
  std::string allowed;  ///< e.g. "0 to 4"

  bool operator==(const RangeViolation&) const = default;
};

/// "register 4 (slide_state) holds 9; allowed 0 (unknown), 1 (at home), ..."
std::string describe(const RangeViolation& v);

template <class T>
struct Decoded {
  T value{};
  std::vector<RangeViolation> violations;  ///< empty when every register is allowed
  [[nodiscard]] bool ok() const { return violations.empty(); }
};

using PlcBlock = std::array<std::uint16_t, reg::plc_block_size>;
using FettleBlock = std::array<std::uint16_t, reg::fettle_block_size>;

/// Decodes the PLC block (registers plc_block_start.., any length: a wrong length is a
/// violation at the first missing/extra register). Checks every register and the
/// combination of slide state and position.
Decoded<PlcInputs> decode_plc_block(std::span<const std::uint16_t> regs, const Limits& limits);
PlcBlock encode_plc_block(const PlcInputs& in);

/// Decodes the Fettle block (for the PLC side, e.g. the simulator), with the same rigour.
Decoded<FettleOutputs> decode_fettle_block(std::span<const std::uint16_t> regs, const Limits& limits);
FettleBlock encode_fettle_block(const FettleOutputs& out);

/// Reconnect delay before attempt `attempt` (0-based): initial, 2×initial, ... capped at max.
int backoff_delay_ms(int attempt, int initial_ms, int max_ms);

}  // namespace fettle::drivers::plc
