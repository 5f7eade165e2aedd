// RobotLink against peers that are not a robot controller, or a broken one: a raw TCP
// server on 127.0.0.1 that says nothing, closes at once, sends binary garbage, an endless
// line, lines out of sequence or replies nobody asked for. Every case ends in a specific
// error, the link never reports ready on garbage, and it keeps reconnecting.
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <functional>
#include <memory>
#include <thread>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>
#include <boost/asio/steady_timer.hpp>

#include "../support/raw_tcp_peer.hpp"
#include "fettle/drivers/robot_link.hpp"

using fettle::drivers::RobotLink;
using fettle::drivers::RobotLinkOptions;
using fettle::drivers::RobotState;
using fettle::test::RawTcpPeer;
using namespace std::chrono_literals;

namespace {

class RobotBadPeer : public ::testing::Test {
 protected:
  void start(RawTcpPeer::Session session) {
    peer_ = std::make_unique<RawTcpPeer>(std::move(session));
    RobotLinkOptions o;
    o.port = peer_->port();
    o.cell_id = "test-cell";
    o.connect_timeout_ms = 300;
    o.reply_timeout_ms = 300;
    o.ping_period_ms = 50;
    o.missed_pings = 3;
    o.reconnect_initial_ms = 20;
    o.reconnect_max_ms = 50;
    link_ = std::make_unique<RobotLink>(io_, o);
    link_->on_state([this](RobotState s, const fettle::Error& e) {
      states_.push_back(s);
      if (!e.code.empty()) errors_.push_back(e);
    });
    link_->start();
  }

  bool run_until(const std::function<bool()>& pred, std::chrono::milliseconds timeout = 5000ms) {
    const auto end = std::chrono::steady_clock::now() + timeout;
    while (!pred()) {
      if (std::chrono::steady_clock::now() > end) return false;
      io_.run_for(5ms);
      if (io_.stopped()) io_.restart();
    }
    return true;
  }

  [[nodiscard]] bool saw(const std::string& code) const {
    return std::any_of(errors_.begin(), errors_.end(), [&](const fettle::Error& e) { return e.code == code; });
  }
  [[nodiscard]] std::string message_of(const std::string& code) const {
    for (const auto& e : errors_)
      if (e.code == code) return e.message;
    return {};
  }
  [[nodiscard]] bool was_ready() const {
    return std::find(states_.begin(), states_.end(), RobotState::ready) != states_.end();
  }
  [[nodiscard]] std::string error_codes() const {
    std::string s;
    for (const auto& e : errors_) s += e.code + " ";
    return s;
  }

  void TearDown() override {
    if (link_) link_->shutdown();
    run_until([] { return false; }, 20ms);
    link_.reset();
    peer_.reset();
  }

  /// A session that reads the HELLO line, then sends `reply` and keeps the connection open.
  static RawTcpPeer::Session after_hello(std::string reply) {
    return [reply](RawTcpPeer& peer, int fd) {
      std::string got;
      while (got.find('\n') == std::string::npos && !peer.stop_requested()) got += peer.read_some(fd);
      RawTcpPeer::send(fd, reply);
      peer.hold(fd, 1s);
    };
  }

  /// A well-behaved robot, by hand: ACKs HELLO, PONGs every PING; `send` puts each line on the wire.
  static RawTcpPeer::Session good_robot(std::function<bool(int, const std::string&)> send) {
    return [send](RawTcpPeer& peer, int fd) {
      std::string buf;
      int seq = 0;
      while (!peer.stop_requested()) {
        const auto got = peer.read_some(fd, 20ms);
        buf += got;
        for (auto nl = buf.find('\n'); nl != std::string::npos; nl = buf.find('\n')) {
          const std::string line = buf.substr(0, nl);
          buf.erase(0, nl + 1);
          const auto sp = line.find(' ');
          const std::string ref = line.substr(0, sp);
          std::string reply;
          if (line.find(" HELLO ") != std::string::npos) reply = "ACK " + ref + " 1 hand-made";
          if (line.find(" PING") != std::string::npos) reply = "PONG " + ref;
          if (!reply.empty() && !send(fd, std::to_string(++seq) + " " + reply + "\n")) return;
        }
      }
    };
  }

