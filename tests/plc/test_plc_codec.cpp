// The PLC register map's pure encoding/decoding: round trips and every range check. The
// Modbus TCP frames the link sends and the check of each reply (modbus_frame.hpp).
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include "fettle/drivers/modbus_frame.hpp"
#include "fettle/drivers/packml.hpp"
#include "fettle/drivers/plc_registers.hpp"

namespace plc = fettle::drivers::plc;
namespace packml = fettle::packml;

namespace {

plc::PlcInputs sample_inputs() {
  plc::PlcInputs in;
  in.heartbeat = 65535;
  in.cycle_request_toggle = 1;
  in.recipe_id = 4711;
  in.slide_status = plc::SlideStatus::at_position;
  in.slide_position = 2;
  in.command = packml::Command::clear;
  in.command_toggle = 1;
  in.slide_command_ack = 1;
  in.result_ack = 1;
  return in;
}

plc::Limits two_positions() {
  plc::Limits l;
  l.slide_positions = 2;
  return l;
}

/// Decodes `block` with register `offset` set to `value`; returns the violations.
std::vector<plc::RangeViolation> plc_with(int offset, std::uint16_t value) {
  auto block = plc::encode_plc_block(sample_inputs());
  block[static_cast<std::size_t>(offset - plc::reg::plc_block_start)] = value;
  return plc::decode_plc_block(block, two_positions()).violations;
}

std::vector<plc::RangeViolation> fettle_with(int offset, std::uint16_t value) {
  plc::FettleOutputs out;
  auto block = plc::encode_fettle_block(out);
  block[static_cast<std::size_t>(offset - plc::reg::fettle_block_start)] = value;
  return plc::decode_fettle_block(block, two_positions()).violations;
}

}  // namespace

TEST(PackML, StateCodesFollowIsaTr88) {
  EXPECT_EQ(packml::code(packml::State::clearing), 1);
  EXPECT_EQ(packml::code(packml::State::stopped), 2);
  EXPECT_EQ(packml::code(packml::State::idle), 4);
  EXPECT_EQ(packml::code(packml::State::execute), 6);
  EXPECT_EQ(packml::code(packml::State::aborted), 9);
  EXPECT_EQ(packml::code(packml::State::held), 11);
  EXPECT_EQ(packml::code(packml::State::resetting), 15);
  EXPECT_EQ(packml::code(packml::State::complete), 17);
  for (int c = 1; c <= 17; ++c) EXPECT_EQ(packml::code(*packml::state_from_code(c)), c);
  EXPECT_FALSE(packml::state_from_code(0));
  EXPECT_FALSE(packml::state_from_code(18));
  EXPECT_EQ(packml::name(packml::State::unholding), "Unholding");
}

TEST(PackML, CommandCodesFollowPackTags) {
  EXPECT_EQ(packml::code(packml::Command::reset), 1);
  EXPECT_EQ(packml::code(packml::Command::abort), 8);
  EXPECT_EQ(packml::code(packml::Command::clear), 9);
  EXPECT_FALSE(packml::command_from_code(10));
  EXPECT_EQ(packml::name(packml::Command::unhold), "Unhold");
}

TEST(PlcCodec, PlcBlockRoundTrips) {
  const auto in = sample_inputs();
  const auto d = plc::decode_plc_block(plc::encode_plc_block(in), two_positions());
  ASSERT_TRUE(d.ok()) << plc::describe(d.violations.front());
  EXPECT_EQ(d.value, in);
}

TEST(PlcCodec, FettleBlockRoundTrips) {
  plc::FettleOutputs out;
  out.heartbeat = 12345;
  out.cycle_ack_toggle = 1;
  out.state = packml::State::execute;
  out.slide_target = 2;
  out.slide_command_toggle = 1;
  out.result = plc::CycleResult::regrind;
  out.result_toggle = 1;
  out.fault_code = 321;
  out.fault_latched = true;
  out.command_ack_toggle = 1;
  const auto block = plc::encode_fettle_block(out);
  EXPECT_EQ(block[plc::reg::packml_state - plc::reg::fettle_block_start], 6);
  EXPECT_EQ(block[plc::reg::cycle_result - plc::reg::fettle_block_start], 3);
  const auto d = plc::decode_fettle_block(block, two_positions());
  ASSERT_TRUE(d.ok());
  EXPECT_EQ(d.value, out);
}

