// Fuzz target: the check of a Modbus TCP reply against its request (drivers/modbus_frame.hpp),
// which is all that stands between a peer on port 502 and the PLC link. The first bytes pick
// the request (function, transaction, unit, address, count), the rest is the reply as
// libmodbus read it off the wire. A reply is either good, with exactly the registers asked
// for, or refused with one line saying why; an exception is only ever a 9-byte frame.
#include <algorithm>
#include <array>
#include <cstdint>
#include <span>

#include "fettle/drivers/modbus_frame.hpp"
#include "fuzz_input.hpp"

namespace modbus = fettle::drivers::modbus;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fettle::fuzz::ByteReader in(data, size);
  const bool write = in.take_bool();
  const auto transaction = in.take<std::uint16_t>();
  const auto unit = in.take<std::uint8_t>();
  const auto address = in.take<std::uint16_t>();
  const auto count = static_cast<std::uint16_t>(1 + in.take<std::uint8_t>() % modbus::kMaxWriteRegisters);
  std::array<std::uint16_t, modbus::kMaxWriteRegisters> values{};
  const auto request = write ? modbus::write_multiple_registers(transaction, unit, address, std::span(values.data(), count))
                             : modbus::read_holding_registers(transaction, unit, address, count);
  FUZZ_CHECK(request.adu.size() <= modbus::kMaxAduSize);
  const auto rest = in.rest();
  const std::span<const std::uint8_t> reply(reinterpret_cast<const std::uint8_t*>(rest.data()), rest.size());

  const auto checked = modbus::check_reply(request, reply);
  if (checked.ok()) {
    FUZZ_CHECK(checked.exception_code == 0);
    FUZZ_CHECK(reply.size() >= modbus::kMbapSize + 1);
    FUZZ_CHECK(reply[7] == request.function);
    FUZZ_CHECK(((reply[0] << 8) | reply[1]) == transaction && reply[6] == unit);
    FUZZ_CHECK(checked.registers.size() == (write ? 0U : count));
  } else {
    FUZZ_CHECK(checked.registers.empty());
    FUZZ_CHECK(std::none_of(checked.error.begin(), checked.error.end(), [](char c) { return c == '\n'; }));
    if (checked.exception_code != 0) FUZZ_CHECK(reply.size() == modbus::kMbapSize + 2);
  }
  return 0;
}
