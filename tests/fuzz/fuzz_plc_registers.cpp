// Fuzz target: PLC register decoding (drivers/plc_registers.hpp). The bytes are a block of
// holding registers of any length as a PLC (or anything answering on port 502) returns them,
// decoded as the PLC block (what Fettle reads) and as the Fettle block (what the simulated PLC
// reads). A block that decodes without violations encodes back to the same registers; every
// violation names a register of the block and describes itself.
#include <cstdint>
#include <vector>

#include "fettle/drivers/plc_registers.hpp"
#include "fuzz_input.hpp"

namespace plc = fettle::drivers::plc;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fettle::fuzz::ByteReader in(data, size);
  plc::Limits limits;
  limits.slide_positions = in.take<std::int16_t>();
  std::vector<std::uint16_t> regs;
  while (in.remaining() > 0) regs.push_back(in.take<std::uint16_t>());

  const auto plc_block = plc::decode_plc_block(regs, limits);
  for (const auto& v : plc_block.violations) {
    FUZZ_CHECK(v.offset >= plc::reg::plc_block_start && v.offset <= plc::reg::plc_block_start + plc::reg::plc_block_size);
    FUZZ_CHECK(!plc::describe(v).empty());
  }
  if (plc_block.ok()) {
    FUZZ_CHECK(regs.size() == plc::reg::plc_block_size);
    const auto encoded = plc::encode_plc_block(plc_block.value);
    FUZZ_CHECK(std::equal(encoded.begin(), encoded.end(), regs.begin()));
    FUZZ_CHECK(plc_block.value.slide_position >= 0 && plc_block.value.slide_position <= std::max(1, limits.slide_positions));
  }

  const auto fettle_block = plc::decode_fettle_block(regs, limits);
  for (const auto& v : fettle_block.violations) {
    FUZZ_CHECK(v.offset >= plc::reg::fettle_block_start &&
               v.offset <= plc::reg::fettle_block_start + plc::reg::fettle_block_size);
    FUZZ_CHECK(!plc::describe(v).empty());
  }
  if (fettle_block.ok()) {
    const auto encoded = plc::encode_fettle_block(fettle_block.value);
    FUZZ_CHECK(std::equal(encoded.begin(), encoded.end(), regs.begin()));
    (void)plc::name(fettle_block.value.result);
  }
  for (int attempt = 0; attempt < 40; attempt += 7)
    FUZZ_CHECK(plc::backoff_delay_ms(attempt, limits.slide_positions, 5000) >= 1);
  return 0;
}
