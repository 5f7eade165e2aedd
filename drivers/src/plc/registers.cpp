// PLC register map: pure encoding/decoding with range checks (see docs/plc-interface.md).
#include <algorithm>
#include <string>

#include "fettle/drivers/plc_registers.hpp"

namespace fettle::drivers::plc {

std::string_view register_name(int offset) {
  switch (offset) {
    case reg::interface_version: return "interface_version";
    case reg::plc_heartbeat: return "plc_heartbeat";
    case reg::cycle_request_toggle: return "cycle_request_toggle";
    case reg::recipe_id: return "recipe_id";
    case reg::slide_state: return "slide_state";
    case reg::slide_position: return "slide_position";
    case reg::packml_command: return "packml_command";
    case reg::packml_command_toggle: return "packml_command_toggle";
    case reg::slide_command_ack: return "slide_command_ack";
    case reg::cycle_result_ack: return "cycle_result_ack";
    case reg::fettle_heartbeat: return "fettle_heartbeat";
    case reg::cycle_ack_toggle: return "cycle_ack_toggle";
    case reg::packml_state: return "packml_state";
    case reg::slide_target: return "slide_target";
    case reg::slide_command_toggle: return "slide_command_toggle";
    case reg::cycle_result: return "cycle_result";
    case reg::cycle_result_toggle: return "cycle_result_toggle";
    case reg::fault_code: return "fault_code";
    case reg::fault_latched: return "fault_latched";
    case reg::packml_command_ack: return "packml_command_ack";
    default: return "reserved";
  }
}

std::string_view name(SlideStatus s) {
  switch (s) {
    case SlideStatus::unknown: return "unknown";
    case SlideStatus::at_home: return "at home";
    case SlideStatus::at_position: return "at position";
    case SlideStatus::moving: return "moving";
    case SlideStatus::fault: return "fault";
  }
  return "?";
}

std::string_view name(CycleResult r) {
  switch (r) {
    case CycleResult::none: return "none";
    case CycleResult::ok: return "OK";
    case CycleResult::nok: return "NOK";
    case CycleResult::regrind: return "re-grind";
    case CycleResult::fault: return "FAULT";
  }
  return "?";
}

std::string describe(const RangeViolation& v) {
  return "register " + std::to_string(v.offset) + " (" + std::string(register_name(v.offset)) + ") holds " +
         std::to_string(v.value) + "; allowed " + v.allowed;
}

namespace {

class Checker {
 public:
  Checker(std::span<const std::uint16_t> regs, int first_offset, std::vector<RangeViolation>& out)
      : regs_(regs), first_(first_offset), out_(out) {}

  /// The register's value if it lies in [lo, hi], else records a violation and returns lo.
  int range(int offset, int lo, int hi, const std::string& allowed) {
    const int v = regs_[static_cast<std::size_t>(offset - first_)];
    if (v < lo || v > hi) {
      out_.push_back({offset, v, allowed});
      return lo;
    }
    return v;
  }
  int raw(int offset) const { return regs_[static_cast<std::size_t>(offset - first_)]; }

