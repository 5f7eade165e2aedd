// The spindle master against the simulated CiA 402 drive on the in-process CAN bus.
#include <cmath>
#include <optional>

#include <gtest/gtest.h>

#include "fettle/core/error.hpp"
#include "fettle/drivers/spindle.hpp"
#include "fettle/sim/spindle.hpp"
#include "spindle_test_util.hpp"

using namespace fettle::canopen;
using fettle::Status;
using fettle::drivers::SpindleDrive;
using fettle::drivers::SpindleEvent;
using fettle::drivers::SpindleOptions;
using fettle::test::await;
using fettle::test::run_for;
using fettle::test::run_until;
using namespace std::chrono_literals;

namespace {

class SpindleDriveTest : public ::testing::Test {
 protected:
  void make(SpindleOptions o = {}, fettle::sim::SpindleSimOptions so = {}) {
    bus = InProcessBus::create();
    drive = std::make_unique<fettle::sim::SimulatedSpindleDrive>(io, bus->attach(io, "drive"), so);
    drive->power_on();
    master = std::make_unique<SpindleDrive>(io, bus->attach(io, "master"), o);
    EXPECT_TRUE(master->configure().ok());
    master->on_event([this](const SpindleEvent& e) { events.push_back(e); });
  }
  void make_started(SpindleOptions o = {}, fettle::sim::SpindleSimOptions so = {}) {
    make(o, so);
    const Status s = await(io, [&](auto h) { master->activate_async(h); });
    ASSERT_TRUE(s.ok()) << s.error().message;
  }
  /// Heartbeats every 30 ms, lost after 120 ms: heartbeat tests finish quickly.
  static SpindleOptions fast_heartbeats() {
    SpindleOptions o;
    o.heartbeat_producer_ms = 30;
    o.heartbeat_timeout_ms = 120;
    return o;
  }
  bool saw(SpindleEvent::Kind k) const {
    return std::any_of(events.begin(), events.end(), [k](const auto& e) { return e.kind == k; });
  }
  void TearDown() override {
    master.reset();
    drive.reset();
  }

  boost::asio::io_context io;
  std::shared_ptr<InProcessBus> bus;
  std::unique_ptr<fettle::sim::SimulatedSpindleDrive> drive;
  std::unique_ptr<SpindleDrive> master;
  std::vector<SpindleEvent> events;
};

}  // namespace

TEST_F(SpindleDriveTest, StartConfiguresHeartbeatModeAndTpdoThenGoesOperational) {
  SpindleOptions o;
  o.heartbeat_producer_ms = 50;
  o.heartbeat_timeout_ms = 200;
  make_started(o);
  EXPECT_EQ(drive->heartbeat_producer_ms(), 50);
  EXPECT_EQ(drive->mode(), 3);
  EXPECT_EQ(drive->nmt_state(), NmtState::operational);
  const auto& st = master->status();
  EXPECT_TRUE(st.configured);
  EXPECT_EQ(st.state, DriveState::switch_on_disabled);
  EXPECT_DOUBLE_EQ(st.rated_current_a, 8.0);
  EXPECT_GT(st.feedback_frames, 0U);
  run_for(io, 300ms);
  EXPECT_TRUE(master->status().heartbeat_ok);
  EXPECT_FALSE(master->status().fault);
}

TEST_F(SpindleDriveTest, SpinUpCompletesAtSpeedWithinToleranceThenStopReachesStandstill) {
  make_started();
  const Status s = await(io, [&](auto h) { master->spin_up(6000, h); });
  ASSERT_TRUE(s.ok()) << s.error().message;
  EXPECT_EQ(master->status().state, DriveState::operation_enabled);
  EXPECT_NEAR(master->status().velocity_rpm, 6000.0, 100.0);
  EXPECT_NEAR(drive->velocity_rpm(), 6000.0, 100.0);
  const Status st = await(io, [&](auto h) { master->spin_down(h); });
  ASSERT_TRUE(st.ok()) << st.error().message;
  EXPECT_NEAR(drive->velocity_rpm(), 0.0, 100.0);
  EXPECT_EQ(drive->state(), DriveState::ready_to_switch_on);
}

