#pragma once
// Close-on-exec for the simulator's sockets: a program a simulator process starts (fettle-sim
// soak's fettled and helper runs, anything a test or an integrator's script spawns next to a
// simulated cell) must not inherit the simulated devices' listening and accepted sockets (a
// connection a simulated device drops would stay open in the child; its port would stay
// bound). soak also closes every descriptor above 2 in fettled's child; this is the guard for
// every other child. Boost.Asio opens and accepts sockets without SOCK_CLOEXEC: its sockets get
// the flag right after (a spawn on another thread in between would still inherit one).
#include <fcntl.h>

namespace fettle::sim::detail {

inline void set_cloexec(int fd) {
  if (fd < 0) return;
  const int flags = ::fcntl(fd, F_GETFD);
  if (flags >= 0) ::fcntl(fd, F_SETFD, flags | FD_CLOEXEC);
}

}  // namespace fettle::sim::detail