// A PLC written for map version 1 has no slide and result acknowledges: refused, never half-served.
TEST(PlcCodec, WrongInterfaceVersionIsAViolation) {
  EXPECT_EQ(plc::kInterfaceVersion, 2);
  for (const int version : {0, 1, 3}) {
    const auto v = plc_with(plc::reg::interface_version, static_cast<std::uint16_t>(version));
    ASSERT_EQ(v.size(), 1U) << version;
    EXPECT_EQ(v[0].offset, plc::reg::interface_version);
    EXPECT_EQ(v[0].value, version);
  }
}

TEST(PlcCodec, ToggleOtherThanZeroOrOneIsAViolation) {
  EXPECT_EQ(plc_with(plc::reg::cycle_request_toggle, 2).at(0).offset, plc::reg::cycle_request_toggle);
  EXPECT_EQ(plc_with(plc::reg::packml_command_toggle, 7).at(0).offset, plc::reg::packml_command_toggle);
  EXPECT_EQ(plc_with(plc::reg::slide_command_ack, 2).at(0).offset, plc::reg::slide_command_ack);
  EXPECT_EQ(plc_with(plc::reg::cycle_result_ack, 65535).at(0).offset, plc::reg::cycle_result_ack);
}

TEST(PlcCodec, UnknownSlideStateIsAViolation) {
  const auto v = plc_with(plc::reg::slide_state, 5);
  ASSERT_EQ(v.size(), 1U);
  EXPECT_EQ(v[0].allowed, "0 (unknown), 1 (at home), 2 (at position), 3 (moving), 4 (fault)");
}

TEST(PlcCodec, SlidePositionBeyondConfiguredPositionsIsAViolation) {
  const auto v = plc_with(plc::reg::slide_position, 3);
  ASSERT_EQ(v.size(), 1U);
  EXPECT_EQ(v[0].offset, plc::reg::slide_position);
  EXPECT_EQ(v[0].value, 3);
}

TEST(PlcCodec, SlideStateAndPositionMustAgree) {
  auto in = sample_inputs();
  in.slide_status = plc::SlideStatus::at_home;
  in.slide_position = 1;
  EXPECT_EQ(plc::decode_plc_block(plc::encode_plc_block(in), two_positions()).violations.size(), 1U);
  in.slide_status = plc::SlideStatus::at_position;
  in.slide_position = 0;
  EXPECT_EQ(plc::decode_plc_block(plc::encode_plc_block(in), two_positions()).violations.size(), 1U);
  in.slide_status = plc::SlideStatus::moving;
  EXPECT_TRUE(plc::decode_plc_block(plc::encode_plc_block(in), two_positions()).ok());
}

TEST(PlcCodec, PackMLCommandOutsideTheAcceptedSetIsAViolation) {
  EXPECT_EQ(plc_with(plc::reg::packml_command, 10).size(), 1U);
  EXPECT_EQ(plc_with(plc::reg::packml_command, 6).size(), 1U);  // Suspend: not taken from the PLC
  EXPECT_EQ(plc_with(plc::reg::packml_command, 7).size(), 1U);  // Unsuspend
  EXPECT_TRUE(plc_with(plc::reg::packml_command, 8).empty());   // Abort
}

TEST(PlcCodec, AnyHeartbeatAndRecipeValueIsAllowed) {
  EXPECT_TRUE(plc_with(plc::reg::plc_heartbeat, 0).empty());
  EXPECT_TRUE(plc_with(plc::reg::plc_heartbeat, 65535).empty());
  EXPECT_TRUE(plc_with(plc::reg::recipe_id, 65535).empty());
}

TEST(PlcCodec, WrongBlockLengthIsAViolation) {
  const std::vector<std::uint16_t> short_block(5, 0);
  const auto d = plc::decode_plc_block(short_block, two_positions());
  ASSERT_EQ(d.violations.size(), 1U);
  EXPECT_EQ(d.violations[0].offset, 5);
}

