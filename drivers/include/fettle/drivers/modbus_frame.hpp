#pragma once
// Modbus TCP application data units (MBAP header + PDU) for the two functions the PLC link
// uses, read holding registers (0x03) and write multiple registers (0x10), and the check of a
// reply against its request (Modbus Application Protocol V1.1b3; Modbus Messaging on TCP/IP
// Implementation Guide V1.0b, section 3.1.3).
//
// The link sends these frames on libmodbus's socket and lets libmodbus read the reply off the
// stream (timeouts, lengths from the function code); every field of the reply is then checked
// here, because libmodbus 3.1.6 does not: it accepts a protocol id whose high byte is 0 (7,
// say), any unit id, any MBAP length (2, 0xFFFF), and an FC16 reply that echoes another
// address. docs/plc-interface.md ("What a reply must be") lists the checks; the tests are
// ModbusFrame.* (test_plc_codec) and PlcBadPeer.* (test_plc_bad_input).
#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace fettle::drivers::modbus {

inline constexpr std::uint8_t kReadHoldingRegisters = 0x03;
inline constexpr std::uint8_t kWriteMultipleRegisters = 0x10;
/// The MBAP header: transaction id (2), protocol id (2), length (2), unit id (1).
inline constexpr std::size_t kMbapSize = 7;
/// The largest Modbus TCP ADU (MBAP + 253-byte PDU).
inline constexpr std::size_t kMaxAduSize = 260;
/// The most registers one request may read (0x03) or write (0x10).
inline constexpr std::uint16_t kMaxReadRegisters = 125;
inline constexpr std::uint16_t kMaxWriteRegisters = 123;

/// A request as sent, with what its reply must echo.
struct Request {
  std::vector<std::uint8_t> adu;
  std::uint16_t transaction = 0;
  std::uint8_t unit = 0;
  std::uint8_t function = 0;
  std::uint16_t address = 0;
  std::uint16_t count = 0;
};

/// Read `count` (1..125) holding registers from `address`. Throws std::invalid_argument
/// beyond the protocol's limits.
Request read_holding_registers(std::uint16_t transaction, std::uint8_t unit, std::uint16_t address,
                               std::uint16_t count);
/// Write `values` (1..123 registers) from `address`. Throws std::invalid_argument beyond the
/// protocol's limits.
Request write_multiple_registers(std::uint16_t transaction, std::uint8_t unit, std::uint16_t address,
                                 std::span<const std::uint16_t> values);

/// A checked reply: the registers read (0x03; empty for 0x10), or what is wrong with it in one
/// line. `exception_code` is the Modbus exception when the server answered with one (1..255),
/// 0 otherwise.
struct Reply {
  std::vector<std::uint16_t> registers;
  std::string error;
  int exception_code = 0;
  bool ok() const { return error.empty(); }
};

/// Checks `reply` (the whole ADU as received) against `request`: transaction id, protocol id 0,
/// MBAP length equal to the bytes that follow it, the unit id echoed, the function (or its
/// exception), and for 0x03 the byte count and size, for 0x10 the echoed address and quantity.
Reply check_reply(const Request& request, std::span<const std::uint8_t> reply);

/// "illegal data address" for 2, and so on; "exception N" for codes the standard does not name.
std::string exception_name(int code);

}  // namespace fettle::drivers::modbus
