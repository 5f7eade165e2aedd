#pragma once
// Close-on-exec for the simulator's sockets: `fettle-sim soak` runs fettled as a child process,
// which must not inherit the simulated devices' listening and accepted sockets (a connection a
// simulated device drops would stay open in the child; its port would stay bound). Boost.Asio
// opens and accepts sockets without SOCK_CLOEXEC: its sockets get the flag right after.
#include <fcntl.h>

namespace fettle::sim::detail {

inline void set_cloexec(int fd) {
  if (fd < 0) return;
  const int flags = ::fcntl(fd, F_GETFD);
  if (flags >= 0) ::fcntl(fd, F_SETFD, flags | FD_CLOEXEC);
}

}  // namespace fettle::sim::detail