// The device lifecycle (device.hpp): deactivate() mid-spin sets the target to 0 and keeps the
// heartbeats going, so the drive ramps down instead of faulting on a lost master; a second
// activate() configures it again and it spins up.
TEST_F(SpindleDriveTest, TheDriveGoesThroughTheDeviceLifecycleAndDeactivateRampsItDown) {
  make();
  EXPECT_EQ(master->lifecycle(), fettle::drivers::Lifecycle::inactive);
  make_started(fast_heartbeats());
  EXPECT_EQ(master->lifecycle(), fettle::drivers::Lifecycle::active);
  ASSERT_TRUE(await(io, [&](auto h) { master->spin_up(6000, h); }).ok());
  std::optional<Status> pending;  // a spin-up in progress fails when the drive is deactivated
  master->spin_up(3000, [&](Status s) { pending = std::move(s); });
  master->deactivate();
  ASSERT_TRUE(pending.has_value());
  EXPECT_EQ(pending->error().code, "spindle.inactive");
  EXPECT_EQ(master->lifecycle(), fettle::drivers::Lifecycle::inactive);
  EXPECT_FALSE(master->status().configured);
  ASSERT_TRUE(run_until(io, [&] { return std::abs(drive->velocity_rpm()) < 1.0; }, 15s)) << drive->velocity_rpm();
  run_for(io, 300ms);  // longer than the drive's heartbeat timeout: our heartbeat still arrives
  EXPECT_NE(drive->state(), DriveState::fault);
  EXPECT_FALSE(master->status().fault);
  Status s = await(io, [&](auto h) { master->spin_up(2000, h); });
  EXPECT_EQ(s.error().code, "spindle.not_started");
  ASSERT_TRUE(await(io, [&](auto h) { master->activate_async(h); }).ok());
  s = await(io, [&](auto h) { master->spin_up(2000, h); });
  EXPECT_TRUE(s.ok()) << s.error().message;
}

// A clean stop: the released drive no longer watches our heartbeat, so the master may go away
// without the heartbeat fault (0x8130) a killed master leaves (next test but one).
TEST_F(SpindleDriveTest, AReleasedDriveDoesNotFaultWhenTheMasterGoes) {
  make_started(fast_heartbeats());
  ASSERT_TRUE(await(io, [&](auto h) { master->spin_up(3000, h); }).ok());
  ASSERT_TRUE(await(io, [&](auto h) { master->spin_down(h); }).ok());
  const Status released = await(io, [&](auto h) { master->deactivate_async(h); });
  ASSERT_TRUE(released.ok()) << released.error().message;
  EXPECT_EQ(master->lifecycle(), fettle::drivers::Lifecycle::inactive);
  master.reset();  // the process exits: no more heartbeats
  run_for(io, 500ms);  // four times the drive's heartbeat timeout
  EXPECT_EQ(drive->state(), DriveState::switch_on_disabled);
}

TEST_F(SpindleDriveTest, ConfigureRefusesOptionsThatCannotWorkNamingTheKey) {
  bus = InProcessBus::create();
  SpindleOptions o;
  o.heartbeat_producer_ms = 300;
  o.heartbeat_timeout_ms = 300;
  master = std::make_unique<SpindleDrive>(io, bus->attach(io, "master"), o);
  const Status s = master->configure();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code, "spindle.config");
  EXPECT_NE(s.error().message.find("[spindle] heartbeat_timeout_ms"), std::string::npos) << s.error().message;
  EXPECT_EQ(master->last_error().code, "spindle.config");
  EXPECT_EQ(master->lifecycle(), fettle::drivers::Lifecycle::unconfigured);
  const Status a = await(io, [&](auto h) { master->activate_async(h); });
  EXPECT_EQ(a.error().code, "spindle.lifecycle");
}

TEST_F(SpindleDriveTest, VlModeUsesObject6042) {
  SpindleOptions o;
  o.mode = OperationMode::velocity;
  make_started(o);
  EXPECT_EQ(drive->mode(), 2);
  const Status s = await(io, [&](auto h) { master->spin_up(-3000, h); });
  ASSERT_TRUE(s.ok()) << s.error().message;
  EXPECT_NEAR(drive->velocity_rpm(), -3000.0, 100.0);
  Status r = await(io, [&](auto h) {
    master->sdo_read(od::vl_target_velocity, 0, [h](fettle::Result<std::uint32_t> v) {
      if (!v) return h(v.error());
      h(static_cast<std::int16_t>(*v) == -3000 ? Status{} : Status{fettle::Error{"x", std::to_string(*v)}});
    });
  });
  EXPECT_TRUE(r.ok()) << r.error().message;
}

