// The camera driver against the simulated GigE Vision camera on 127.0.0.1 (real GVCP/GVSP
// through Aravis): geometry of decoded clouds, pixel formats, faults and reconnection.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <memory>
#include <thread>

#include "fettle/core/error.hpp"
#include "fettle/drivers/camera.hpp"
#include "fettle/sim/camera.hpp"

namespace fd = fettle::drivers;
namespace fs = fettle::sim;
using ::testing::HasSubstr;

namespace {

fs::RangeImageModel small_model() {
  fs::RangeImageModel m;
  m.width = 320;
  m.height = 240;
  m.focal_px = 372.0;
  m.cx_px = 159.5;
  m.cy_px = 119.5;
  return m;
}

fd::CameraOptions driver_options() {
  fd::CameraOptions o;
  o.address = "127.0.0.1";
  o.frame_timeout_ms = 1500;
  o.retries = 2;
  o.exposure_us = 5000.0;
  return o;
}

class CameraSim : public ::testing::Test {
 protected:
  void SetUp() override { start_camera(); }
  void start_camera() {
    sim_ = std::make_unique<fs::SimulatedCamera>(fs::SimulatedCameraOptions{}, fs::synthetic_range_source(model_, scene_));
  }
  fs::RangeImageModel model_ = small_model();
  fs::SyntheticScene scene_;
  std::unique_ptr<fs::SimulatedCamera> sim_;
};

/// Every valid point lies on the plane or on the sphere (shifted by the slide); returns the
/// number of sphere points.
std::size_t check_geometry(const fettle::OrganizedCloud& cloud, const fs::SyntheticScene& s, double slide_mm) {
  std::size_t sphere = 0;
  const Eigen::Vector3d c(s.sphere_center_mm[0] - slide_mm, s.sphere_center_mm[1], s.sphere_center_mm[2]);
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    if (!cloud.is_valid(i)) continue;
    const Eigen::Vector3d p = cloud.points[i].cast<double>();
    const double to_plane = std::abs(p.z() - s.plane_z_mm);
    const double to_sphere = std::abs((p - c).norm() - s.sphere_radius_mm);
    EXPECT_LT(std::min(to_plane, to_sphere), 0.05) << "point " << i << " (" << p.transpose() << ") is on neither";
    if (to_sphere < to_plane) ++sphere;
  }
  return sphere;
}

}  // namespace

TEST_F(CameraSim, InfoReportsScan3dFeaturesAndModel) {
  fd::Camera camera(driver_options());
  const auto& info = camera.info();
  EXPECT_EQ(info.serial, "FETTLE-SIM-3D");
  EXPECT_EQ(info.width, 320u);
  EXPECT_EQ(info.height, 240u);
  EXPECT_EQ(info.pixel_format, "Coord3D_C16");
  EXPECT_TRUE(info.scan3d_from_camera);
  EXPECT_DOUBLE_EQ(info.scan3d.scale, model_.scale_mm);
  EXPECT_TRUE(info.scan3d.invalid_data_flag);
  ASSERT_TRUE(info.scan3d.intrinsics.has_value());
  EXPECT_DOUBLE_EQ(info.scan3d.intrinsics->fx_px, 372.0);
  EXPECT_DOUBLE_EQ(info.scan3d.intrinsics->cy_px, 119.5);
  EXPECT_EQ(info.intrinsics_source, "camera");
  EXPECT_THAT(info.to_string(), HasSubstr("Coord3D_ABC32f"));
}