  /// Drives the link until `pred`, with a probe timer every 10 ms on the link's own io_context:
  /// returns the largest lateness of the probe (the event loop's worst stall).
  std::chrono::milliseconds worst_stall_until(const std::function<bool()>& pred) {
    boost::asio::steady_timer probe(io_);
    std::chrono::steady_clock::duration worst{};
    std::function<void()> arm = [&] {
      const auto due = std::chrono::steady_clock::now() + 10ms;
      probe.expires_at(due);
      probe.async_wait([&, due](const boost::system::error_code& ec) {
        if (ec) return;
        worst = std::max(worst, std::chrono::steady_clock::now() - due);
        arm();
      });
    };
    arm();
    EXPECT_TRUE(run_until(pred)) << error_codes();
    probe.cancel();
    run_until([] { return false; }, 5ms);
    return std::chrono::duration_cast<std::chrono::milliseconds>(worst);
  }

  boost::asio::io_context io_;
  std::unique_ptr<RawTcpPeer> peer_;
  std::unique_ptr<RobotLink> link_;
  std::vector<RobotState> states_;
  std::vector<fettle::Error> errors_;
};

}  // namespace

TEST_F(RobotBadPeer, SilentPeerTimesOutAndIsRetried) {
  start([](RawTcpPeer& peer, int fd) { peer.hold(fd, 2s); });
  ASSERT_TRUE(run_until([&] { return saw("robot.reply_timeout"); })) << error_codes();
  EXPECT_FALSE(was_ready());
  EXPECT_GT(peer_->bytes_received(), 0) << "the link sent no HELLO";
  EXPECT_NE(message_of("robot.reply_timeout").find("HELLO"), std::string::npos) << message_of("robot.reply_timeout");
}

TEST_F(RobotBadPeer, PeerThatClosesAtOnceIsRetriedWithBackoff) {
  start([](RawTcpPeer&, int) {});
  ASSERT_TRUE(run_until([&] { return peer_->connections() >= 3; })) << error_codes();
  EXPECT_TRUE(saw("robot.connection_lost")) << error_codes();
  EXPECT_FALSE(was_ready());
  EXPECT_EQ(link_->state() == RobotState::ready, false);
}

TEST_F(RobotBadPeer, BinaryGarbageIsAProtocolError) {
  start(after_hello(std::string("\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\n\xff\xfe\n", 15)));
  ASSERT_TRUE(run_until([&] { return saw("robot.protocol"); })) << error_codes();
  EXPECT_FALSE(was_ready());
  ASSERT_TRUE(run_until([&] { return peer_->connections() >= 2; }));  // and it reconnects
}

TEST_F(RobotBadPeer, EndlessLineIsCutAtEightyCharacters) {
  start(after_hello(std::string(1 << 20, 'A')));
  ASSERT_TRUE(run_until([&] { return saw("robot.protocol"); })) << error_codes();
  EXPECT_NE(message_of("robot.protocol").find("longer than 80"), std::string::npos) << message_of("robot.protocol");
  EXPECT_FALSE(was_ready());
}

TEST_F(RobotBadPeer, FirstLineWithTheWrongSequenceNumberIsASeqError) {
  start(after_hello("5 ACK 1 1 robot\n"));
  ASSERT_TRUE(run_until([&] { return saw("robot.seq"); })) << error_codes();
  EXPECT_FALSE(was_ready());
}

TEST_F(RobotBadPeer, VerbsOnlyFettleMaySendAreAProtocolError) {
  start(after_hello("1 HELLO 1 cell 1000\n"));
  ASSERT_TRUE(run_until([&] { return saw("robot.protocol"); })) << error_codes();
  EXPECT_FALSE(was_ready());
}

