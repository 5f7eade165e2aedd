// `fettle camera info|capture` against `fettle-sim camera`, as an integrator runs them.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <string>

#include "fettle/core/ply.hpp"

namespace fs = std::filesystem;
using ::testing::HasSubstr;

namespace {

struct Run {
  int exit_code;
  std::string output;
};

Run run(const std::string& command) {
  FILE* pipe = ::popen((command + " 2>&1").c_str(), "r");
  std::string out;
  std::array<char, 4096> buf{};
  while (pipe != nullptr && std::fgets(buf.data(), buf.size(), pipe) != nullptr) out += buf.data();
  const int status = pipe != nullptr ? ::pclose(pipe) : -1;
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

/// `fettle-sim camera` as a child process; ready once it printed its "ready" line.
class SimCamera {
 public:
  explicit SimCamera(const std::string& args) {
    int out[2];
    if (::pipe(out) != 0) return;
    pid_ = ::fork();
    if (pid_ == 0) {
      ::dup2(out[1], STDOUT_FILENO);
      ::close(out[0]);
      const std::string cmd = "exec " + std::string(FETTLE_BIN_DIR) + "/fettle-sim camera " + args + " < /dev/null";
      ::execl("/bin/sh", "sh", "-c", cmd.c_str(), nullptr);
      ::_exit(127);
    }
    ::close(out[1]);
    FILE* f = ::fdopen(out[0], "r");
    std::array<char, 512> line{};
    while (f != nullptr && std::fgets(line.data(), line.size(), f) != nullptr) {
      if (std::string(line.data()).rfind("ready", 0) == 0) {
        ready_ = true;
        break;
      }
    }
    out_ = f;
  }
  ~SimCamera() {
    if (pid_ > 0) {
      ::kill(pid_, SIGTERM);
      int status = 0;
      ::waitpid(pid_, &status, 0);
    }
    if (out_ != nullptr) ::fclose(out_);
  }
  SimCamera(const SimCamera&) = delete;
  SimCamera& operator=(const SimCamera&) = delete;
  [[nodiscard]] bool ready() const { return ready_; }

 private:
  pid_t pid_ = -1;
  FILE* out_ = nullptr;
  bool ready_ = false;
};

const std::string kFettle = std::string(FETTLE_BIN_DIR) + "/fettle";

}  // namespace

TEST(CameraCli, InfoShowsTheSimulatedCamerasScan3dFeatures) {
  SimCamera sim("--address 127.0.0.1 --resolution 320x240");
  ASSERT_TRUE(sim.ready());
  const auto r = run(kFettle + " camera info --address 127.0.0.1");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_THAT(r.output, HasSubstr("FETTLE-SIM-3D"));
  EXPECT_THAT(r.output, HasSubstr("320 x 240"));
  EXPECT_THAT(r.output, HasSubstr("Coord3D_C16"));
  EXPECT_THAT(r.output, HasSubstr("intrinsics:    camera (fx"));
}

TEST(CameraCli, CaptureWritesTheFull32MegapixelOrganizedCloud) {
  SimCamera sim("--address 127.0.0.1 --seed 3");
  ASSERT_TRUE(sim.ready());
  const fs::path out = fs::temp_directory_path() / ("fettle-camera-cli-" + std::to_string(::getpid()) + ".ply");
  const auto r = run(kFettle + " camera capture --address 127.0.0.1 --out " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_THAT(r.output, HasSubstr("2064 x 1544 organized cloud"));
  auto cloud = fettle::read_ply(out);
  fs::remove(out);
  ASSERT_TRUE(cloud.ok()) << cloud.error().message;
  EXPECT_EQ(cloud->width, 2064u);
  EXPECT_EQ(cloud->height, 1544u);
  EXPECT_EQ(cloud->count_valid(), std::size_t{2064} * 1544);  // the synthetic plane fills the view
  // Centre pixel: the sphere's front at 640 mm.
  EXPECT_NEAR(cloud->points[std::size_t{772} * 2064 + 1032].z(), 640.0, 0.5);
}

TEST(CameraCli, NoCameraIsADeviceFailureWithExitCode3) {
  const auto r = run(kFettle + " camera info --address 127.0.0.1");
  EXPECT_EQ(r.exit_code, 3) << r.output;
  EXPECT_THAT(r.output, HasSubstr("127.0.0.1"));
}

TEST(CameraCli, CaptureNeedsAnOutputFile) {
  const auto r = run(kFettle + " camera capture --address 127.0.0.1");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_THAT(r.output, HasSubstr("--out"));
}
