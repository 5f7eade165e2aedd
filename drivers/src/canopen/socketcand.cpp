// socketcand rawmode client (linux-can/socketcand doc/protocol.md) and the protocol's codec.
//   server: < hi >            client: < open can0 >
//   server: < ok >            client: < rawmode >
//   server: < ok >            then frames both ways:
//   server: < frame 181 12.000345 11223344 >   client: < send 601 8 40 41 60 00 00 00 00 00 >
#include <array>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <deque>

#include <boost/asio/connect.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/write.hpp>

#include "fettle/drivers/canopen_transport.hpp"

namespace fettle::canopen {

namespace socketcand {

namespace {

bool parse_hex(const std::string& s, std::uint32_t& out) {
  if (s.empty() || s.size() > 8) return false;
  const auto* end = s.data() + s.size();
  auto [p, ec] = std::from_chars(s.data(), end, out, 16);
  return ec == std::errc() && p == end;
}

Error bad(const std::vector<std::string>& words, const std::string& why) {
  std::string text = "<";
  for (const auto& w : words) text += " " + w;
  return Error{"socketcand.bad_message", "socketcand: cannot parse '" + text + " >': " + why};
}

Result<std::uint32_t> parse_id(const std::vector<std::string>& words, const std::string& id, bool& extended) {
  std::uint32_t v = 0;
  if (!parse_hex(id, v)) return bad(words, "identifier '" + id + "' is not hex");
  extended = id.size() > 3;
  if (v > (extended ? 0x1FFFFFFFU : 0x7FFU)) return bad(words, "identifier out of range");
  return v;
}

}  // namespace

std::string format_frame(const CanFrame& f, double timestamp_s) {
  char buf[96];
  const long long total_us = std::llround(timestamp_s * 1e6);
  const long long secs = total_us / 1000000;
  const long long usecs = total_us % 1000000;
  std::snprintf(buf, sizeof buf, f.extended ? "< frame %08X %lld.%06lld " : "< frame %03X %lld.%06lld ", f.id, secs,
                usecs);
  std::string s = buf;
  for (std::size_t i = 0; i < f.len && i < 8; ++i) {
    std::snprintf(buf, sizeof buf, "%02X", static_cast<unsigned>(f.data[i]));
    s += buf;
  }
  return s + (f.len > 0 ? " >" : ">");
}

std::string format_send(const CanFrame& f) {
  char buf[32];
  std::snprintf(buf, sizeof buf, f.extended ? "< send %08X %u" : "< send %03X %u", f.id, static_cast<unsigned>(f.len));
  std::string s = buf;
  for (std::size_t i = 0; i < f.len && i < 8; ++i) {
    std::snprintf(buf, sizeof buf, " %02X", static_cast<unsigned>(f.data[i]));
    s += buf;
  }
  return s + " >";
}

Result<std::vector<std::vector<std::string>>> take_messages(std::string& buffer) {
  std::vector<std::vector<std::string>> out;
  std::size_t pos = 0;
  while (true) {
    const auto open = buffer.find('<', pos);
    if (open == std::string::npos) {
      pos = buffer.size();
      break;
    }
    const auto close = buffer.find('>', open);
    if (close == std::string::npos) {
      pos = open;
      if (buffer.size() - open > 256)
        return Error{"socketcand.bad_message", "socketcand: element longer than 256 characters without '>'"};
      break;
    }
    std::vector<std::string> words;
    std::string word;
    for (std::size_t i = open + 1; i < close; ++i) {
      const char c = buffer[i];
      if (c == ' ' || c == '\t' || c == '\r' || c == '\n') {
        if (!word.empty()) words.push_back(std::move(word));
        word.clear();
      } else {
        word += c;
      }
    }
    if (!word.empty()) words.push_back(std::move(word));
    out.push_back(std::move(words));
    pos = close + 1;
  }
  buffer.erase(0, pos);
  return out;
}

Result<CanFrame> parse_frame(const std::vector<std::string>& words) {
  // frame ID SECS.USECS [DATA]
  if (words.size() < 3 || words.size() > 4 || words[0] != "frame") return bad(words, "expected 'frame ID TIME DATA'");
  CanFrame f;
  auto id = parse_id(words, words[1], f.extended);
  if (!id) return id.error();
  f.id = *id;
  const std::string data = words.size() == 4 ? words[3] : "";
  if (data.size() % 2 != 0 || data.size() > 16) return bad(words, "data must be 0 to 8 bytes as hex pairs");
  for (std::size_t i = 0; i < data.size(); i += 2) {
    std::uint32_t b = 0;
    if (!parse_hex(data.substr(i, 2), b)) return bad(words, "data is not hex");
    f.data[f.len++] = static_cast<std::uint8_t>(b);
  }
  return f;
}

Result<CanFrame> parse_send(const std::vector<std::string>& words) {
  // send ID LEN [BYTE...]
  if (words.size() < 3 || words[0] != "send") return bad(words, "expected 'send ID LEN BYTES'");
  CanFrame f;
  auto id = parse_id(words, words[1], f.extended);
  if (!id) return id.error();
  f.id = *id;
  std::uint32_t len = 0;
  if (!parse_hex(words[2], len) || len > 8) return bad(words, "length must be 0 to 8");
  if (words.size() != 3 + len) return bad(words, "length does not match the number of data bytes");
  for (std::uint32_t i = 0; i < len; ++i) {
    std::uint32_t b = 0;
    if (!parse_hex(words[3 + i], b) || b > 0xFF) return bad(words, "data byte '" + words[3 + i] + "' is not hex");
    f.data[f.len++] = static_cast<std::uint8_t>(b);
  }
  return f;
}

}  // namespace socketcand

namespace {

using boost::asio::ip::tcp;

class SocketcandClient : public CanTransport, public std::enable_shared_from_this<SocketcandClient> {
 public:
  SocketcandClient(boost::asio::io_context& io, std::string address, int port, std::string bus)
      : socket_(io), address_(std::move(address)), port_(port), bus_(std::move(bus)) {}

