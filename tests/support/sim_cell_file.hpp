#pragma once
// Test helper: the shipped simulator cell (config/cell.sim.toml) written to a folder of the
// test's own, with its device ports replaced (free ones, so tests run in parallel) and its
// relative paths made absolute, so a test can start the device simulators with `--cell`.
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>
#include <stdexcept>
#include <string>

namespace fettle::test {

/// A TCP port of 127.0.0.1 that was free a moment ago (the kernel's pick for port 0).
inline int free_tcp_port() {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t len = sizeof a;
  if (fd < 0 || ::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 ||
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) != 0) {
    if (fd >= 0) ::close(fd);
    throw std::runtime_error("no free TCP port on 127.0.0.1");
  }
  ::close(fd);
  return ntohs(a.sin_port);
}

struct SimCellPorts {
  int plc = 0;
  int robot = 0;
  int spindle = 0;
};

/// Writes `dir`/cell.toml from config/cell.sim.toml with `ports`; returns its path.
inline std::filesystem::path write_sim_cell(const std::filesystem::path& dir, const SimCellPorts& ports) {
  const std::filesystem::path config = std::filesystem::path(FETTLE_SOURCE_DIR) / "config";
  std::ifstream in(config / "cell.sim.toml");
  std::stringstream text;
  text << in.rdbuf();
  std::string s = text.str();
  s = std::regex_replace(s, std::regex(R"(\nport = 1502\n)"), "\nport = " + std::to_string(ports.plc) + "\n");
  s = std::regex_replace(s, std::regex(R"(\nport = 30100\n)"), "\nport = " + std::to_string(ports.robot) + "\n");
  s = std::regex_replace(s, std::regex(R"(\nport = 29536\n)"), "\nport = " + std::to_string(ports.spindle) + "\n");
  s = std::regex_replace(s, std::regex(R"(file = "parts/)"), "file = \"" + (config / "parts").string() + "/");
  s = std::regex_replace(s, std::regex(R"(file = "calibration)"), "file = \"" + config.string() + "/calibration");
  s = std::regex_replace(s, std::regex(R"("\.\./var/fettle)"), "\"" + (dir / "var").string());
  const auto path = dir / "cell.toml";
  std::ofstream(path) << s;
  return path;
}

}  // namespace fettle::test
