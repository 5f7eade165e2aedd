// SocketCAN transport: a CAN_RAW socket read and written in the Asio loop through
// posix::stream_descriptor (one struct can_frame per read/write).
#include <cerrno>
#include <cstring>
#include <deque>

#include <linux/can.h>
#include <linux/can/error.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <sys/socket.h>
#include <unistd.h>

#include <boost/asio/posix/stream_descriptor.hpp>
#include <boost/asio/write.hpp>

#include "fettle/core/error.hpp"
#include "fettle/drivers/canopen_transport.hpp"

namespace fettle::canopen {

namespace {

std::string errno_text(int e) { return std::strerror(e); }

can_frame to_linux(const CanFrame& f) {
  can_frame out{};
  out.can_id = f.id & (f.extended ? CAN_EFF_MASK : CAN_SFF_MASK);
  if (f.extended) out.can_id |= CAN_EFF_FLAG;
  if (f.rtr) out.can_id |= CAN_RTR_FLAG;
  out.len = f.len > 8 ? 8 : f.len;
  std::memcpy(out.data, f.data.data(), out.len);
  return out;
}

CanFrame from_linux(const can_frame& in) {
  CanFrame f;
  f.extended = (in.can_id & CAN_EFF_FLAG) != 0;
  f.rtr = (in.can_id & CAN_RTR_FLAG) != 0;
  f.error = (in.can_id & CAN_ERR_FLAG) != 0;
  f.id = in.can_id & (f.error ? CAN_ERR_MASK : f.extended ? CAN_EFF_MASK : CAN_SFF_MASK);
  f.len = in.len > 8 ? 8 : in.len;
  std::memcpy(f.data.data(), in.data, f.len);
  return f;
}

std::string describe_error_frame(const CanFrame& f) {
  std::string s = "CAN error frame:";
  if (f.id & CAN_ERR_TX_TIMEOUT) s += " TX timeout;";
  if (f.id & CAN_ERR_LOSTARB) s += " lost arbitration;";
  if (f.id & CAN_ERR_CRTL) s += " controller problem;";
  if (f.id & CAN_ERR_PROT) s += " protocol violation;";
  if (f.id & CAN_ERR_TRX) s += " transceiver problem (check wiring);";
  if (f.id & CAN_ERR_ACK) s += " no ACK on transmission (no other node on the bus, or missing termination);";
  if (f.id & CAN_ERR_BUSOFF) s += " bus off;";
  if (f.id & CAN_ERR_BUSERROR) s += " bus error;";
  if (f.id & CAN_ERR_RESTARTED) s += " controller restarted;";
  return s;
}

class SocketCan : public CanTransport, public std::enable_shared_from_this<SocketCan> {
 public:
  SocketCan(boost::asio::io_context& io, int fd, std::string interface)
      : stream_(io, fd), interface_(std::move(interface)) {}

  void start(FrameHandler on_frame, ErrorHandler on_error) override {
    on_frame_ = std::move(on_frame);
    on_error_ = std::move(on_error);
    read();
  }
  void send(const CanFrame& frame) override {
    if (!stream_.is_open()) return;
    queue_.push_back(to_linux(frame));
    if (queue_.size() == 1) write();
  }
  void close() override {
    on_frame_ = nullptr;
    on_error_ = nullptr;
    boost::system::error_code ec;
    stream_.close(ec);
  }
  [[nodiscard]] std::string name() const override { return "socketcan:" + interface_; }

 private:
  void read() {
    stream_.async_read_some(boost::asio::buffer(&rx_, sizeof rx_),
                            [self = shared_from_this()](const boost::system::error_code& ec, std::size_t n) {
                              if (ec == boost::asio::error::operation_aborted || !self->stream_.is_open()) return;
                              if (ec) return self->fail("read: " + ec.message());
                              if (n == sizeof(can_frame)) {
                                const CanFrame f = from_linux(self->rx_);
                                if (f.error) {
                                  if (self->on_error_)
                                    self->on_error_(Error{"can.error_frame", self->name() + ": " +
                                                                                 describe_error_frame(f)});
                                } else if (self->on_frame_) {
                                  self->on_frame_(f);
                                }
                              }
                              self->read();
                            });
  }
  void write() {
    boost::asio::async_write(stream_, boost::asio::buffer(&queue_.front(), sizeof(can_frame)),
                             [self = shared_from_this()](const boost::system::error_code& ec, std::size_t) {
                               if (ec == boost::asio::error::operation_aborted || !self->stream_.is_open()) return;
                               self->queue_.pop_front();
                               if (ec) self->fail("write: " + ec.message() + " (is the interface up? the TX queue full?)");
                               if (!self->queue_.empty()) self->write();
                             });
  }
  void fail(const std::string& what) {
    if (on_error_) on_error_(Error{"can.socket", name() + ": " + what});
  }

  boost::asio::posix::stream_descriptor stream_;
  std::string interface_;
  can_frame rx_{};
  std::deque<can_frame> queue_;
  FrameHandler on_frame_;
  ErrorHandler on_error_;
};

}  // namespace

bool socketcan_available(std::string* why) {
  const int fd = ::socket(PF_CAN, SOCK_RAW, CAN_RAW);
  if (fd < 0) {
    if (why != nullptr)
      *why = "socket(PF_CAN, SOCK_RAW, CAN_RAW) failed: " + errno_text(errno) +
             " (this kernel has no AF_CAN / can-raw support)";
    return false;
  }
  ::close(fd);
  return true;
}

std::shared_ptr<CanTransport> open_socketcan(boost::asio::io_context& io, const std::string& interface,
                                             const std::vector<CanFilter>& filters) {
  const int fd = ::socket(PF_CAN, SOCK_RAW | SOCK_NONBLOCK | SOCK_CLOEXEC, CAN_RAW);
  if (fd < 0)
    throw DeviceError("spindle: cannot open a CAN_RAW socket: " + errno_text(errno) +
                      " (does this kernel have SocketCAN? try 'modprobe can-raw')");
  auto fail = [&](const std::string& what) {
    const std::string e = errno_text(errno);
    ::close(fd);
    throw DeviceError("spindle: CAN interface '" + interface + "': " + what + ": " + e);
  };
  const unsigned index = ::if_nametoindex(interface.c_str());
  if (index == 0) fail("no such interface (bring it up first, see docs/spindle-canopen.md)");
  if (!filters.empty()) {
    std::vector<can_filter> f;
    for (const auto& c : filters) f.push_back(can_filter{c.id, c.mask});
    if (::setsockopt(fd, SOL_CAN_RAW, CAN_RAW_FILTER, f.data(), static_cast<socklen_t>(f.size() * sizeof(can_filter))) != 0)
      fail("setting the receive filters");
  }
  const can_err_mask_t err_mask = CAN_ERR_MASK;
  if (::setsockopt(fd, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, &err_mask, sizeof err_mask) != 0)
    fail("enabling error frames");
  sockaddr_can addr{};
  addr.can_family = AF_CAN;
  addr.can_ifindex = static_cast<int>(index);
  if (::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) fail("bind");
  return std::make_shared<SocketCan>(io, fd, interface);
}

}  // namespace fettle::canopen