 private:
  std::span<const std::uint16_t> regs_;
  int first_;
  std::vector<RangeViolation>& out_;
};

std::string positions_text(int n) { return "0 (home) to " + std::to_string(n) + " (photo positions)"; }

bool check_length(std::span<const std::uint16_t> regs, int first, int size, std::vector<RangeViolation>& out) {
  if (static_cast<int>(regs.size()) == size) return true;
  const int at = first + std::min(static_cast<int>(regs.size()), size);
  out.push_back({at, static_cast<int>(regs.size()), "a block of exactly " + std::to_string(size) + " registers"});
  return false;
}

constexpr const char* kToggle = "0 or 1";

}  // namespace

Decoded<PlcInputs> decode_plc_block(std::span<const std::uint16_t> regs, const Limits& limits) {
  Decoded<PlcInputs> d;
  if (!check_length(regs, reg::plc_block_start, reg::plc_block_size, d.violations)) return d;
  Checker c(regs, reg::plc_block_start, d.violations);
  auto& in = d.value;
  in.interface_version = c.range(reg::interface_version, kInterfaceVersion, kInterfaceVersion,
                                 std::to_string(kInterfaceVersion) + " (this map's version)");
  in.heartbeat = static_cast<std::uint16_t>(c.raw(reg::plc_heartbeat));
  in.cycle_request_toggle = c.range(reg::cycle_request_toggle, 0, 1, kToggle);
  in.recipe_id = c.raw(reg::recipe_id);
  in.slide_status = static_cast<SlideStatus>(
      c.range(reg::slide_state, 0, 4, "0 (unknown), 1 (at home), 2 (at position), 3 (moving), 4 (fault)"));
  const int n = std::clamp(limits.slide_positions, 1, 0xFFFF);
  const auto before = d.violations.size();
  in.slide_position = c.range(reg::slide_position, 0, n, positions_text(n));
  if (d.violations.size() == before) {
    // The position must agree with the state.
    if (in.slide_status == SlideStatus::at_home && in.slide_position != 0)
      d.violations.push_back({reg::slide_position, in.slide_position, "0 while slide_state is 1 (at home)"});
    if (in.slide_status == SlideStatus::at_position && in.slide_position == 0)
      d.violations.push_back(
          {reg::slide_position, 0, "1 to " + std::to_string(n) + " while slide_state is 2 (at position)"});
  }
  const int cmd = c.raw(reg::packml_command);
  const auto command = packml::command_from_code(cmd);
  // Suspend/Unsuspend are PackML commands this cell does not take from its PLC.
  if (!command || *command == packml::Command::suspend || *command == packml::Command::unsuspend)
    d.violations.push_back({reg::packml_command, cmd,
                            "0 (none), 1 (Reset), 2 (Start), 3 (Stop), 4 (Hold), 5 (Unhold), 8 (Abort), 9 (Clear)"});
  else
    in.command = *command;
  in.command_toggle = c.range(reg::packml_command_toggle, 0, 1, kToggle);
  in.slide_command_ack = c.range(reg::slide_command_ack, 0, 1, kToggle);
  in.result_ack = c.range(reg::cycle_result_ack, 0, 1, kToggle);
  return d;
}

PlcBlock encode_plc_block(const PlcInputs& in) {
  PlcBlock b{};
  auto at = [&b](int offset) -> std::uint16_t& { return b[static_cast<std::size_t>(offset - reg::plc_block_start)]; };
  at(reg::interface_version) = static_cast<std::uint16_t>(in.interface_version);
  at(reg::plc_heartbeat) = in.heartbeat;
  at(reg::cycle_request_toggle) = static_cast<std::uint16_t>(in.cycle_request_toggle);
  at(reg::recipe_id) = static_cast<std::uint16_t>(in.recipe_id);
  at(reg::slide_state) = static_cast<std::uint16_t>(in.slide_status);
  at(reg::slide_position) = static_cast<std::uint16_t>(in.slide_position);
  at(reg::packml_command) = static_cast<std::uint16_t>(in.command);
  at(reg::packml_command_toggle) = static_cast<std::uint16_t>(in.command_toggle);
  at(reg::slide_command_ack) = static_cast<std::uint16_t>(in.slide_command_ack);
  at(reg::cycle_result_ack) = static_cast<std::uint16_t>(in.result_ack);
  return b;
}

Decoded<FettleOutputs> decode_fettle_block(std::span<const std::uint16_t> regs, const Limits& limits) {
  Decoded<FettleOutputs> d;
  if (!check_length(regs, reg::fettle_block_start, reg::fettle_block_size, d.violations)) return d;
  Checker c(regs, reg::fettle_block_start, d.violations);
  auto& out = d.value;
  out.heartbeat = static_cast<std::uint16_t>(c.raw(reg::fettle_heartbeat));
  out.cycle_ack_toggle = c.range(reg::cycle_ack_toggle, 0, 1, kToggle);
  const int s = c.raw(reg::packml_state);
  if (const auto state = packml::state_from_code(s))
    out.state = *state;
  else
    d.violations.push_back({reg::packml_state, s, "1 to 17 (PackML state)"});
  const int n = std::clamp(limits.slide_positions, 1, 0xFFFF);
  out.slide_target = c.range(reg::slide_target, 0, n, positions_text(n));
  out.slide_command_toggle = c.range(reg::slide_command_toggle, 0, 1, kToggle);
  out.result = static_cast<CycleResult>(c.range(reg::cycle_result, 0, 4, "0 (none), 1 (OK), 2 (NOK), 3 (re-grind), 4 (FAULT)"));
  out.result_toggle = c.range(reg::cycle_result_toggle, 0, 1, kToggle);
  out.fault_code = static_cast<std::uint16_t>(c.raw(reg::fault_code));
  out.fault_latched = c.range(reg::fault_latched, 0, 1, kToggle) == 1;
  if (out.fault_latched != (out.fault_code != 0))
    d.violations.push_back({reg::fault_latched, out.fault_latched ? 1 : 0,
                            "1 exactly when fault_code is not 0 (fault_code is " + std::to_string(out.fault_code) +
                                ")"});
  out.command_ack_toggle = c.range(reg::packml_command_ack, 0, 1, kToggle);
  return d;
}

FettleBlock encode_fettle_block(const FettleOutputs& out) {
  FettleBlock b{};
  auto at = [&b](int offset) -> std::uint16_t& {
    return b[static_cast<std::size_t>(offset - reg::fettle_block_start)];
  };
  at(reg::fettle_heartbeat) = out.heartbeat;
  at(reg::cycle_ack_toggle) = static_cast<std::uint16_t>(out.cycle_ack_toggle);
  at(reg::packml_state) = static_cast<std::uint16_t>(out.state);
  at(reg::slide_target) = static_cast<std::uint16_t>(out.slide_target);
  at(reg::slide_command_toggle) = static_cast<std::uint16_t>(out.slide_command_toggle);
  at(reg::cycle_result) = static_cast<std::uint16_t>(out.result);
  at(reg::cycle_result_toggle) = static_cast<std::uint16_t>(out.result_toggle);
  at(reg::fault_code) = out.fault_code;
  at(reg::fault_latched) = out.fault_latched ? 1 : 0;
  at(reg::packml_command_ack) = static_cast<std::uint16_t>(out.command_ack_toggle);
  return b;
}

int backoff_delay_ms(int attempt, int initial_ms, int max_ms) {
  initial_ms = std::max(1, initial_ms);
  max_ms = std::max(initial_ms, max_ms);
  long long d = initial_ms;
  for (int i = 0; i < attempt && d < max_ms; ++i) d *= 2;
  return static_cast<int>(std::min<long long>(d, max_ms));
}

}  // namespace fettle::drivers::plc