  void start(FrameHandler on_frame, ErrorHandler on_error) override {
    on_frame_ = std::move(on_frame);
    on_error_ = std::move(on_error);
    boost::system::error_code ec;
    const auto addr = boost::asio::ip::make_address(address_, ec);
    if (ec) return fail("'" + address_ + "' is not an IP address");
    socket_.async_connect(tcp::endpoint(addr, static_cast<unsigned short>(port_)),
                          [self = shared_from_this()](const boost::system::error_code& e) {
                            if (self->closed_) return;
                            if (e) return self->fail("connect: " + e.message() + " (is the socketcand server running?)");
                            boost::system::error_code ignored;
                            self->socket_.set_option(tcp::no_delay(true), ignored);
                            self->read();
                          });
  }
  void send(const CanFrame& frame) override {
    if (closed_) return;
    if (state_ != State::raw) {
      pending_.push_back(frame);
      return;
    }
    write(socketcand::format_send(frame));
  }
  void close() override {
    closed_ = true;
    on_frame_ = nullptr;
    on_error_ = nullptr;
    boost::system::error_code ec;
    socket_.close(ec);
  }
  [[nodiscard]] std::string name() const override {
    return "socketcand:" + address_ + ":" + std::to_string(port_) + "/" + bus_;
  }

 private:
  enum class State { greeting, opening, switching, raw };

  void read() {
    socket_.async_read_some(boost::asio::buffer(rx_), [self = shared_from_this()](const boost::system::error_code& ec,
                                                                                  std::size_t n) {
      if (self->closed_) return;
      if (ec) return self->fail(ec == boost::asio::error::eof ? "server closed the connection" : "read: " + ec.message());
      self->buffer_.append(self->rx_.data(), n);
      auto messages = socketcand::take_messages(self->buffer_);
      if (!messages) return self->fail(messages.error().message);
      for (const auto& words : *messages) {
        self->handle(words);
        if (self->closed_) return;
      }
      self->read();
    });
  }

  void handle(const std::vector<std::string>& words) {
    if (words.empty()) return;
    if (words[0] == "error") {
      std::string text;
      for (std::size_t i = 1; i < words.size(); ++i) text += (i > 1 ? " " : "") + words[i];
      return report("server reported an error: " + text);
    }
    switch (state_) {
      case State::greeting:
        if (words[0] != "hi") return fail("expected '< hi >' from the server, got '" + words[0] + "'");
        state_ = State::opening;
        write("< open " + bus_ + " >");
        return;
      case State::opening:
        if (words[0] != "ok") return fail("opening bus '" + bus_ + "' refused: '" + words[0] + "'");
        state_ = State::switching;
        write("< rawmode >");
        return;
      case State::switching:
        if (words[0] != "ok") return fail("switching to rawmode refused: '" + words[0] + "'");
        state_ = State::raw;
        for (const auto& f : pending_) write(socketcand::format_send(f));
        pending_.clear();
        return;
      case State::raw:
        if (words[0] == "frame") {
          auto f = socketcand::parse_frame(words);
          if (!f) return report(f.error().message);
          if (on_frame_) on_frame_(*f);
        }
        return;  // other elements (e.g. "ok" to an echo) are ignored
    }
  }

  void write(std::string text) {
    out_.push_back(std::move(text));
    if (out_.size() == 1) write_front();
  }
  void write_front() {
    boost::asio::async_write(socket_, boost::asio::buffer(out_.front()),
                             [self = shared_from_this()](const boost::system::error_code& ec, std::size_t) {
                               if (self->closed_) return;
                               if (ec) return self->fail("write: " + ec.message());
                               self->out_.pop_front();
                               if (!self->out_.empty()) self->write_front();
                             });
  }
  void report(const std::string& what) {
    if (on_error_) on_error_(Error{"can.socketcand", name() + ": " + what});
  }
  void fail(const std::string& what) {
    auto handler = on_error_;
    closed_ = true;
    boost::system::error_code ec;
    socket_.close(ec);
    on_frame_ = nullptr;
    on_error_ = nullptr;
    if (handler) handler(Error{"can.socketcand", name() + ": " + what});
  }

  tcp::socket socket_;
  std::string address_;
  int port_;
  std::string bus_;
  State state_ = State::greeting;
  bool closed_ = false;
  std::array<char, 4096> rx_{};
  std::string buffer_;
  std::deque<std::string> out_;
  std::vector<CanFrame> pending_;
  FrameHandler on_frame_;
  ErrorHandler on_error_;
};

}  // namespace

std::shared_ptr<CanTransport> open_socketcand(boost::asio::io_context& io, const std::string& address, int port,
                                              const std::string& bus) {
  return std::make_shared<SocketcandClient>(io, address, port, bus);
}

}  // namespace fettle::canopen
