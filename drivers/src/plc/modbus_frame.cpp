#include "fettle/drivers/modbus_frame.hpp"

#include <stdexcept>

namespace fettle::drivers::modbus {
namespace {

void put16(std::vector<std::uint8_t>& out, std::uint16_t v) {
  out.push_back(static_cast<std::uint8_t>(v >> 8));
  out.push_back(static_cast<std::uint8_t>(v & 0xFF));
}

std::uint16_t get16(std::span<const std::uint8_t> b, std::size_t at) {
  return static_cast<std::uint16_t>((b[at] << 8) | b[at + 1]);
}

std::string hex2(unsigned v) {
  static constexpr char digits[] = "0123456789ABCDEF";
  return std::string("0x") + digits[(v >> 4) & 0xF] + digits[v & 0xF];
}

/// MBAP header + the function code; the length field is filled in by finish().
Request start(std::uint16_t transaction, std::uint8_t unit, std::uint8_t function, std::uint16_t address,
              std::uint16_t count) {
  Request r{{}, transaction, unit, function, address, count};
  put16(r.adu, transaction);
  put16(r.adu, 0);  // protocol id: Modbus
  put16(r.adu, 0);  // length, below
  r.adu.push_back(unit);
  r.adu.push_back(function);
  put16(r.adu, address);
  put16(r.adu, count);
  return r;
}

void finish(Request& r) {
  const auto length = static_cast<std::uint16_t>(r.adu.size() - 6);  // unit id + PDU
  r.adu[4] = static_cast<std::uint8_t>(length >> 8);
  r.adu[5] = static_cast<std::uint8_t>(length & 0xFF);
}

Reply fail(std::string what) { return Reply{{}, std::move(what), 0}; }

}  // namespace

Request read_holding_registers(std::uint16_t transaction, std::uint8_t unit, std::uint16_t address,
                               std::uint16_t count) {
  if (count < 1 || count > kMaxReadRegisters)
    throw std::invalid_argument("a Modbus read covers 1 to 125 registers, not " + std::to_string(count));
  auto r = start(transaction, unit, kReadHoldingRegisters, address, count);
  finish(r);
  return r;
}

Request write_multiple_registers(std::uint16_t transaction, std::uint8_t unit, std::uint16_t address,
                                 std::span<const std::uint16_t> values) {
  if (values.empty() || values.size() > kMaxWriteRegisters)
    throw std::invalid_argument("a Modbus write covers 1 to 123 registers, not " + std::to_string(values.size()));
  auto r = start(transaction, unit, kWriteMultipleRegisters, address, static_cast<std::uint16_t>(values.size()));
  r.adu.push_back(static_cast<std::uint8_t>(2 * values.size()));
  for (const auto v : values) put16(r.adu, v);
  finish(r);
  return r;
}

std::string exception_name(int code) {
  switch (code) {
    case 1: return "illegal function";
    case 2: return "illegal data address";
    case 3: return "illegal data value";
    case 4: return "server device failure";
    case 5: return "acknowledge";
    case 6: return "server device busy";
    case 8: return "memory parity error";
    case 10: return "gateway path unavailable";
    case 11: return "gateway target device failed to respond";
    default: return "exception " + std::to_string(code);
  }
}

Reply check_reply(const Request& request, std::span<const std::uint8_t> reply) {
  const std::string asked = "function " + hex2(request.function) + " at address " + std::to_string(request.address);
  if (reply.size() < kMbapSize + 1)
    return fail("a reply of " + std::to_string(reply.size()) + " bytes, shorter than a Modbus TCP header and function");
  if (const auto t = get16(reply, 0); t != request.transaction)
    return fail("transaction id " + std::to_string(t) + " in the reply to transaction " +
                std::to_string(request.transaction));
  if (const auto p = get16(reply, 2); p != 0)
    return fail("protocol id " + std::to_string(p) + " in the reply (Modbus is 0)");
  if (const auto length = get16(reply, 4); length != reply.size() - 6)
    return fail("MBAP length " + std::to_string(length) + " where " + std::to_string(reply.size() - 6) +
                " bytes follow it");
  if (reply[6] != request.unit)
    return fail("unit id " + std::to_string(reply[6]) + " in the reply to unit " + std::to_string(request.unit));
  const std::uint8_t function = reply[7];
  if (function == (request.function | 0x80)) {
    if (reply.size() != kMbapSize + 2)
      return fail("an exception reply of " + std::to_string(reply.size()) + " bytes (a Modbus exception is 9)");
    const int code = reply[8];
    return Reply{{}, "Modbus exception " + std::to_string(code) + " (" + exception_name(code) + ") to " + asked, code};
  }
  if (function != request.function)
    return fail("function " + hex2(function) + " in the reply to " + asked);

  if (request.function == kReadHoldingRegisters) {
    const std::size_t expected = 2U * request.count;
    if (reply.size() < kMbapSize + 2 || reply[8] != expected)
      return fail("byte count " + (reply.size() > 8 ? std::to_string(reply[8]) : std::string("missing")) + " where " +
                  std::to_string(request.count) + " registers (" + std::to_string(expected) + " bytes) were asked for");
    if (reply.size() != kMbapSize + 2 + expected)
      return fail("a read reply of " + std::to_string(reply.size()) + " bytes where " +
                  std::to_string(kMbapSize + 2 + expected) + " were due");
    Reply ok;
    ok.registers.reserve(request.count);
    for (std::size_t i = 0; i < request.count; ++i) ok.registers.push_back(get16(reply, kMbapSize + 2 + 2 * i));
    return ok;
  }
  if (request.function == kWriteMultipleRegisters) {
    if (reply.size() != kMbapSize + 5)
      return fail("a write reply of " + std::to_string(reply.size()) + " bytes (function 0x10 echoes 12)");
    if (const auto a = get16(reply, 8); a != request.address)
      return fail("the write reply echoes address " + std::to_string(a) + " where " +
                  std::to_string(request.address) + " was written");
    if (const auto n = get16(reply, 10); n != request.count)
      return fail("the write reply echoes " + std::to_string(n) + " registers where " +
                  std::to_string(request.count) + " were written");
    return Reply{};
  }
  return fail("a reply to " + asked + ", a function this link does not check");
}

}  // namespace fettle::drivers::modbus
