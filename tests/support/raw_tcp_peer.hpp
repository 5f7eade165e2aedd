#pragma once
// Test helper: a raw TCP server on 127.0.0.1 (ephemeral port) on its own thread, playing a
// broken or hostile peer by hand: it says nothing, sends garbage, closes at once, or answers
// whatever a test's script returns. For bad-input tests of the device links.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <functional>
#include <stdexcept>
#include <string>
#include <thread>

namespace fettle::test {

class RawTcpPeer {
 public:
  /// Called on the peer's thread for each accepted connection; the connection is closed when
  /// it returns. Use read_some() / send() on it; stop_requested() turns true at shutdown.
  using Session = std::function<void(RawTcpPeer& peer, int fd)>;

  explicit RawTcpPeer(Session session) : session_(std::move(session)) {
    listen_fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    a.sin_port = 0;
    socklen_t len = sizeof a;
    if (listen_fd_ < 0 || ::bind(listen_fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 ||
        ::listen(listen_fd_, 8) != 0 || ::getsockname(listen_fd_, reinterpret_cast<sockaddr*>(&a), &len) != 0)
      throw std::runtime_error("RawTcpPeer: cannot listen on 127.0.0.1");
    port_ = ntohs(a.sin_port);
    thread_ = std::thread([this] { serve(); });
  }
  ~RawTcpPeer() {
    stop_ = true;
    thread_.join();
    ::close(listen_fd_);
  }
  RawTcpPeer(const RawTcpPeer&) = delete;
  RawTcpPeer& operator=(const RawTcpPeer&) = delete;

  [[nodiscard]] int port() const { return port_; }
  [[nodiscard]] int connections() const { return connections_; }
  [[nodiscard]] long long bytes_received() const { return bytes_received_; }
  [[nodiscard]] bool stop_requested() const { return stop_; }

  /// Waits up to `timeout` for bytes; returns them ("" on timeout, close or stop).
  std::string read_some(int fd, std::chrono::milliseconds timeout = std::chrono::milliseconds(100)) {
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, static_cast<int>(timeout.count())) <= 0) return {};
    char buf[4096];
    const auto n = ::recv(fd, buf, sizeof buf, 0);
    if (n <= 0) return {};
    bytes_received_ += n;
    return std::string(buf, static_cast<std::size_t>(n));
  }
  /// Sends all of `bytes` (false if the connection broke).
  static bool send(int fd, const std::string& bytes) {
    std::size_t done = 0;
    while (done < bytes.size()) {
      const auto n = ::send(fd, bytes.data() + done, bytes.size() - done, MSG_NOSIGNAL);
      if (n <= 0) return false;
      done += static_cast<std::size_t>(n);
    }
    return true;
  }
  /// Keeps the connection open, reading and discarding, until `d` passed or stop.
  void hold(int fd, std::chrono::milliseconds d) {
    const auto end = std::chrono::steady_clock::now() + d;
    while (!stop_ && std::chrono::steady_clock::now() < end) (void)read_some(fd, std::chrono::milliseconds(20));
  }

 private:
  void serve() {
    while (!stop_) {
      pollfd p{listen_fd_, POLLIN, 0};
      if (::poll(&p, 1, 20) <= 0) continue;
      const int fd = ::accept4(listen_fd_, nullptr, nullptr, SOCK_CLOEXEC);
      if (fd < 0) continue;
      ++connections_;
      session_(*this, fd);
      ::close(fd);
    }
  }

  Session session_;
  int listen_fd_ = -1;
  int port_ = 0;
  std::atomic<bool> stop_{false};
  std::atomic<int> connections_{0};
  std::atomic<long long> bytes_received_{0};
  std::thread thread_;
};

}  // namespace fettle::test
