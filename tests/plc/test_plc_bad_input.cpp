// The PLC link against peers on port "502" that are not a well-behaved Modbus TCP server: a
// raw TCP socket on 127.0.0.1 that says nothing, closes at once, answers with garbage, with
// Modbus frames that do not match the request, or with register values out of range. Every
// case is a LinkDown or a ValueOutOfRange with a reason, never a LinkUp, and the link keeps
// retrying. (Out-of-range values from the simulated PLC: test_plc_link.)
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <cstdint>
#include <string>
#include <thread>

#include "../support/raw_tcp_peer.hpp"
#include "event_log.hpp"

namespace plc = fettle::drivers::plc;
using fettle::test::EventLog;
using fettle::test::fast_options;
using fettle::test::RawTcpPeer;
using std::chrono::milliseconds;

namespace {

constexpr milliseconds kWait{3000};

/// One Modbus TCP request as read from the wire (MBAP header + PDU).
struct Request {
  std::uint16_t transaction = 0;
  std::uint8_t unit = 0;
  std::uint8_t function = 0;
  std::uint16_t address = 0;
  std::uint16_t count = 0;
};

/// Reads one request (whole frame), or nothing if the peer went away.
std::optional<Request> read_request(RawTcpPeer& peer, int fd, std::string& buf) {
  while (!peer.stop_requested()) {
    if (buf.size() >= 7) {
      const std::size_t len = (static_cast<std::uint8_t>(buf[4]) << 8) | static_cast<std::uint8_t>(buf[5]);
      if (buf.size() >= 6 + len && len >= 6) {
        auto b = [&](std::size_t i) { return static_cast<std::uint8_t>(buf[i]); };
        Request r{static_cast<std::uint16_t>((b(0) << 8) | b(1)), b(6), b(7),
                  static_cast<std::uint16_t>((b(8) << 8) | b(9)), static_cast<std::uint16_t>((b(10) << 8) | b(11))};
        buf.erase(0, 6 + len);
        return r;
      }
    }
    const auto got = peer.read_some(fd, milliseconds(50));
    if (got.empty() && peer.stop_requested()) break;
    buf += got;
  }
  return std::nullopt;
}

std::string be16(unsigned v) { return {static_cast<char>((v >> 8) & 0xFF), static_cast<char>(v & 0xFF)}; }

/// A Modbus TCP frame: MBAP (transaction, protocol 0, length, unit) + PDU.
std::string frame(std::uint16_t transaction, std::uint8_t unit, const std::string& pdu) {
  return be16(transaction) + be16(0) + be16(static_cast<unsigned>(pdu.size() + 1)) + static_cast<char>(unit) + pdu;
}

/// How a peer puts a reply on the wire (whole, byte by byte, half and then nothing, ...).
using Sender = std::function<bool(int fd, const std::string& bytes)>;
const Sender kWhole = [](int fd, const std::string& bytes) { return RawTcpPeer::send(fd, bytes); };

/// A Modbus server in a few lines: answers reads with `value_of(offset)`, acknowledges writes.
RawTcpPeer::Session modbus_server(std::function<std::uint16_t(int)> value_of, Sender send = kWhole) {
  return [value_of, send](RawTcpPeer& peer, int fd) {
    std::string buf;
    while (auto r = read_request(peer, fd, buf)) {
      std::string pdu;
      if (r->function == 0x03) {
        pdu = std::string(1, '\x03') + static_cast<char>(2 * r->count);
        for (int i = 0; i < r->count; ++i) pdu += be16(value_of(r->address + i));
      } else if (r->function == 0x10) {
        pdu = std::string(1, '\x10') + be16(r->address) + be16(r->count);
      } else {
        pdu = std::string(1, static_cast<char>(r->function | 0x80)) + '\x01';
      }
      if (!send(fd, frame(r->transaction, r->unit, pdu))) return;
    }
  };
}

/// A valid, live PLC block (the heartbeat counts up on every read).
std::function<std::uint16_t(int)> good_plc() {
  auto heartbeat = std::make_shared<std::atomic<std::uint16_t>>(0);
  return [heartbeat](int address) -> std::uint16_t {
    switch (address - plc::reg::plc_block_start) {
      case plc::reg::interface_version: return plc::kInterfaceVersion;
      case plc::reg::plc_heartbeat: return (*heartbeat)++;
      case plc::reg::slide_state: return static_cast<std::uint16_t>(plc::SlideStatus::at_home);
      default: return 0;
    }
  };
}

/// A modbus_server() sender that sends a reply one byte at a time, `gap` apart.
auto byte_by_byte(milliseconds gap) {
  return [gap](int fd, const std::string& bytes) {
    for (const char c : bytes) {
      if (!RawTcpPeer::send(fd, std::string(1, c))) return false;
      std::this_thread::sleep_for(gap);
    }
    return true;
  };
}

class PlcBadPeer : public ::testing::Test {
 protected:
  void start(RawTcpPeer::Session session) {
    peer = std::make_unique<RawTcpPeer>(std::move(session));
    link = std::make_unique<plc::Link>(events.executor(), fast_options(peer->port()), events.handler());
    link->start();
  }
  void TearDown() override {
    if (link) link->stop();
    link.reset();
    peer.reset();
  }
  /// A good PLC whose every reply goes through `mangle` first: the link goes down with
  /// bad_reply naming `what`, never up.
  void expect_bad_reply(std::function<void(std::string&)> mangle, const std::string& what) {
    start(modbus_server(good_plc(), [mangle](int fd, const std::string& bytes) {
      auto b = bytes;
      mangle(b);
      return RawTcpPeer::send(fd, b);
    }));
    const auto down = events.wait_for<plc::LinkDown>(kWait);
    ASSERT_TRUE(down) << events.dump();
    EXPECT_EQ(down->reason, plc::LinkDownReason::bad_reply) << down->detail;
    EXPECT_NE(down->detail.find(what), std::string::npos) << down->detail;
    ASSERT_TRUE(events.wait_for<plc::Reconnecting>(kWait)) << events.dump();
    EXPECT_TRUE(events.all<plc::LinkUp>().empty()) << events.dump();
  }
  void expect_down_and_retried() {
    ASSERT_TRUE(events.wait_for<plc::LinkDown>(kWait)) << events.dump();
    ASSERT_TRUE(events.wait_for<plc::Reconnecting>(kWait)) << events.dump();
    EXPECT_TRUE(events.all<plc::LinkUp>().empty()) << events.dump();
  }