TEST_F(CameraSim, CaptureDecodesThePlaneAndSphereExactly) {
  fd::Camera camera(driver_options());
  auto c = camera.capture();
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_EQ(c->stats.attempts, 1);
  EXPECT_EQ(c->cloud.width, 320u);
  EXPECT_EQ(c->cloud.height, 240u);
  EXPECT_EQ(c->cloud.count_valid(), c->cloud.size());  // plane behind everything
  EXPECT_GT(check_geometry(c->cloud, scene_, 0.0), 2000u);
  // Pixel by pixel against the exact depth (quantisation 0.02 mm).
  for (std::uint32_t v = 0; v < 240; v += 13)
    for (std::uint32_t u = 0; u < 320; u += 11) {
      const double z = fs::synthetic_depth_mm(model_, scene_, 0.0, u, v);
      EXPECT_NEAR(c->cloud.points[v * 320 + u].z(), z, 0.011) << "pixel " << u << "," << v;
    }
}

TEST_F(CameraSim, SlidePositionMovesTheScene) {
  fd::Camera camera(driver_options());
  sim_->set_slide_position_mm(40.0);
  auto c = camera.capture();
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_GT(check_geometry(c->cloud, scene_, 40.0), 2000u);
  // The sphere's nearest point moved 40 mm towards -x: about 40 * 372 / 640 px left of centre.
  const auto centre = c->cloud.points[120 * 320 + 160];
  EXPECT_GT(centre.z(), 650.0);  // still on the sphere's flank, not its front
  const double z_front = c->cloud.points[120 * 320 + static_cast<int>(159.5 - 40.0 * 372.0 / 640.0)].z();
  EXPECT_NEAR(z_front, 640.0, 1.0);
}

TEST_F(CameraSim, CaptureIntoAReusedCloudKeepsItsStorageAndSeesTheNewScene) {
  fd::Camera camera(driver_options());
  fd::CameraCapture c;
  const auto first = camera.capture(c);
  ASSERT_TRUE(first.ok()) << first.error().message;
  EXPECT_GT(check_geometry(c.cloud, scene_, 0.0), 2000u);
  const auto* storage = c.cloud.points.data();
  const auto first_frame = c.frame_id;
  sim_->set_slide_position_mm(40.0);
  auto s = camera.capture(c);
  ASSERT_TRUE(s.ok()) << s.error().message;
  EXPECT_EQ(c.cloud.points.data(), storage);  // no new allocation for the second frame
  EXPECT_NE(c.frame_id, first_frame);
  // One trigger, one frame: a retry here would mean a frame was lost on loopback (this test
  // failed once under heavy load in 2026-11; the numbers say which way if it happens again).
  EXPECT_EQ(c.stats.attempts, 1) << "missing packets " << c.stats.missing_packets << ", failed frames "
                                 << c.stats.failed_frames << ", underruns " << c.stats.underruns << ", wait "
                                 << c.stats.wait_ms << " ms";
  EXPECT_GT(check_geometry(c.cloud, scene_, 40.0), 2000u);
  EXPECT_NEAR(c.cloud.points[120 * 320 + static_cast<int>(159.5 - 40.0 * 372.0 / 640.0)].z(), 640.0, 1.0);
}

TEST_F(CameraSim, HeartbeatTimeoutFromTheOptionsIsSetOnTheCamera) {
  auto o = driver_options();
  o.heartbeat_timeout_ms = 2500;
  fd::Camera camera(o);
  EXPECT_EQ(camera.info().heartbeat_timeout_ms, 2500);
  EXPECT_THAT(camera.info().to_string(), HasSubstr("2500 ms timeout"));
  EXPECT_TRUE(camera.capture().ok());
}

TEST_F(CameraSim, FloatRangeMapAndPointCloudFormatsDecodeTheSameScene) {
  for (const char* format : {"Coord3D_C32f", "Coord3D_ABC32f"}) {
    auto o = driver_options();
    o.pixel_format = format;
    fd::Camera camera(o);
    EXPECT_EQ(camera.info().pixel_format, format);
    auto c = camera.capture();
    ASSERT_TRUE(c.ok()) << format << ": " << c.error().message;
    EXPECT_EQ(fd::pixel_format_name(c->pixel_format), format);
    EXPECT_GT(check_geometry(c->cloud, scene_, 0.0), 2000u) << format;
  }
}