TEST(PlcCodec, FettleBlockIsCheckedToo) {
  EXPECT_EQ(fettle_with(plc::reg::packml_state, 0).size(), 1U);
  EXPECT_EQ(fettle_with(plc::reg::packml_state, 18).size(), 1U);
  EXPECT_EQ(fettle_with(plc::reg::cycle_result, 4).size(), 0U);  // FAULT
  EXPECT_EQ(fettle_with(plc::reg::cycle_result, 5).size(), 1U);
  EXPECT_EQ(fettle_with(plc::reg::slide_target, 3).size(), 1U);
  // A latched bit without a code (or a code without the bit) is inconsistent.
  EXPECT_EQ(fettle_with(plc::reg::fault_latched, 1).size(), 1U);
  EXPECT_EQ(fettle_with(plc::reg::fault_code, 9).size(), 1U);
}

TEST(PlcCodec, DescribeNamesRegisterValueAndAllowedValues) {
  const auto v = plc_with(plc::reg::slide_state, 9);
  EXPECT_EQ(plc::describe(v.at(0)),
            "register 4 (slide_state) holds 9; allowed 0 (unknown), 1 (at home), 2 (at position), 3 (moving), 4 "
            "(fault)");
}

TEST(PlcCodec, MapLayoutIsTheDocumentedOne) {
  EXPECT_EQ(plc::register_name(0), "interface_version");
  EXPECT_EQ(plc::register_name(7), "packml_command_toggle");
  EXPECT_EQ(plc::register_name(8), "slide_command_ack");
  EXPECT_EQ(plc::register_name(9), "cycle_result_ack");
  EXPECT_EQ(plc::reg::plc_block_size, 10);
  EXPECT_EQ(plc::register_name(16), "fettle_heartbeat");
  EXPECT_EQ(plc::register_name(25), "packml_command_ack");
  EXPECT_EQ(plc::register_name(10), "reserved");
  EXPECT_EQ(plc::reg::map_size, 26);
}

TEST(Backoff, DoublesFromInitialUpToMax) {
  const std::vector<int> expected{100, 200, 400, 800, 1600, 3200, 5000, 5000};
  for (std::size_t i = 0; i < expected.size(); ++i)
    EXPECT_EQ(plc::backoff_delay_ms(static_cast<int>(i), 100, 5000), expected[i]) << "attempt " << i;
  EXPECT_EQ(plc::backoff_delay_ms(1000, 100, 5000), 5000);  // no overflow
}

namespace modbus = fettle::drivers::modbus;

namespace {

using Bytes = std::vector<std::uint8_t>;

/// A well-formed reply to `r` (registers 0x0100 + i for a read).
Bytes good_reply(const modbus::Request& r) {
  Bytes pdu{r.function};
  if (r.function == modbus::kReadHoldingRegisters) {
    pdu.push_back(static_cast<std::uint8_t>(2 * r.count));
    for (int i = 0; i < r.count; ++i) {
      pdu.push_back(0x01);
      pdu.push_back(static_cast<std::uint8_t>(i));
    }
  } else {
    pdu.insert(pdu.end(), {static_cast<std::uint8_t>(r.address >> 8), static_cast<std::uint8_t>(r.address & 0xFF),
                           static_cast<std::uint8_t>(r.count >> 8), static_cast<std::uint8_t>(r.count & 0xFF)});
  }
  const auto length = pdu.size() + 1;
  Bytes adu(7 + pdu.size());
  adu[0] = static_cast<std::uint8_t>(r.transaction >> 8);
  adu[1] = static_cast<std::uint8_t>(r.transaction & 0xFF);
  adu[4] = static_cast<std::uint8_t>(length >> 8);
  adu[5] = static_cast<std::uint8_t>(length & 0xFF);
  adu[6] = r.unit;
  std::copy(pdu.begin(), pdu.end(), adu.begin() + 7);
  return adu;
}

}  // namespace