TEST_F(SpindleDriveTest, SdoAbortIsReportedWithCodeAndText) {
  make_started();
  std::optional<fettle::Result<std::uint32_t>> got;
  master->sdo_read(0x2345, 0, [&](fettle::Result<std::uint32_t> r) { got = std::move(r); });
  ASSERT_TRUE(run_until(io, [&] { return got.has_value(); }));
  ASSERT_FALSE(got->ok());
  EXPECT_EQ(got->error().code, "spindle.sdo_abort");
  EXPECT_NE(got->error().message.find("0x06020000 object does not exist"), std::string::npos) << got->error().message;
  EXPECT_NE(got->error().message.find("0x2345:00"), std::string::npos) << got->error().message;

  const Status w = await(io, [&](auto h) { master->sdo_write(od::statusword, 0, 0, 2, h); });
  ASSERT_FALSE(w.ok());
  EXPECT_NE(w.error().message.find("read-only"), std::string::npos) << w.error().message;

  const Status m = await(io, [&](auto h) { master->sdo_write(od::modes_of_operation, 0, 7, 1, h); });
  ASSERT_FALSE(m.ok());
  EXPECT_NE(m.error().message.find("0x06090030"), std::string::npos) << m.error().message;
}

TEST_F(SpindleDriveTest, SdoAnswerForAnotherObjectIsRejected) {
  // A protocol fake on the bus that answers every upload with index 0x1000.
  bus = InProcessBus::create();
  auto fake = bus->attach(io, "fake");
  fake->start(
      [&](const CanFrame& f) {
        if (f.id == 0x601) fake->send(sdo_upload_response(1, 0x1000, 0, 0x192, 4));
      },
      [](const fettle::Error&) {});
  master = std::make_unique<SpindleDrive>(io, bus->attach(io, "master"), SpindleOptions{});
  EXPECT_TRUE(master->configure().ok());
  std::optional<fettle::Result<std::uint32_t>> got;
  master->sdo_read(od::statusword, 0, [&](fettle::Result<std::uint32_t> r) { got = std::move(r); });
  ASSERT_TRUE(run_until(io, [&] { return got.has_value(); }));
  ASSERT_FALSE(got->ok());
  EXPECT_EQ(got->error().code, "spindle.sdo_mismatch");
  fake->close();
}

TEST_F(SpindleDriveTest, StartWithoutADriveTimesOutWaitingForBootUp) {
  bus = InProcessBus::create();
  SpindleOptions o;
  o.step_timeout_ms = 150;
  master = std::make_unique<SpindleDrive>(io, bus->attach(io, "master"), o);
  EXPECT_TRUE(master->configure().ok());
  const Status s = await(io, [&](auto h) { master->activate_async(h); });
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code, "spindle.timeout");
  EXPECT_NE(s.error().message.find("boot-up"), std::string::npos) << s.error().message;
}

TEST_F(SpindleDriveTest, SdoTimeoutWhenNodeDoesNotAnswer) {
  bus = InProcessBus::create();
  SpindleOptions o;
  o.sdo_timeout_ms = 80;
  master = std::make_unique<SpindleDrive>(io, bus->attach(io, "master"), o);
  EXPECT_TRUE(master->configure().ok());
  std::optional<fettle::Result<std::uint32_t>> got;
  master->sdo_read(od::statusword, 0, [&](fettle::Result<std::uint32_t> r) { got = std::move(r); });
  ASSERT_TRUE(run_until(io, [&] { return got.has_value(); }));
  ASSERT_FALSE(got->ok());
  EXPECT_EQ(got->error().code, "spindle.sdo_timeout");
}

TEST_F(SpindleDriveTest, SpinUpIsRefusedBeforeStartAndAboveMaxRpm) {
  make();
  Status s = await(io, [&](auto h) { master->spin_up(1000, h); });
  EXPECT_EQ(s.error().code, "spindle.not_started");
  const Status started = await(io, [&](auto h) { master->activate_async(h); });
  ASSERT_TRUE(started.ok());
  s = await(io, [&](auto h) { master->spin_up(20000, h); });
  EXPECT_EQ(s.error().code, "spindle.bad_speed");
  EXPECT_EQ(drive->state(), DriveState::switch_on_disabled);
}

TEST_F(SpindleDriveTest, SpinUpTimesOutWhenTheDriveIsTooSlow) {
  SpindleOptions o;
  o.spin_up_timeout_ms = 200;
  fettle::sim::SpindleSimOptions so;
  so.ramp_rpm_s = 1000;
  make_started(o, so);
  const Status s = await(io, [&](auto h) { master->spin_up(8000, h); });
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code, "spindle.timeout");
  EXPECT_NE(s.error().message.find("8000 rpm"), std::string::npos) << s.error().message;
}

