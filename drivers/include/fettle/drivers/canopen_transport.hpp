#pragma once
// Where CAN frames come from and go to. Three implementations of one interface:
//  - SocketCAN: a CAN_RAW socket (can0, vcan0) in the Asio loop, with filters and error frames;
//  - socketcand: CAN frames over TCP with socketcand's rawmode ASCII protocol (linux-can project),
//    so the master and a drive simulator in another process meet on loopback;
//  - an in-process bus: every attached node sees every other node's frames.
// All handlers run on the io_context the transport was made with; send() never blocks.
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>

#include "fettle/core/result.hpp"
#include "fettle/drivers/canopen.hpp"

namespace fettle::canopen {

class CanTransport {
 public:
  using FrameHandler = std::function<void(const CanFrame&)>;
  /// A link problem (socket error, connection lost, handshake refused, SocketCAN error frame).
  using ErrorHandler = std::function<void(const Error&)>;

  virtual ~CanTransport() = default;
  /// Starts receiving. Handlers are called on the transport's io_context until close().
  virtual void start(FrameHandler on_frame, ErrorHandler on_error) = 0;
  /// Queues a frame for sending; failures are reported through the error handler.
  virtual void send(const CanFrame& frame) = 0;
  /// Stops receiving and drops the handlers (none is called afterwards).
  virtual void close() = 0;
  /// "socketcan:can0", "socketcand:127.0.0.1:29536/can0", "bus:drive" — for logs and errors.
  [[nodiscard]] virtual std::string name() const = 0;
};

// ---------------------------------------------------------------- in-process bus
/// A CAN bus inside one process. Nodes may live on different io_contexts (threads).
class InProcessBus : public std::enable_shared_from_this<InProcessBus> {
 public:
  static std::shared_ptr<InProcessBus> create();
  /// A new node on the bus whose handlers run on `io`.
  std::shared_ptr<CanTransport> attach(boost::asio::io_context& io, std::string name = "node");
  /// Cuts (false) or restores (true) the wire: while cut, frames are dropped (to test heartbeat loss).
  void set_connected(bool connected);
  /// Frames put on the wire so far.
  [[nodiscard]] std::uint64_t frames_sent() const;

  struct Impl;

 private:
  InProcessBus();
  std::shared_ptr<Impl> impl_;
};

// ---------------------------------------------------------------- SocketCAN
/// A receive filter: a frame passes when (frame.id & mask) == (id & mask).
struct CanFilter {
  std::uint32_t id = 0;
  std::uint32_t mask = 0;
};

/// Whether this kernel can open a CAN_RAW socket; if not, `why` says so (e.g. no AF_CAN).
bool socketcan_available(std::string* why = nullptr);

/// Opens a CAN_RAW socket bound to `interface` with `filters` (empty: everything) and all
/// error-frame classes enabled. Throws fettle::DeviceError (no AF_CAN, no such interface).
std::shared_ptr<CanTransport> open_socketcan(boost::asio::io_context& io, const std::string& interface,
                                             const std::vector<CanFilter>& filters = {});

// ---------------------------------------------------------------- socketcand
/// Connects (asynchronously) to a socketcand server and opens `bus` in rawmode. Frames sent
/// before the handshake finishes are queued; connection or handshake failures go to the
/// error handler.
std::shared_ptr<CanTransport> open_socketcand(boost::asio::io_context& io, const std::string& address, int port,
                                              const std::string& bus);

/// The socketcand rawmode ASCII protocol, shared by the client above and the simulator's server.
namespace socketcand {
/// Server → client: "< frame 181 12.000345 11223344 >" (id in hex, data as one hex string).
std::string format_frame(const CanFrame& f, double timestamp_s);
/// Client → server: "< send 601 8 40 41 60 00 00 00 00 00 >".
std::string format_send(const CanFrame& f);
/// Removes every complete "< ... >" element from the front of `buffer` and returns the words
/// of each. Bytes before a '<' are dropped. An element over 256 characters is an error.
Result<std::vector<std::vector<std::string>>> take_messages(std::string& buffer);
/// Parses the words of a "frame" element (server → client).
Result<CanFrame> parse_frame(const std::vector<std::string>& words);
/// Parses the words of a "send" element (client → server).
Result<CanFrame> parse_send(const std::vector<std::string>& words);
}  // namespace socketcand

}  // namespace fettle::canopen