TEST_F(CameraSim, Mono8FromTheCameraIsRejectedByName) {
  auto o = driver_options();
  o.pixel_format = "Mono8";  // the camera offers an intensity view too
  fd::Camera camera(o);
  auto c = camera.capture();
  ASSERT_FALSE(c.ok());
  EXPECT_EQ(c.error().code, "camera.unsupported_pixel_format");
  EXPECT_THAT(c.error().message, HasSubstr("unsupported pixel format Mono8"));
}

TEST_F(CameraSim, DroppedFrameIsRetriedAndSucceeds) {
  fd::Camera camera(driver_options());
  sim_->drop_frames(1);
  auto c = camera.capture();
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_EQ(c->stats.attempts, 2);
  EXPECT_GT(check_geometry(c->cloud, scene_, 0.0), 2000u);
}

TEST_F(CameraSim, MoreDroppedFramesThanRetriesIsACameraFault) {
  auto o = driver_options();
  o.frame_timeout_ms = 400;
  o.retries = 1;
  fd::Camera camera(o);
  sim_->drop_frames(2);
  auto c = camera.capture();
  ASSERT_FALSE(c.ok());
  EXPECT_EQ(c.error().code, "camera.fault");
  EXPECT_EQ(c.error().kind, fettle::ErrorKind::no_data);  // fettled's fault 201 comes from the kind
  EXPECT_THAT(c.error().message, HasSubstr("after 2 attempts"));
  // The camera is not broken for good: the next capture works, on a fresh connection.
  auto again = camera.capture();
  ASSERT_TRUE(again.ok()) << again.error().message;
  EXPECT_TRUE(again->stats.reconnected);
  EXPECT_EQ(camera.reconnects(), 1);
}

// A camera that stopped acquiring by itself acknowledges triggers and sends nothing, and Aravis'
// heartbeat still finds our control: only a new connection (which starts acquisition again)
// brings the frames back. The capture that finds no frame fails; the next one reconnects.
TEST_F(CameraSim, ACameraThatStoppedAcquiringIsReopenedByTheNextCapture) {
  auto o = driver_options();
  o.frame_timeout_ms = 400;
  o.retries = 1;
  fd::Camera camera(o);
  ASSERT_TRUE(camera.capture().ok());
  sim_->stop_acquisition();
  auto lost = camera.capture();
  ASSERT_FALSE(lost.ok());
  EXPECT_EQ(lost.error().code, "camera.fault");
  EXPECT_FALSE(camera.control_lost()) << "the heartbeat noticed: this test no longer tests the silent case";
  auto c = camera.capture();
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_TRUE(c->stats.reconnected);
  EXPECT_EQ(camera.reconnects(), 1);
  EXPECT_GT(check_geometry(c->cloud, scene_, 0.0), 2000u);
}

TEST_F(CameraSim, MissingPacketsAreRetriedAndCounted) {
  fd::Camera camera(driver_options());
  sim_->lose_packets(1, 0.2);
  auto c = camera.capture();
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_EQ(c->stats.attempts, 2);
  EXPECT_GT(c->stats.missing_packets + c->stats.failed_frames, 0u);
}

TEST_F(CameraSim, StallShorterThanTheTimeoutOnlyDelays) {
  fd::Camera camera(driver_options());
  sim_->stall_next_frame_ms(300);
  auto c = camera.capture();
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_EQ(c->stats.attempts, 1);
  EXPECT_GE(c->stats.wait_ms, 250.0);
}