TEST_F(SpindleDriveTest, StopCancelsARunningSpinUp) {
  fettle::sim::SpindleSimOptions so;
  so.ramp_rpm_s = 5000;
  make_started({}, so);
  fettle::test::Completion spin;
  master->spin_up(10000, spin.handler());
  run_for(io, 100ms);
  const Status st = await(io, [&](auto h) { master->spin_down(h); });
  EXPECT_TRUE(st.ok()) << st.error().message;
  ASSERT_TRUE(spin.done());
  EXPECT_EQ(spin.status->error().code, "spindle.cancelled");
  EXPECT_NEAR(drive->velocity_rpm(), 0.0, 100.0);
}

TEST_F(SpindleDriveTest, OvercurrentEmcyFailsSpinUpLatchesFaultAndIsNeverReEnabledSilently) {
  fettle::sim::SpindleSimOptions so;
  so.ramp_rpm_s = 5000;
  make_started({}, so);
  fettle::test::Completion spin;
  master->spin_up(10000, spin.handler());
  run_for(io, 100ms);
  drive->inject_fault(fettle::sim::SpindleFault::overcurrent);
  ASSERT_TRUE(run_until(io, [&] { return spin.done(); }));
  ASSERT_FALSE(spin.status->ok());
  EXPECT_EQ(spin.status->error().code, "spindle.fault");
  EXPECT_EQ(spin.status->error().kind, fettle::ErrorKind::device_fault);
  EXPECT_NE(spin.status->error().message.find("0x2310 continuous over-current"), std::string::npos)
      << spin.status->error().message;
  EXPECT_TRUE(saw(SpindleEvent::Kind::emergency));
  EXPECT_TRUE(saw(SpindleEvent::Kind::fault));
  ASSERT_TRUE(master->status().last_emcy);
  EXPECT_EQ(master->status().last_emcy->error_register, 0x03);

  // Refused while latched; the drive stays in fault.
  Status again = await(io, [&](auto h) { master->spin_up(2000, h); });
  EXPECT_EQ(again.error().code, "spindle.fault");
  run_for(io, 100ms);
  EXPECT_EQ(drive->state(), DriveState::fault);

  // Explicit reset, then it can be enabled again.
  const Status reset = await(io, [&](auto h) { master->fault_reset(h); });
  ASSERT_TRUE(reset.ok()) << reset.error().message;
  EXPECT_FALSE(master->status().fault);
  EXPECT_EQ(drive->state(), DriveState::switch_on_disabled);
  again = await(io, [&](auto h) { master->spin_up(2000, h); });
  EXPECT_TRUE(again.ok()) << again.error().message;
}

TEST_F(SpindleDriveTest, OvertemperatureWhileIdleIsReportedAsAFaultEvent) {
  make_started();
  drive->inject_fault(fettle::sim::SpindleFault::overtemperature);
  ASSERT_TRUE(run_until(io, [&] { return master->status().fault.has_value(); }));
  EXPECT_NE(master->status().fault->message.find("0x4310"), std::string::npos) << master->status().fault->message;
  EXPECT_TRUE(run_until(io, [&] { return master->status().state == DriveState::fault; }));
}

TEST_F(SpindleDriveTest, DriveHeartbeatLossIsAFault) {
  const SpindleOptions o = fast_heartbeats();
  make_started(o);
  drive->set_heartbeat_enabled(false);
  ASSERT_TRUE(run_until(io, [&] { return saw(SpindleEvent::Kind::heartbeat_lost); }));
  ASSERT_TRUE(master->status().fault);
  EXPECT_EQ(master->status().fault->code, "spindle.heartbeat_lost");
  const Status s = await(io, [&](auto h) { master->fault_reset(h); });
  EXPECT_EQ(s.error().code, "spindle.heartbeat_lost");
  drive->set_heartbeat_enabled(true);
  ASSERT_TRUE(run_until(io, [&] { return saw(SpindleEvent::Kind::heartbeat_restored); }));
  EXPECT_TRUE(master->status().fault) << "the fault stays latched until fault_reset";
}