  EventLog events;  // declared first: destroyed after the link
  std::unique_ptr<RawTcpPeer> peer;
  std::unique_ptr<plc::Link> link;
};

}  // namespace

TEST_F(PlcBadPeer, SilentPeerIsATimeout) {
  start([](RawTcpPeer& p, int fd) { p.hold(fd, std::chrono::seconds(2)); });
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  EXPECT_EQ(down->reason, plc::LinkDownReason::timeout) << down->detail;
  // The LinkDown above was taken from the queue: what must follow is the retry, never a LinkUp.
  ASSERT_TRUE(events.wait_for<plc::Reconnecting>(kWait)) << events.dump();
  EXPECT_TRUE(events.all<plc::LinkUp>().empty()) << events.dump();
}

TEST_F(PlcBadPeer, PeerThatClosesAtOnceIsRetried) {
  start([](RawTcpPeer&, int) {});
  expect_down_and_retried();
  const auto deadline = std::chrono::steady_clock::now() + kWait;
  while (peer->connections() < 3 && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(milliseconds(10));
  EXPECT_GE(peer->connections(), 3);
}

TEST_F(PlcBadPeer, GarbageReplyIsALinkDown) {
  start([](RawTcpPeer& p, int fd) {
    std::string buf;
    if (read_request(p, fd, buf)) RawTcpPeer::send(fd, "HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n");
    p.hold(fd, milliseconds(500));
  });
  expect_down_and_retried();
}

TEST_F(PlcBadPeer, ReplyToAnotherTransactionIsALinkDown) {
  start([](RawTcpPeer& p, int fd) {
    std::string buf;
    while (auto r = read_request(p, fd, buf))
      RawTcpPeer::send(fd, frame(static_cast<std::uint16_t>(r->transaction + 1), r->unit,
                                 std::string("\x03\x10", 2) + std::string(16, '\0')));
  });
  expect_down_and_retried();
}

TEST_F(PlcBadPeer, ByteCountThatDisagreesWithTheRequestIsALinkDown) {
  start([](RawTcpPeer& p, int fd) {
    std::string buf;
    while (auto r = read_request(p, fd, buf))  // 3 registers where 8 were asked for
      RawTcpPeer::send(fd, frame(r->transaction, r->unit, std::string("\x03\x06", 2) + std::string(6, '\x01')));
  });
  expect_down_and_retried();
}

TEST_F(PlcBadPeer, MbapLengthClaimingMoreThanAFrameIsALinkDown) {
  start([](RawTcpPeer& p, int fd) {
    std::string buf;
    while (auto r = read_request(p, fd, buf))
      RawTcpPeer::send(fd, be16(r->transaction) + be16(0) + be16(0xFFFF) + static_cast<char>(r->unit) + "\x03\xff" +
                               std::string(300, '\x7f'));
  });
  expect_down_and_retried();
}

TEST_F(PlcBadPeer, ModbusExceptionIsALinkDownNamingIt) {
  start([](RawTcpPeer& p, int fd) {
    std::string buf;
    while (auto r = read_request(p, fd, buf))
      RawTcpPeer::send(fd, frame(r->transaction, r->unit, std::string("\x83\x02", 2)));  // illegal data address
  });
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  EXPECT_EQ(down->reason, plc::LinkDownReason::io_error) << down->detail;
  EXPECT_NE(down->detail.find("Modbus exception 2 (illegal data address)"), std::string::npos) << down->detail;
  EXPECT_TRUE(events.all<plc::LinkUp>().empty());
}

// Replies that libmodbus 3.1.6 takes as good, each otherwise a perfect answer from a live PLC
// (issue 40, item 8; the checks: modbus_frame.hpp, docs/plc-interface.md).
TEST_F(PlcBadPeer, AReplyWithProtocolId7IsABadReply) {
  expect_bad_reply([](std::string& b) { b[3] = 7; }, "protocol id 7");
}

TEST_F(PlcBadPeer, AReplyFromAnotherUnitIsABadReply) {
  expect_bad_reply([](std::string& b) { b[6] = static_cast<char>(b[6] + 1); }, "unit id 2 in the reply to unit 1");
}

TEST_F(PlcBadPeer, AnMbapLengthOf2IsABadReply) {
  expect_bad_reply([](std::string& b) { b[4] = 0, b[5] = 2; }, "MBAP length 2 where");
}

TEST_F(PlcBadPeer, AnMbapLengthOf0xFFFFIsABadReply) {
  expect_bad_reply([](std::string& b) { b[4] = b[5] = static_cast<char>(0xFF); }, "MBAP length 65535 where");
}

TEST_F(PlcBadPeer, AWriteReplyEchoingAnotherAddressIsABadReply) {
  expect_bad_reply([](std::string& b) { if (b[7] == 0x10) b[9] = static_cast<char>(b[9] + 1); },
                   "the write reply echoes address 17 where 16 was written");
}

// A reply that stops halfway (a PLC that hangs while sending) is a timeout, not a hang.
TEST_F(PlcBadPeer, AReplyThatStopsHalfwayIsATimeout) {
  start([](RawTcpPeer& p, int fd) {
    std::string buf;
    if (auto r = read_request(p, fd, buf))
      RawTcpPeer::send(fd, frame(r->transaction, r->unit, std::string("\x03\x14", 2) + std::string(20, '\0')).substr(0, 9));
    p.hold(fd, std::chrono::seconds(2));
  });
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  EXPECT_EQ(down->reason, plc::LinkDownReason::timeout) << down->detail;
  EXPECT_NE(down->detail.find("no reply within"), std::string::npos) << down->detail;
  EXPECT_TRUE(events.all<plc::LinkUp>().empty()) << events.dump();
}

// A slow PLC that answers one byte at a time, each well within the response timeout: that is
// Modbus TCP (a stream), and the link comes up.
TEST_F(PlcBadPeer, AReplySentByteByByteComesUp) {
  start(modbus_server(good_plc(), byte_by_byte(milliseconds(1))));
  ASSERT_TRUE(events.wait_for<plc::LinkUp>(kWait)) << events.dump();
  EXPECT_TRUE(events.all<plc::LinkDown>().empty()) << events.dump();
}

// A PLC dripping its reply a byte every 60 ms, each byte well within libmodbus's per-byte
// timeout (150 ms) but the whole reply taking seconds: the poll's deadline is the response
// timeout for the whole read, and the link goes down saying so (issue 40, item 7).
TEST_F(PlcBadPeer, AReplyDrippedSlowerThanTheDeadlineIsATimeout) {
  start(modbus_server(good_plc(), byte_by_byte(milliseconds(60))));
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  EXPECT_EQ(down->reason, plc::LinkDownReason::timeout) << down->detail;
  EXPECT_NE(down->detail.find("more than the poll's deadline"), std::string::npos) << down->detail;
  EXPECT_TRUE(events.all<plc::LinkUp>().empty()) << events.dump();
}

// After a hostile peer, the link comes up by itself once a good PLC answers on the same port.
TEST_F(PlcBadPeer, AfterGarbageTheLinkRecoversWhenAGoodPlcAnswers) {
  auto good = modbus_server(good_plc());
  auto connections = std::make_shared<std::atomic<int>>(0);
  start([good, connections](RawTcpPeer& p, int fd) {
    if ((*connections)++ < 2) {  // the first two connections: garbage
      std::string buf;
      if (read_request(p, fd, buf)) RawTcpPeer::send(fd, std::string(40, '\xff'));
      return;
    }
    good(p, fd);
  });
  const auto down = events.wait_for<plc::LinkDown>(kWait);
  ASSERT_TRUE(down) << events.dump();
  EXPECT_FALSE(down->detail.empty());
  ASSERT_TRUE(events.wait_for<plc::LinkUp>(kWait)) << events.dump();
  EXPECT_GE(connections->load(), 3);
}

TEST_F(PlcBadPeer, EveryRegisterAtItsMaximumIsOutOfRangeNeverUp) {
  start(modbus_server([](int) { return std::uint16_t{0xFFFF}; }));
  const auto bad = events.wait_for<plc::ValueOutOfRange>(kWait);
  ASSERT_TRUE(bad) << events.dump();
  EXPECT_EQ(bad->value, 0xFFFF);
  EXPECT_FALSE(bad->allowed.empty());
  std::this_thread::sleep_for(milliseconds(200));
  EXPECT_TRUE(events.all<plc::LinkUp>().empty()) << events.dump();
  EXPECT_TRUE(events.all<plc::CycleRequest>().empty()) << events.dump();
  EXPECT_TRUE(events.all<plc::PackMLCommand>().empty()) << events.dump();
}

TEST_F(PlcBadPeer, AValidBlockFromTheRawServerComesUp) {
  // The control case: the same hand-made server with a valid, live block is accepted.
  start(modbus_server(good_plc()));
  ASSERT_TRUE(events.wait_for<plc::LinkUp>(kWait)) << events.dump();
}
