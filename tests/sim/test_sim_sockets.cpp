// Every socket the simulated devices open is close-on-exec: a program started next to a
// simulated cell (fettle-sim soak's runs, a test's, an integrator's script) that inherited the
// simulator's listening and accepted sockets would keep a connection the simulated PLC or robot
// drops open (the "PLC reboot" would not reach fettled) and keep the simulator's ports bound
// after it exits. (soak also closes descriptors above 2 in fettled's child.)
#include <gtest/gtest.h>

#include <chrono>
#include <filesystem>
#include <string>
#include <thread>
#include <vector>

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include "fettle/config/load.hpp"
#include "fettle/sim/cell.hpp"

namespace {

/// A TCP connection to 127.0.0.1:port (close-on-exec itself, so it does not count).
int connect_to(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(static_cast<std::uint16_t>(port));
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (fd < 0 || ::connect(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) {
    if (fd >= 0) ::close(fd);
    return -1;
  }
  return fd;
}

struct SocketFd {
  int fd;
  bool cloexec;
  std::string where;  ///< local address:port
};

std::vector<SocketFd> open_sockets() {
  std::vector<SocketFd> out;
  for (const auto& e : std::filesystem::directory_iterator("/proc/self/fd")) {
    std::error_code ec;
    const auto target = std::filesystem::read_symlink(e.path(), ec).string();
    if (ec || target.rfind("socket:", 0) != 0) continue;
    const int fd = std::stoi(e.path().filename().string());
    const int flags = ::fcntl(fd, F_GETFD);
    if (flags < 0) continue;  // the directory iterator's own descriptor, closed since
    sockaddr_storage ss{};
    socklen_t len = sizeof ss;
    std::string where = "?";
    if (::getsockname(fd, reinterpret_cast<sockaddr*>(&ss), &len) == 0 && ss.ss_family == AF_INET) {
      const auto* in = reinterpret_cast<const sockaddr_in*>(&ss);
      char ip[INET_ADDRSTRLEN] = {};
      ::inet_ntop(AF_INET, &in->sin_addr, ip, sizeof ip);
      where = std::string(ip) + ":" + std::to_string(ntohs(in->sin_port));
    }
    out.push_back({fd, (flags & FD_CLOEXEC) != 0, where});
  }
  return out;
}

TEST(SimSockets, EveryDeviceSocketIsCloseOnExec) {
  const std::size_t before = open_sockets().size();
  fettle::sim::CellSimOptions o;
  o.cell = fettle::config::load_cell(FETTLE_SOURCE_DIR "/config/cell.sim.toml");
  o.plc_port = 0;
  o.robot_port = 0;
  o.spindle_port = 0;
  o.castings = 0;
  o.auto_start = false;
  fettle::sim::CellSim sim(o);
  sim.start();
  // a client on each TCP device, so that its accepted connection exists too
  std::vector<int> clients;
  for (int port : {sim.plc_port(), sim.robot_port(), sim.spindle_port()}) {
    const int fd = connect_to(port);
    ASSERT_GE(fd, 0) << "cannot connect to the simulated device on port " << port;
    clients.push_back(fd);
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(300));  // the servers accept
  const auto sockets = open_sockets();
  // listening: PLC, robot, spindle; accepted: three; the camera's GVCP socket
  EXPECT_GE(sockets.size(), before + clients.size() + 7) << "the test did not see the devices' sockets";
  for (const auto& s : sockets)
    EXPECT_TRUE(s.cloexec) << "socket fd " << s.fd << " (" << s.where << ") is inherited by child processes";
  for (int fd : clients) ::close(fd);
  sim.stop();
}

}  // namespace
