// The PLC register map's pure encoding/decoding: round trips and every range check.
#include <gtest/gtest.h>

#include <array>
#include <cstdint>
#include <vector>

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
