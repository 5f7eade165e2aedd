// The SocketCAN transport. This needs a kernel with AF_CAN and a vcan0 interface; elsewhere the
// tests skip and say why.
#include <net/if.h>

#include <gtest/gtest.h>

#include "fettle/core/error.hpp"
#include "fettle/drivers/canopen_transport.hpp"
#include "spindle_test_util.hpp"

using namespace fettle::canopen;

namespace {

void require_vcan0() {
  std::string why;
  if (!socketcan_available(&why)) GTEST_SKIP() << why;
  if (::if_nametoindex("vcan0") == 0)
    GTEST_SKIP() << "no vcan0 interface (ip link add dev vcan0 type vcan && ip link set up vcan0)";
}

}  // namespace

TEST(CanopenSocketCan, UnknownInterfaceIsADeviceErrorNamingIt) {
  std::string why;
  if (!socketcan_available(&why)) GTEST_SKIP() << why;
  boost::asio::io_context io;
  try {
    (void)open_socketcan(io, "nosuchcan7");
    FAIL() << "expected a DeviceError";
  } catch (const fettle::DeviceError& e) {
    EXPECT_NE(std::string(e.what()).find("nosuchcan7"), std::string::npos) << e.what();
  }
}

TEST(CanopenSocketCan, WithoutAfCanOpeningFailsWithAClearDeviceError) {
  std::string why;
  if (socketcan_available(&why)) GTEST_SKIP() << "this kernel has AF_CAN; the no-AF_CAN path cannot be exercised";
  EXPECT_NE(why.find("AF_CAN"), std::string::npos) << why;
  boost::asio::io_context io;
  EXPECT_THROW((void)open_socketcan(io, "vcan0"), fettle::DeviceError);
}

TEST(CanopenSocketCan, TwoSocketsOnVcan0SeeEachOthersFramesThroughFilters) {
  require_vcan0();
  if (testing::Test::IsSkipped()) return;
  boost::asio::io_context io;
  auto a = open_socketcan(io, "vcan0");
  auto b = open_socketcan(io, "vcan0", {CanFilter{0x581, 0x7FF}});
  std::vector<CanFrame> got;
  a->start([](const CanFrame&) {}, [](const fettle::Error&) {});
  b->start([&](const CanFrame& f) { got.push_back(f); }, [](const fettle::Error&) {});
  a->send(CanFrame::make(0x123, {1}));  // filtered out
  a->send(CanFrame::make(0x581, {0x60, 0x40, 0x60, 0, 0, 0, 0, 0}));
  ASSERT_TRUE(fettle::test::run_until(io, [&] { return !got.empty(); }));
  fettle::test::run_for(io, std::chrono::milliseconds(50));
  ASSERT_EQ(got.size(), 1U);
  EXPECT_EQ(got[0].id, 0x581U);
  a->close();
  b->close();
}
