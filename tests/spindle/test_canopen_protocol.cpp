// CANopen and socketcand codecs: byte layouts from CiA 301/402 and socketcand's protocol.md.
#include <gtest/gtest.h>

#include "fettle/drivers/canopen.hpp"
#include "fettle/drivers/canopen_transport.hpp"

using namespace fettle::canopen;

TEST(CanopenSdo, ExpeditedDownloadOfTwoBytesHasCommand2BAndLittleEndianData) {
  const auto f = sdo_download_request(5, 0x6040, 0, 0x000F, 2);
  EXPECT_EQ(f.id, 0x605U);
  ASSERT_EQ(f.len, 8);
  EXPECT_EQ(f.data[0], 0x2B);
  EXPECT_EQ(f.data[1], 0x40);
  EXPECT_EQ(f.data[2], 0x60);
  EXPECT_EQ(f.data[3], 0x00);
  EXPECT_EQ(f.data[4], 0x0F);
  EXPECT_EQ(f.data[5], 0x00);
}

TEST(CanopenSdo, DownloadCommandBytesForOneThreeAndFourBytes) {
  EXPECT_EQ(sdo_download_request(1, 0x6060, 0, 3, 1).data[0], 0x2F);
  EXPECT_EQ(sdo_download_request(1, 0x2000, 0, 3, 3).data[0], 0x27);
  EXPECT_EQ(sdo_download_request(1, 0x60FF, 0, 3, 4).data[0], 0x23);
  EXPECT_EQ(sdo_upload_request(1, 0x6041, 0).data[0], 0x40);
}

TEST(CanopenSdo, ServerDecodesWhatTheClientEncodes) {
  const auto m = decode_sdo(sdo_download_request(1, 0x60FF, 0, 0xFFFFF830U, 4), true);  // -2000 rpm
  ASSERT_TRUE(m);
  EXPECT_EQ(m->kind, SdoMessage::Kind::download_request);
  EXPECT_EQ(m->index, 0x60FF);
  EXPECT_EQ(m->size, 4);
  EXPECT_EQ(static_cast<std::int32_t>(m->value), -2000);
}

TEST(CanopenSdo, ClientDecodesUploadResponseWithItsSize) {
  const auto f = sdo_upload_response(1, 0x6041, 0, 0x0237, 2);
  EXPECT_EQ(f.id, 0x581U);
  EXPECT_EQ(f.data[0], 0x4B);
  const auto m = decode_sdo(f, false);
  ASSERT_TRUE(m);
  EXPECT_EQ(m->kind, SdoMessage::Kind::upload_response);
  EXPECT_EQ(m->value, 0x0237U);
  EXPECT_EQ(m->size, 2);
}

TEST(CanopenSdo, SegmentedUploadInitiateIsRecognised) {
  CanFrame f = CanFrame::make(0x581, {0x41, 0x08, 0x10, 0x00, 20, 0, 0, 0});
  const auto m = decode_sdo(f, false);
  ASSERT_TRUE(m);
  EXPECT_EQ(m->kind, SdoMessage::Kind::upload_segmented);
}

TEST(CanopenSdo, AbortCarriesCodeAndHasCiA301Text) {
  const auto f = sdo_abort(1, false, 0x1234, 0, abort_code::no_object);
  EXPECT_EQ(f.data[0], 0x80);
  const auto m = decode_sdo(f, false);
  ASSERT_TRUE(m);
  EXPECT_EQ(m->kind, SdoMessage::Kind::abort);
  EXPECT_EQ(m->value, 0x06020000U);
  EXPECT_EQ(abort_code_text(m->value), "object does not exist in the object dictionary");
  EXPECT_EQ(abort_code_text(0x06090030), "invalid value for parameter (download only)");
  EXPECT_EQ(abort_code_text(0x12345678), "unknown abort code");
}

TEST(CanopenSdo, ShortFramesAreNotSdo) {
  EXPECT_FALSE(decode_sdo(CanFrame::make(0x581, {0x60, 0x40}), false));
}

TEST(CanopenEmcy, DecodesCodeAndRegisterAndDescribesThem) {
  const auto f = emcy_frame(3, Emergency{0x2310, 0x03, {}});
  EXPECT_EQ(f.id, 0x083U);
  const auto e = decode_emcy(CanFrame::make(0x083, {0x10, 0x23, 0x03, 0, 0, 0, 0, 0}));
  ASSERT_TRUE(e);
  EXPECT_EQ(e->error_code, 0x2310);
  EXPECT_EQ(e->error_register, 0x03);
  EXPECT_EQ(describe(*e), "0x2310 continuous over-current (error register 0x03: generic, current)");
  EXPECT_EQ(emcy_code_text(0x8130), "life guard error or heartbeat error");
  EXPECT_EQ(emcy_code_text(0x4311), "temperature");
}

