// The blocking control client used by the fettle CLI (see control.hpp).
#include <fcntl.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <string>
#include <utility>

#include "fettle/daemon/control.hpp"

namespace fettle::daemon::control {

namespace {

using Clock = std::chrono::steady_clock;

constexpr std::size_t max_reply_bytes = 64U * 1024U * 1024U;

int remaining_ms(Clock::time_point deadline) {
  const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
  return left <= 0 ? 0 : static_cast<int>(left);
}

/// Waits for `events` on fd until the deadline: 1 ready, 0 timeout, -1 error (errno set).
int wait_for(int fd, short events, Clock::time_point deadline) {
  for (;;) {
    pollfd p{fd, events, 0};
    const int r = ::poll(&p, 1, remaining_ms(deadline));
    if (r < 0 && errno == EINTR) continue;
    return r;
  }
}

Error connect_error(const std::filesystem::path& path, int e) {
  const std::string where = "socket " + path.string();
  switch (e) {
    case ENOENT:
      return Error{code::not_running, "is fettled running? " + where +
                                          ": no such file (start it with systemctl start fettled, or pass "
                                          "--socket/--config naming its [control] socket)"};
    case ECONNREFUSED:
      return Error{code::not_running, "is fettled running? " + where + ": connection refused"};
    case EACCES:
    case EPERM:
      return Error{code::permission_denied,
                   where + ": permission denied; add your user to the fettle group (docs/service.md) or use sudo"};
    default:
      return Error{code::io, where + ": cannot connect: " + std::strerror(e)};
  }
}

}  // namespace

Result<Client> Client::connect(const std::filesystem::path& socket_path, std::chrono::milliseconds timeout) {
  sockaddr_un addr{};
  if (socket_path.native().size() >= sizeof(addr.sun_path))
    return Error{code::io, "socket " + socket_path.string() + ": path too long for a Unix socket"};
  const int fd = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
  if (fd < 0) return Error{code::io, std::string{"cannot create a Unix socket: "} + std::strerror(errno)};
  addr.sun_family = AF_UNIX;
  std::strncpy(addr.sun_path, socket_path.c_str(), sizeof(addr.sun_path) - 1);
  const auto deadline = Clock::now() + timeout;
  for (;;) {
    if (::connect(fd, reinterpret_cast<const sockaddr*>(&addr), sizeof addr) == 0) break;
    const int e = errno;
    if (e == EINTR) continue;
    if (e == EAGAIN || e == EINPROGRESS) {  // the server's backlog is full: retry until the deadline
      if (remaining_ms(deadline) == 0) {
        ::close(fd);
        return Error{code::timeout, "socket " + socket_path.string() + ": the server did not accept within " +
                                        std::to_string(timeout.count()) + " ms"};
      }
      ::usleep(10000);
      continue;
    }
    ::close(fd);
    return connect_error(socket_path, e);
  }
  return Client{fd, socket_path};
}

Client::Client(Client&& other) noexcept
    : fd_(std::exchange(other.fd_, -1)), path_(std::move(other.path_)), buffer_(std::move(other.buffer_)) {}

Client& Client::operator=(Client&& other) noexcept {
  if (this != &other) {
    if (fd_ >= 0) ::close(fd_);
    fd_ = std::exchange(other.fd_, -1);
    path_ = std::move(other.path_);
    buffer_ = std::move(other.buffer_);
  }
  return *this;
}

Client::~Client() {
  if (fd_ >= 0) ::close(fd_);
}

Result<json> Client::request(const json& request, std::chrono::milliseconds timeout) {
  return request_raw(request.dump() + "\n", timeout);
}

Result<json> Client::request_raw(std::string_view bytes, std::chrono::milliseconds timeout) {
  if (fd_ < 0) return Error{code::io, "socket " + path_.string() + ": not connected"};
  const auto deadline = Clock::now() + timeout;
  while (!bytes.empty()) {
    const ssize_t n = ::send(fd_, bytes.data(), bytes.size(), MSG_NOSIGNAL);
    if (n > 0) {
      bytes.remove_prefix(static_cast<std::size_t>(n));
      continue;
    }
    if (n < 0 && errno == EINTR) continue;
    if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
      const int w = wait_for(fd_, POLLOUT, deadline);
      if (w > 0) continue;
      if (w == 0)
        return Error{code::timeout, "socket " + path_.string() + ": could not send the request within " +
                                        std::to_string(timeout.count()) + " ms"};
    }
    return Error{code::io, "socket " + path_.string() + ": send failed: " + std::strerror(errno)};
  }
  return read_reply(std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()));
}

Result<json> Client::read_reply(std::chrono::milliseconds timeout) {
  const auto deadline = Clock::now() + std::max(timeout, std::chrono::milliseconds{0});
  for (;;) {
    if (const auto nl = buffer_.find('\n'); nl != std::string::npos) {
      const std::string line = buffer_.substr(0, nl);
      buffer_.erase(0, nl + 1);
      json reply = json::parse(line, nullptr, false);
      if (reply.is_discarded() || !reply.is_object())
        return Error{code::io, "socket " + path_.string() + ": the server sent a reply that is not a JSON object"};
      return reply;
    }
    if (buffer_.size() > max_reply_bytes)
      return Error{code::io, "socket " + path_.string() + ": reply longer than " + std::to_string(max_reply_bytes) + " bytes"};
    char chunk[65536];
    const ssize_t n = ::recv(fd_, chunk, sizeof chunk, 0);
    if (n > 0) {
      buffer_.append(chunk, static_cast<std::size_t>(n));
      continue;
    }
    if (n == 0) return Error{code::io, "socket " + path_.string() + ": the server closed the connection before replying"};
    if (errno == EINTR) continue;
    if (errno == EAGAIN || errno == EWOULDBLOCK) {
      const int w = wait_for(fd_, POLLIN, deadline);
      if (w > 0) continue;
      if (w == 0)
        return Error{code::timeout, "socket " + path_.string() + ": no reply within " +
                                        std::to_string(timeout.count()) + " ms (is fettled's event loop stuck?)"};
    }
    return Error{code::io, "socket " + path_.string() + ": receive failed: " + std::strerror(errno)};
  }
}

Result<json> call(const std::filesystem::path& socket_path, const json& request, std::chrono::milliseconds timeout) {
  auto client = Client::connect(socket_path, timeout);
  if (!client) return client.error();
  return client->request(request, timeout);
}

}  // namespace fettle::daemon::control