TEST_F(CameraSim, ControlLostRecreatesCameraAndStream) {
  fd::Camera camera(driver_options());
  ASSERT_TRUE(camera.capture().ok());
  sim_->revoke_control();
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(8);
  while (!camera.control_lost() && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  ASSERT_TRUE(camera.control_lost()) << "Aravis' heartbeat did not report control-lost";
  auto c = camera.capture();
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_TRUE(c->stats.reconnected);
  EXPECT_EQ(camera.reconnects(), 1);
  EXPECT_FALSE(camera.control_lost());
  EXPECT_GT(check_geometry(c->cloud, scene_, 0.0), 2000u);
}

TEST_F(CameraSim, CameraRebootIsSurvived) {
  fd::Camera camera(driver_options());
  ASSERT_TRUE(camera.capture().ok());
  sim_.reset();  // power cycle
  start_camera();
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (!camera.control_lost() && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  ASSERT_TRUE(camera.control_lost());
  auto c = camera.capture();
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_TRUE(c->stats.reconnected);
}

// The camera as the cycle sees it (drivers::CameraDevice): configure, activate, capture,
// deactivate, and activate again; each refusal says why.
TEST_F(CameraSim, TheGigECameraGoesThroughItsLifecycleAndCapturesOnlyWhenActive) {
  fd::GigECamera camera(driver_options());
  EXPECT_EQ(camera.lifecycle(), fd::Lifecycle::unconfigured);
  const auto early = camera.activate();
  ASSERT_FALSE(early);
  EXPECT_EQ(early.error().code, "camera.lifecycle");
  ASSERT_TRUE(camera.configure());
  EXPECT_EQ(camera.lifecycle(), fd::Lifecycle::inactive);
  const auto inactive = camera.capture();
  ASSERT_FALSE(inactive.ok());
  EXPECT_EQ(inactive.error().code, "camera.inactive");
  ASSERT_TRUE(camera.activate()) << camera.last_error().message;
  EXPECT_EQ(camera.lifecycle(), fd::Lifecycle::active);
  EXPECT_EQ(camera.info().width, small_model().width);
  auto c = camera.capture();
  ASSERT_TRUE(c.ok()) << c.error().message;
  EXPECT_GT(check_geometry(c->cloud, scene_, 0.0), 2000u);
  camera.deactivate();
  EXPECT_EQ(camera.lifecycle(), fd::Lifecycle::inactive);
  EXPECT_EQ(camera.capture().error().code, "camera.inactive");
  ASSERT_TRUE(camera.activate()) << camera.last_error().message;  // the control channel was given back
  EXPECT_TRUE(camera.capture().ok());
}

TEST(CameraSimOpen, AGigECameraThatCannotBeOpenedStaysInactiveAndSaysWhy) {
  auto o = driver_options();
  o.address.clear();
  fd::GigECamera nowhere(o);
  const auto bad = nowhere.configure();
  ASSERT_FALSE(bad);
  EXPECT_EQ(bad.error().code, "camera.config");
  EXPECT_EQ(nowhere.lifecycle(), fd::Lifecycle::unconfigured);
  fd::GigECamera absent(driver_options());  // no simulated camera runs in this test
  ASSERT_TRUE(absent.configure());
  const auto st = absent.activate();
  ASSERT_FALSE(st);
  EXPECT_EQ(st.error().code, "camera.unavailable");
  EXPECT_THAT(st.error().message, HasSubstr("powered"));
  EXPECT_EQ(absent.lifecycle(), fd::Lifecycle::inactive);
  EXPECT_EQ(absent.last_error().code, "camera.unavailable");
}

TEST(CameraSimOpen, NoCameraAtTheAddressIsADeviceErrorSayingWhatToCheck) {
  auto o = driver_options();
  try {
    fd::Camera camera(o);
    FAIL() << "opened a camera that is not there";
  } catch (const fettle::DeviceError& e) {
    EXPECT_THAT(e.what(), HasSubstr("127.0.0.1"));
    EXPECT_THAT(e.what(), HasSubstr("powered"));
  }
}

TEST(CameraSimOpen, SecondCameraOnTheSameAddressIsRefused) {
  fs::SimulatedCamera first(fs::SimulatedCameraOptions{}, fs::synthetic_range_source(small_model(), {}));
  auto second = [] { fs::SimulatedCamera s(fs::SimulatedCameraOptions{}, fs::synthetic_range_source(small_model(), {})); };
  EXPECT_THROW(second(), fettle::DeviceError);
}
