// Interoperability: the driver against Aravis' own simulator, arv-fake-gv-camera-0.8 (not our
// code): connect by address, trigger, receive a frame, and fail cleanly on its Mono8 images.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <arpa/inet.h>
#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <thread>

#include "fettle/drivers/camera.hpp"

extern char** environ;

namespace fd = fettle::drivers;
using ::testing::HasSubstr;

namespace {

constexpr const char* kFake = "/usr/bin/arv-fake-gv-camera-0.8";

/// True while something holds UDP 127.0.0.1:3956.
bool gvcp_port_in_use() {
  const int fd = ::socket(AF_INET, SOCK_DGRAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(3956);
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  const bool in_use = ::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0;
  ::close(fd);
  return in_use;
}

class AravisFakeCamera {
 public:
  AravisFakeCamera() {
    char* argv[] = {const_cast<char*>(kFake), const_cast<char*>("-i"), const_cast<char*>("127.0.0.1"), nullptr};
    if (::posix_spawn(&pid_, kFake, nullptr, nullptr, argv, environ) != 0) pid_ = -1;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
    while (pid_ > 0 && !gvcp_port_in_use() && std::chrono::steady_clock::now() < deadline)
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  ~AravisFakeCamera() {
    if (pid_ > 0) {
      ::kill(pid_, SIGTERM);
      int status = 0;
      ::waitpid(pid_, &status, 0);
    }
  }
  AravisFakeCamera(const AravisFakeCamera&) = delete;
  AravisFakeCamera& operator=(const AravisFakeCamera&) = delete;
  [[nodiscard]] bool running() const { return pid_ > 0 && gvcp_port_in_use(); }

 private:
  pid_t pid_ = -1;
};

}  // namespace

TEST(CameraInterop, AravisFakeCameraConnectsTriggersAndIsRejectedAsMono8) {
  if (!std::filesystem::exists(kFake)) GTEST_SKIP() << kFake << " is not installed (Debian package aravis-tools)";
  AravisFakeCamera fake;
  ASSERT_TRUE(fake.running()) << "arv-fake-gv-camera-0.8 did not start on 127.0.0.1";
  fd::CameraOptions o;
  o.address = "127.0.0.1";
  o.frame_timeout_ms = 2000;
  o.retries = 1;
  o.exposure_us = 10000.0;
  fd::Camera camera(o);
  EXPECT_EQ(camera.info().vendor, "Aravis");
  EXPECT_EQ(camera.info().pixel_format, "Mono8");
  EXPECT_FALSE(camera.info().scan3d_from_camera);
  auto c = camera.capture();
  ASSERT_FALSE(c.ok());
  // The frame arrived (no timeout, no fault): it is refused for what it is.
  EXPECT_EQ(c.error().code, "camera.unsupported_pixel_format") << c.error().message;
  EXPECT_THAT(c.error().message, HasSubstr("unsupported pixel format Mono8"));
  // And again: the driver is still in a clean state.
  auto again = camera.capture();
  ASSERT_FALSE(again.ok());
  EXPECT_EQ(again.error().code, "camera.unsupported_pixel_format");
}
