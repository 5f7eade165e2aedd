// Fuzz target: CANopen frame handling (drivers/canopen.hpp, canopen_transport.hpp).
//  1. The bytes as a socketcand TCP stream (split into reads of varying size): every element
//     is parsed as a server "frame" and a client "send"; a frame that parses formats back to
//     the same frame.
//  2. The bytes as raw CAN frames (id, flags, length, data) decoded as SDO (both directions),
//     EMCY and statusword, and fed to the spindle master (drivers::SpindleDrive) on an
//     in-process bus while it starts up, as a broken or hostile node on the bus would send them.
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>

#include "fettle/drivers/canopen.hpp"
#include "fettle/drivers/canopen_transport.hpp"
#include "fettle/drivers/spindle.hpp"
#include "fuzz_input.hpp"

namespace canopen = fettle::canopen;

namespace {

void check_frame(const canopen::CanFrame& f) {
  FUZZ_CHECK(f.len <= 8);
  (void)canopen::to_string(f);
  for (bool from_client : {true, false}) {
    if (auto sdo = canopen::decode_sdo(f, from_client)) {
      FUZZ_CHECK(sdo->size <= 4);
      (void)canopen::abort_code_text(sdo->value);
    }
  }
  if (auto e = canopen::decode_emcy(f)) {
    (void)canopen::describe(*e);
    (void)canopen::emcy_code_text(e->error_code);
  }
  std::uint16_t sw = 0;
  if (f.len >= 2) sw = static_cast<std::uint16_t>(f.data[0] | (f.data[1] << 8));
  (void)canopen::to_string(canopen::decode_statusword(sw));
}

void socketcand_stream(std::string_view stream) {
  std::string buffer;
  std::size_t pos = 0;
  std::size_t piece = 7;
  while (pos < stream.size()) {
    const auto chunk = stream.substr(pos, piece);
    pos += chunk.size();
    piece = piece * 5 % 97 + 1;
    buffer.append(chunk);
    auto messages = canopen::socketcand::take_messages(buffer);
    if (!messages) return;  // the connection is dropped
    FUZZ_CHECK(buffer.empty() || (buffer[0] == '<' && buffer.size() <= 257));
    for (const auto& words : *messages) {
      if (auto f = canopen::socketcand::parse_frame(words)) {
        check_frame(*f);
        std::string text = canopen::socketcand::format_frame(*f, 1.5);
        auto again = canopen::socketcand::take_messages(text);
        FUZZ_CHECK(again.ok() && again->size() == 1);
        auto g = canopen::socketcand::parse_frame(again->front());
        FUZZ_CHECK(g.ok() && *g == *f);
      }
      if (auto f = canopen::socketcand::parse_send(words)) {
        check_frame(*f);
        std::string text = canopen::socketcand::format_send(*f);
        auto again = canopen::socketcand::take_messages(text);
        FUZZ_CHECK(again.ok() && again->size() == 1);
        auto g = canopen::socketcand::parse_send(again->front());
        FUZZ_CHECK(g.ok() && *g == *f);
      }
    }
  }
}

canopen::CanFrame take_frame(fettle::fuzz::ByteReader& in) {
  canopen::CanFrame f;
  const auto flags = in.take<std::uint8_t>();
  f.extended = (flags & 1U) != 0;
  f.rtr = (flags & 2U) != 0;
  // Mostly the drive's and the master's COB-IDs (node 1), sometimes any identifier.
  const auto id = in.take<std::uint16_t>();
  static constexpr std::uint32_t kBases[] = {canopen::kNmtId,      canopen::kEmcyBase + 1, canopen::kTpdo1Base + 1,
                                             canopen::kSdoTxBase + 1, canopen::kSdoRxBase + 1,
                                             canopen::kHeartbeatBase + 1};
  f.id = (flags & 4U) != 0 ? id & (f.extended ? 0x1FFFFFFFU : 0x7FFU) : kBases[id % 6];
  f.len = static_cast<std::uint8_t>(in.take<std::uint8_t>() % 9);
  for (std::size_t i = 0; i < f.len; ++i) f.data[i] = in.take<std::uint8_t>();
  return f;
}

void bus_frames(fettle::fuzz::ByteReader& in) {
  boost::asio::io_context io;
  auto bus = canopen::InProcessBus::create();
  auto hostile = bus->attach(io, "hostile");
  hostile->start([](const canopen::CanFrame&) {}, [](const fettle::Error&) {});
  fettle::drivers::SpindleDrive master(io, bus->attach(io, "master"), fettle::drivers::SpindleOptions{});
  master.on_event([](const fettle::drivers::SpindleEvent& e) { (void)fettle::drivers::to_string(e.kind); });
  (void)master.configure();
  master.activate_async([](fettle::Status) {});
  master.sdo_read(canopen::od::statusword, 0, [](fettle::Result<std::uint32_t>) {});
  int frames = 0;
  while (in.remaining() > 0 && frames++ < 256) {
    const auto f = take_frame(in);
    check_frame(f);
    hostile->send(f);
    io.poll();
    const auto& st = master.status();
    (void)canopen::to_string(st.state);
  }
  io.poll();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fettle::fuzz::ByteReader in(data, size);
  if (in.take<std::uint8_t>() % 2 == 0) {
    socketcand_stream(in.rest());
  } else {
    bus_frames(in);
  }
  return 0;
}