TEST(CanopenNmt, FramesFollowThePredefinedConnectionSet) {
  EXPECT_EQ(nmt_frame(NmtCommand::reset_communication, 4), CanFrame::make(0x000, {0x82, 0x04}));
  EXPECT_EQ(nmt_frame(NmtCommand::start, 4), CanFrame::make(0x000, {0x01, 0x04}));
  EXPECT_EQ(heartbeat_frame(4, NmtState::pre_operational), CanFrame::make(0x704, {0x7F}));
}

TEST(CanopenCia402, StatuswordDecodesEveryState) {
  EXPECT_EQ(decode_statusword(0x0250), DriveState::switch_on_disabled);
  EXPECT_EQ(decode_statusword(0x0231), DriveState::ready_to_switch_on);
  EXPECT_EQ(decode_statusword(0x0233), DriveState::switched_on);
  EXPECT_EQ(decode_statusword(0x0637), DriveState::operation_enabled);
  EXPECT_EQ(decode_statusword(0x0217), DriveState::quick_stop_active);
  EXPECT_EQ(decode_statusword(0x021F), DriveState::fault_reaction_active);
  EXPECT_EQ(decode_statusword(0x0218), DriveState::fault);
  EXPECT_EQ(decode_statusword(0x0000), DriveState::not_ready_to_switch_on);
  for (auto s : {DriveState::switch_on_disabled, DriveState::ready_to_switch_on, DriveState::switched_on,
                 DriveState::operation_enabled, DriveState::quick_stop_active, DriveState::fault})
    EXPECT_EQ(decode_statusword(statusword_of(s)), s) << to_string(s);
}

TEST(CanopenSocketcand, SendAndFrameElementsRoundTrip) {
  const auto f = CanFrame::make(0x601, {0x40, 0x41, 0x60, 0x00, 0, 0, 0, 0});
  EXPECT_EQ(socketcand::format_send(f), "< send 601 8 40 41 60 00 00 00 00 00 >");
  std::string buf = socketcand::format_send(f);
  auto msgs = socketcand::take_messages(buf);
  ASSERT_TRUE(msgs);
  ASSERT_EQ(msgs->size(), 1U);
  auto back = socketcand::parse_send((*msgs)[0]);
  ASSERT_TRUE(back) << back.error().message;
  EXPECT_EQ(*back, f);

  EXPECT_EQ(socketcand::format_frame(CanFrame::make(0x181, {0x37, 0x06}), 12.000345), "< frame 181 12.000345 3706 >");
  std::string in = "< frame 181 12.000345 3706 >";
  auto m2 = socketcand::take_messages(in);
  ASSERT_TRUE(m2);
  auto fr = socketcand::parse_frame((*m2)[0]);
  ASSERT_TRUE(fr);
  EXPECT_EQ(*fr, CanFrame::make(0x181, {0x37, 0x06}));
}

TEST(CanopenSocketcand, ExtendedIdsUseEightDigitsAndEmptyFramesParse) {
  CanFrame f = CanFrame::make(0x1ABCDEF0, {});
  f.extended = true;
  EXPECT_EQ(socketcand::format_send(f), "< send 1ABCDEF0 0 >");
  auto back = socketcand::parse_frame({"frame", "1ABCDEF0", "1.000000"});
  ASSERT_TRUE(back);
  EXPECT_TRUE(back->extended);
  EXPECT_EQ(back->len, 0);
}

TEST(CanopenSocketcand, PartialElementsStayInTheBuffer) {
  std::string buf = "< hi >< ok >< frame 181 1.0 ";
  auto m = socketcand::take_messages(buf);
  ASSERT_TRUE(m);
  ASSERT_EQ(m->size(), 2U);
  EXPECT_EQ((*m)[0][0], "hi");
  EXPECT_EQ((*m)[1][0], "ok");
  EXPECT_EQ(buf, "< frame 181 1.0 ");
  buf += "00 >";
  m = socketcand::take_messages(buf);
  ASSERT_TRUE(m);
  ASSERT_EQ(m->size(), 1U);
  EXPECT_TRUE(buf.empty());
}

TEST(CanopenSocketcand, MalformedElementsAreErrorsThatSayWhy) {
  auto r = socketcand::parse_send({"send", "601", "3", "01", "02"});
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("length does not match"), std::string::npos);
  EXPECT_FALSE(socketcand::parse_send({"send", "XYZ", "0"}));
  EXPECT_FALSE(socketcand::parse_frame({"frame", "800", "1.0"}));  // over 11 bits in 3 digits
  EXPECT_FALSE(socketcand::parse_frame({"frame", "181", "1.0", "123"}));
  std::string junk(300, 'x');
  junk.insert(0, "<");
  EXPECT_FALSE(socketcand::take_messages(junk));
}
