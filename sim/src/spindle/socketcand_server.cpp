// A socketcand server (rawmode only, linux-can/socketcand doc/protocol.md) bridging TCP clients
// onto an in-process CAN bus.
#include <array>
#include <chrono>
#include <deque>
#include <list>

#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/write.hpp>

#include "fettle/core/error.hpp"
#include "fettle/core/log.hpp"
#include "fettle/sim/spindle.hpp"
#include "../cloexec.hpp"

namespace fettle::sim {

using boost::asio::ip::tcp;
using namespace fettle::canopen;

namespace {

class Session : public std::enable_shared_from_this<Session> {
 public:
  Session(boost::asio::io_context& io, tcp::socket socket, std::shared_ptr<InProcessBus> bus, std::string bus_name)
      : io_(io), socket_(std::move(socket)), bus_(std::move(bus)), bus_name_(std::move(bus_name)),
        log_(log::get("sim.socketcand")) {}

  void start() {
    boost::system::error_code ec;
    socket_.set_option(tcp::no_delay(true), ec);
    write("< hi >");
    read();
  }
  void close() {
    if (closed_) return;
    closed_ = true;
    if (node_) node_->close();
    boost::system::error_code ec;
    socket_.close(ec);
  }
  [[nodiscard]] bool closed() const { return closed_; }

 private:
  enum class State { no_bus, bus_open, raw };

  void read() {
    socket_.async_read_some(boost::asio::buffer(rx_), [self = shared_from_this()](const boost::system::error_code& ec,
                                                                                  std::size_t n) {
      if (self->closed_) return;
      if (ec) return self->close();
      self->buffer_.append(self->rx_.data(), n);
      auto messages = socketcand::take_messages(self->buffer_);
      if (!messages) {
        self->write("< error " + messages.error().message + " >");
        return self->close();
      }
      for (const auto& words : *messages) self->handle(words);
      if (!self->closed_) self->read();
    });
  }

  void handle(const std::vector<std::string>& words) {
    if (words.empty()) return;
    const auto& cmd = words[0];
    if (cmd == "echo") return write("< echo >");
    switch (state_) {
      case State::no_bus:
        if (cmd == "open" && words.size() == 2) {
          if (words[1] != bus_name_) return write("< error could not open bus '" + words[1] + "' >");
          state_ = State::bus_open;
          return write("< ok >");
        }
        return write("< error expected 'open BUS' >");
      case State::bus_open:
        if (cmd == "rawmode") {
          state_ = State::raw;
          attach();
          return write("< ok >");
        }
        return write("< error only rawmode is supported by this server >");
      case State::raw:
        if (cmd == "send") {
          auto f = socketcand::parse_send(words);
          if (!f) return write("< error " + f.error().message + " >");
          node_->send(*f);
          return;
        }
        return write("< error unknown command in rawmode >");
    }
  }

  void attach() {
    node_ = bus_->attach(io_, "socketcand");
    std::weak_ptr<Session> weak = shared_from_this();
    node_->start(
        [weak](const CanFrame& f) {
          auto self = weak.lock();
          if (!self || self->closed_) return;
          const double t = std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
          self->write(socketcand::format_frame(f, t));
        },
        [](const Error&) {});
  }

  void write(std::string text) {
    if (closed_) return;
    out_.push_back(std::move(text));
    if (out_.size() == 1) write_front();
  }
  void write_front() {
    boost::asio::async_write(socket_, boost::asio::buffer(out_.front()),
                             [self = shared_from_this()](const boost::system::error_code& ec, std::size_t) {
                               if (self->closed_) return;
                               if (ec) return self->close();
                               self->out_.pop_front();
                               if (!self->out_.empty()) self->write_front();
                             });
  }

  boost::asio::io_context& io_;
  tcp::socket socket_;
  std::shared_ptr<InProcessBus> bus_;
  std::string bus_name_;
  std::shared_ptr<spdlog::logger> log_;
  std::shared_ptr<CanTransport> node_;
  State state_ = State::no_bus;
  bool closed_ = false;
  std::array<char, 4096> rx_{};
  std::string buffer_;
  std::deque<std::string> out_;
};

}  // namespace

struct SocketcandServer::Impl : std::enable_shared_from_this<Impl> {
  Impl(boost::asio::io_context& io_, std::shared_ptr<InProcessBus> b, std::string name)
      : io(io_), acceptor(io_), bus(std::move(b)), bus_name(std::move(name)) {}
  boost::asio::io_context& io;
  tcp::acceptor acceptor;
  std::shared_ptr<InProcessBus> bus;
  std::string bus_name;
  std::list<std::weak_ptr<Session>> sessions;
  bool closed = false;

  void accept() {
    acceptor.async_accept([self = shared_from_this()](const boost::system::error_code& ec, tcp::socket socket) {
      if (self->closed || ec == boost::asio::error::operation_aborted) return;
      if (!ec) {
        detail::set_cloexec(socket.native_handle());
        auto s = std::make_shared<Session>(self->io, std::move(socket), self->bus, self->bus_name);
        self->sessions.remove_if([](const auto& w) { return w.expired(); });
        self->sessions.push_back(s);
        s->start();
      }
      self->accept();
    });
  }
  void drop_all() {
    for (auto& w : sessions)
      if (auto s = w.lock()) s->close();
    sessions.clear();
  }
};

SocketcandServer::SocketcandServer(boost::asio::io_context& io, std::shared_ptr<InProcessBus> bus,
                                   const std::string& address, int port, std::string bus_name)
    : impl_(std::make_shared<Impl>(io, std::move(bus), std::move(bus_name))) {
  boost::system::error_code ec;
  const auto addr = boost::asio::ip::make_address(address, ec);
  if (ec) throw UserError("socketcand server: '" + address + "' is not an IP address");
  const tcp::endpoint ep(addr, static_cast<unsigned short>(port));
  impl_->acceptor.open(ep.protocol(), ec);
  if (!ec) detail::set_cloexec(impl_->acceptor.native_handle());
  if (!ec) impl_->acceptor.set_option(tcp::acceptor::reuse_address(true), ec);
  if (!ec) impl_->acceptor.bind(ep, ec);
  if (!ec) impl_->acceptor.listen(tcp::acceptor::max_listen_connections, ec);
  if (ec)
    throw DeviceError("socketcand server: cannot listen on " + address + ":" + std::to_string(port) + ": " +
                      ec.message() + " (port in use? use port 0 for any free port)");
  impl_->accept();
}

SocketcandServer::~SocketcandServer() {
  impl_->closed = true;
  boost::system::error_code ec;
  impl_->acceptor.close(ec);
  impl_->drop_all();
}

int SocketcandServer::port() const { return impl_->acceptor.local_endpoint().port(); }

std::size_t SocketcandServer::clients() const {
  std::size_t n = 0;
  for (const auto& w : impl_->sessions)
    if (auto s = w.lock(); s && !s->closed()) ++n;
  return n;
}

void SocketcandServer::disconnect_all() { impl_->drop_all(); }

}  // namespace fettle::sim