TEST(ModbusFrame, RequestsAreTheStandardsBytes) {
  const auto read = modbus::read_holding_registers(0x1234, 1, 16, 10);
  EXPECT_EQ(read.adu, (Bytes{0x12, 0x34, 0, 0, 0, 6, 1, 0x03, 0, 16, 0, 10}));
  const std::array<std::uint16_t, 2> values{0xABCD, 7};
  const auto write = modbus::write_multiple_registers(2, 9, 300, values);
  EXPECT_EQ(write.adu, (Bytes{0, 2, 0, 0, 0, 11, 9, 0x10, 0x01, 0x2C, 0, 2, 4, 0xAB, 0xCD, 0, 7}));
  EXPECT_THROW((void)modbus::read_holding_registers(1, 1, 0, 126), std::invalid_argument);
  EXPECT_THROW((void)modbus::write_multiple_registers(1, 1, 0, {}), std::invalid_argument);
}

TEST(ModbusFrame, AGoodReplyGivesItsRegisters) {
  const auto read = modbus::read_holding_registers(7, 1, 0, 3);
  const auto reply = modbus::check_reply(read, good_reply(read));
  ASSERT_TRUE(reply.ok()) << reply.error;
  EXPECT_EQ(reply.registers, (std::vector<std::uint16_t>{0x0100, 0x0101, 0x0102}));
  const std::array<std::uint16_t, 2> values{1, 2};
  const auto write = modbus::write_multiple_registers(8, 1, 16, values);
  EXPECT_TRUE(modbus::check_reply(write, good_reply(write)).ok());
}

// Each field libmodbus 3.1.6 lets through, and the ones it checks, named in the error.
TEST(ModbusFrame, EveryFieldOfTheReplyIsChecked) {
  const auto read = modbus::read_holding_registers(7, 1, 0, 3);
  const auto error_of = [&](const modbus::Request& r, auto&& mangle) {
    auto bytes = good_reply(r);
    mangle(bytes);
    const auto reply = modbus::check_reply(r, bytes);
    EXPECT_TRUE(reply.registers.empty());
    return reply.error;
  };
  EXPECT_NE(error_of(read, [](Bytes& b) { b[1] = 8; }).find("transaction id 8"), std::string::npos);
  EXPECT_NE(error_of(read, [](Bytes& b) { b[3] = 7; }).find("protocol id 7"), std::string::npos);
  EXPECT_NE(error_of(read, [](Bytes& b) { b[2] = 1; }).find("protocol id 256"), std::string::npos);
  EXPECT_NE(error_of(read, [](Bytes& b) { b[5] = 2; }).find("MBAP length 2 where 9 bytes"), std::string::npos);
  EXPECT_NE(error_of(read, [](Bytes& b) { b[4] = b[5] = 0xFF; }).find("MBAP length 65535"), std::string::npos);
  EXPECT_NE(error_of(read, [](Bytes& b) { b[6] = 2; }).find("unit id 2 in the reply to unit 1"), std::string::npos);
  EXPECT_NE(error_of(read, [](Bytes& b) { b[7] = 0x04; }).find("function 0x04"), std::string::npos);
  EXPECT_NE(error_of(read, [](Bytes& b) { b[8] = 4; }).find("byte count 4"), std::string::npos);
  EXPECT_NE(error_of(read, [](Bytes& b) { b.push_back(0); b[5] += 1; }).find("a read reply of 16 bytes"),
            std::string::npos);
  EXPECT_NE(error_of(read, [](Bytes& b) { b.resize(5); }).find("shorter than a Modbus TCP header"), std::string::npos);

  const std::array<std::uint16_t, 2> values{1, 2};
  const auto write = modbus::write_multiple_registers(9, 1, 16, values);
  EXPECT_NE(error_of(write, [](Bytes& b) { b[9] = 17; }).find("echoes address 17 where 16"), std::string::npos);
  EXPECT_NE(error_of(write, [](Bytes& b) { b[11] = 3; }).find("echoes 3 registers where 2"), std::string::npos);
}

TEST(ModbusFrame, AnExceptionIsNamed) {
  const auto read = modbus::read_holding_registers(7, 1, 40000, 3);
  const Bytes bytes{0, 7, 0, 0, 0, 3, 1, 0x83, 0x02};
  const auto reply = modbus::check_reply(read, bytes);
  EXPECT_EQ(reply.exception_code, 2);
  EXPECT_NE(reply.error.find("Modbus exception 2 (illegal data address) to function 0x03 at address 40000"),
            std::string::npos)
      << reply.error;
  EXPECT_EQ(modbus::exception_name(99), "exception 99");
}