TEST_F(RobotBadPeer, AnotherProtocolVersionIsRefused) {
  start(after_hello("1 ACK 1 7 robot\n"));
  ASSERT_TRUE(run_until([&] { return saw("robot.version"); })) << error_codes();
  EXPECT_FALSE(was_ready());
}

TEST_F(RobotBadPeer, HelloAckWithoutVersionIsAProtocolError) {
  start(after_hello("1 ACK 1\n"));
  ASSERT_TRUE(run_until([&] { return saw("robot.protocol"); })) << error_codes();
  EXPECT_FALSE(was_ready());
}

// A reply that stops mid-line (a controller that hangs while sending) is a reply timeout, and
// the event loop is never blocked meanwhile.
TEST_F(RobotBadPeer, ALineThatStopsHalfwayIsAReplyTimeoutNeverAStall) {
  start(after_hello("1 ACK 1 1 rob"));
  const auto stall = worst_stall_until([&] { return saw("robot.reply_timeout"); });
  EXPECT_FALSE(was_ready());
  EXPECT_LT(stall, 100ms) << "the link's event loop stalled";
  EXPECT_NE(message_of("robot.reply_timeout").find("ms"), std::string::npos) << message_of("robot.reply_timeout");
}

// A controller that writes its replies one byte at a time (a stream, as TCP is) is read line by
// line, and the event loop keeps running between the bytes.
TEST_F(RobotBadPeer, ARobotThatAnswersByteByByteIsReady) {
  start(good_robot([](int fd, const std::string& line) {
    for (const char c : line) {
      if (!RawTcpPeer::send(fd, std::string(1, c))) return false;
      std::this_thread::sleep_for(2ms);
    }
    return true;
  }));
  const auto stall = worst_stall_until([&] { return was_ready(); });
  EXPECT_LT(stall, 100ms) << "the link's event loop stalled";
  // and it stays up: its PINGs are answered, byte by byte
  run_until([] { return false; }, 300ms);
  EXPECT_EQ(link_->state(), RobotState::ready) << error_codes();
}

// After garbage the link reconnects by itself and is ready once the controller answers well.
TEST_F(RobotBadPeer, AfterGarbageTheLinkRecoversWhenTheRobotAnswersWell) {
  auto good = good_robot([](int fd, const std::string& line) { return RawTcpPeer::send(fd, line); });
  auto connections = std::make_shared<int>(0);
  start([good, connections](RawTcpPeer& peer, int fd) {
    if ((*connections)++ == 0) {
      (void)peer.read_some(fd);
      RawTcpPeer::send(fd, "\x01\x02 garbage \xff\xfe\n");
      return;
    }
    good(peer, fd);
  });
  ASSERT_TRUE(run_until([&] { return saw("robot.protocol") && link_->state() == RobotState::ready; })) << error_codes();
  EXPECT_NE(message_of("robot.protocol").find("byte 0x01 at column 1"), std::string::npos) << message_of("robot.protocol");
}

TEST_F(RobotBadPeer, RepliesNobodyAskedForAreIgnoredThenALostLineIsCaught) {
  // A valid HELLO ACK, then replies to nothing (ignored, the link stays ready), then a
  // skipped sequence number (a lost line): robot.seq.
  start(after_hello("1 ACK 1 1 robot\n2 ACK 77\n3 DONE 5 10\n4 PROG 9 1 1\n5 NAK 99 SYNTAX what\n"
                    "7 PONG 1\n"));
  ASSERT_TRUE(run_until([&] { return saw("robot.seq"); })) << error_codes();
  EXPECT_TRUE(was_ready());
  EXPECT_EQ(errors_.front().code, "robot.seq") << error_codes();
  EXPECT_NE(errors_.front().message.find("expected 6"), std::string::npos) << errors_.front().message;
}