TEST_F(SpindleDriveTest, DriveFaultsWhenTheMastersHeartbeatStops) {
  const SpindleOptions o = fast_heartbeats();
  make_started(o);
  ASSERT_TRUE(await(io, [&](auto h) { master->spin_up(3000, h); }).ok());
  bus->set_connected(false);  // cable pulled: both sides lose each other's heartbeat
  ASSERT_TRUE(run_until(io, [&] { return drive->state() == DriveState::fault; }));
  EXPECT_TRUE(run_until(io, [&] { return saw(SpindleEvent::Kind::heartbeat_lost); }));
  bus->set_connected(true);
  ASSERT_TRUE(run_until(io, [&] { return master->status().state == DriveState::fault; }));
  EXPECT_TRUE(master->status().fault);
}

// fettled restarted or killed: the drive faulted on the lost heartbeat (0x8130). The new master
// reads 0x603F at start, sees that its own absence was the cause and resets the fault.
TEST_F(SpindleDriveTest, ARestartedMasterResetsTheHeartbeatFaultItsAbsenceCaused) {
  const SpindleOptions o = fast_heartbeats();
  make_started(o);
  ASSERT_TRUE(await(io, [&](auto h) { master->spin_up(3000, h); }).ok());
  master.reset();  // the process is gone: no more heartbeats
  ASSERT_TRUE(run_until(io, [&] { return drive->state() == DriveState::fault; }));
  master = std::make_unique<SpindleDrive>(io, bus->attach(io, "master again"), o);
  EXPECT_TRUE(master->configure().ok());
  const Status s = await(io, [&](auto h) { master->activate_async(h); });
  ASSERT_TRUE(s.ok()) << s.error().message;
  EXPECT_FALSE(master->status().fault);
  EXPECT_EQ(drive->state(), DriveState::switch_on_disabled);
  EXPECT_TRUE(await(io, [&](auto h) { master->spin_up(2000, h); }).ok());
}

// Any other fault found at start stays latched for an operator, and says which it is.
TEST_F(SpindleDriveTest, AnyOtherFaultFoundAtStartStaysLatchedAndIsNamed) {
  make_started();
  drive->inject_fault(fettle::sim::SpindleFault::overcurrent);
  ASSERT_TRUE(run_until(io, [&] { return drive->state() == DriveState::fault; }));
  master.reset();
  master = std::make_unique<SpindleDrive>(io, bus->attach(io, "master again"), SpindleOptions{});
  EXPECT_TRUE(master->configure().ok());
  const Status s = await(io, [&](auto h) { master->activate_async(h); });
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().code, "spindle.fault");
  EXPECT_NE(s.error().message.find("0x2310"), std::string::npos) << s.error().message;
  EXPECT_EQ(drive->state(), DriveState::fault);
}

TEST_F(SpindleDriveTest, LoadCurrentRisesWithMaterialRemoval) {
  make_started();
  ASSERT_TRUE(await(io, [&](auto h) { master->spin_up(6000, h); }).ok());
  run_for(io, 100ms);
  const double idle = master->status().current_a;
  EXPECT_GT(idle, 0.1);
  drive->set_material_removal_rate(100.0);  // mm³/s
  run_for(io, 100ms);
  const double loaded = master->status().current_a;
  EXPECT_NEAR(loaded - idle, 5.0, 0.1) << "0.05 A per mm³/s";
  EXPECT_GT(master->status().current_permille, 600.0);
}

TEST_F(SpindleDriveTest, TooMuchMaterialTripsOverCurrent) {
  make_started();
  ASSERT_TRUE(await(io, [&](auto h) { master->spin_up(6000, h); }).ok());
  drive->set_material_removal_rate(400.0);
  ASSERT_TRUE(run_until(io, [&] { return master->status().fault.has_value(); }));
  EXPECT_NE(master->status().fault->message.find("0x2310"), std::string::npos);
}

TEST_F(SpindleDriveTest, DriveRebootIsLatchedAsAFault) {
  make_started();
  master->nmt(NmtCommand::reset_node);
  ASSERT_TRUE(run_until(io, [&] { return master->status().fault.has_value(); }));
  EXPECT_EQ(master->status().fault->code, "spindle.rebooted");
}

TEST(SpindleConfig, OptionsComeFromTheSpindleSection) {
  fettle::config::SpindleSection s;
  s.node_id = 9;
  s.mode = "velocity";
  s.heartbeat_producer_ms = 40;
  const auto o = SpindleOptions::from_config(s);
  EXPECT_EQ(o.node_id, 9);
  EXPECT_EQ(o.mode, OperationMode::velocity);
  EXPECT_EQ(o.heartbeat_producer_ms, 40);
  boost::asio::io_context io;
  s.transport = "sim";
  EXPECT_THROW((void)fettle::drivers::make_spindle_transport(io, s), fettle::UserError);
}
