// The `browser` device (the mouse in the viewer's page): pointer messages on the bus -> device readings,
// with its safety rules (NaN never forwarded, silence releases, takeover re-grabs).
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/device/browser.hpp"
#include "haptree/device/registry.hpp"
#include "haptree/lcmt_pointer.hpp"

namespace haptree::device {
namespace {

struct Rig {
  bus::Bus bus{"memq://"};
  std::unique_ptr<Device> dev;
  int64_t seq = 0;
  explicit Rig(const std::string& fallback, int id = 3) {
    DeviceConfig c;
    c.bus = &bus;
    c.device_id = id;
    c.options["fallback"] = fallback;
    c.options["grab_m"] = "0,0,0.01";
    dev = make_device("browser", c);
  }
  void send(const Vec3& x, int buttons, int body, int id = 3) {
    lcmt_pointer m{};
    bus::stamp(m, 1);
    m.seq = ++seq;
    m.user_id = id;
    for (int i = 0; i < 3; ++i) m.position_m[i] = x[i];
    m.buttons = buttons;
    m.grab_body = body;
    ASSERT_EQ(bus.publish(bus::channel::pointer(id), m), 0);
    while (bus.handle_timeout(0) > 0) {
    }
  }
  DeviceReading read(double t) {
    DeviceReading r;
    EXPECT_TRUE(dev->read(t, r).ok());
    return r;
  }
};

TEST(BrowserDevice, PressGrabsThePickedPointAndBodyExactly) {
  Rig rig("none");
  const Vec3 x(0.01, -0.02, 0.03);
  rig.send(x, 1, 42);
  // the source switches from "nothing" to the page: the button is held up for switch_s (0.02 s)
  DeviceReading r = rig.read(0.0);
  EXPECT_EQ(r.buttons, 0);
  r = rig.read(0.05);
  EXPECT_EQ(r.buttons, kButtonGrab);
  EXPECT_EQ(r.grab_body, 42);
  EXPECT_EQ(r.position_m, x);   // a press grabs exactly the picked point (no filter lag)
  // a move is filtered towards the target, never beyond it
  const Vec3 y = x + Vec3(0.01, 0, 0);
  rig.send(y, 1, 42);
  r = rig.read(0.051);
  EXPECT_GT(r.position_m.x(), x.x());
  EXPECT_LT(r.position_m.x(), y.x());
  EXPECT_TRUE(r.linear_velocity_mps.allFinite());
}

TEST(BrowserDevice, NonFinitePointerIsNeverForwarded) {
  Rig rig("none");
  const Vec3 x(0.01, 0.02, 0.03);
  rig.send(x, 1, 7);
  rig.read(0.0);
  DeviceReading r = rig.read(0.05);
  ASSERT_EQ(r.buttons, kButtonGrab);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  rig.send(Vec3(nan, 0, 0), 1, 7);
  rig.send(Vec3(0, std::numeric_limits<double>::infinity(), 0), 1, 7);
  rig.send(Vec3(1e6, 0, 0), 1, 7);   // absurd: refused as well
  for (double t = 0.06; t < 0.3; t += 0.01) {
    r = rig.read(t);
    EXPECT_TRUE(r.position_m.allFinite());
    EXPECT_TRUE(r.linear_velocity_mps.allFinite());
    EXPECT_NEAR((r.position_m - x).norm(), 0.0, 1e-15);   // holds the last good pose
  }
  EXPECT_EQ(static_cast<BrowserDevice&>(*rig.dev).refused(), 1);   // latest-value mailbox: the newest of the three
}

TEST(BrowserDevice, SilenceReleasesTheGrab) {
  Rig rig("none");
  rig.send(Vec3(0.01, 0, 0), 1, 5);
  rig.read(0.0);
  EXPECT_EQ(rig.read(0.1).buttons, kButtonGrab);
  EXPECT_EQ(rig.read(0.5).buttons, kButtonGrab);   // within timeout_s (0.5 s) of the message at t = 0
  const DeviceReading r = rig.read(0.51);            // dropped WebSocket / dead viewer: released
  EXPECT_EQ(r.buttons, 0);
  EXPECT_EQ(r.grab_body, 0);
  EXPECT_TRUE(r.position_m.allFinite());
}

TEST(BrowserDevice, PageTakesOverTheScriptWithAReleaseInBetween) {
  Rig rig("scripted");
  // the script (GrabPullRelease) presses its button after its approach; find a time it is down
  double t = 0;
  DeviceReading r;
  for (; t < 10; t += 0.01) {
    r = rig.read(t);
    if (r.buttons == kButtonGrab) break;
  }
  ASSERT_EQ(r.buttons, kButtonGrab) << "the scripted fallback never grabbed";
  EXPECT_EQ(r.grab_body, 0);   // the script lets the coupler pick
  rig.send(Vec3(0.02, 0.02, 0.02), 1, 9);
  r = rig.read(t + 0.001);
  EXPECT_EQ(r.buttons, 0) << "the coupler must see a release before the page's grab";
  r = rig.read(t + 0.03);
  EXPECT_EQ(r.buttons, kButtonGrab);
  EXPECT_EQ(r.grab_body, 9);
  // the press counter moves, so a coupler that missed the short release (coalesced) still re-grabs
  const int32_t seq = r.grab_seq;
  EXPECT_GE(seq, 1);
  // the page releases: the page keeps the user (button up), the script does not come back ...
  rig.send(Vec3(0.02, 0.02, 0.02), 0, 0);
  r = rig.read(t + 0.04);
  EXPECT_EQ(r.buttons, 0);
  rig.send(Vec3(0.02, 0.02, 0.02), 1, 9);
  EXPECT_EQ(rig.read(t + 0.045).grab_seq, seq + 1);   // pressed again: a new grab
  rig.send(Vec3(0.02, 0.02, 0.02), 0, 0);
  rig.read(t + 0.05);
  // ... until the tab goes quiet for timeout_s; then the script runs again
  EXPECT_TRUE(static_cast<BrowserDevice&>(*rig.dev).page_owns());
  rig.read(t + 0.7);
  EXPECT_FALSE(static_cast<BrowserDevice&>(*rig.dev).page_owns());
}

TEST(BrowserDevice, OtherUsersPointerIsIgnoredAndOptionsAreChecked) {
  Rig rig("none", 3);
  rig.send(Vec3(0.01, 0, 0), 1, 5, /*id=*/4);
  rig.read(0.0);
  EXPECT_EQ(rig.read(0.1).buttons, 0);
  DeviceConfig c;
  EXPECT_THROW(make_device("browser", c), std::invalid_argument);   // no bus
  bus::Bus b("memq://");
  c.bus = &b;
  c.options["fallback"] = "joystick";
  EXPECT_THROW(make_device("browser", c), std::invalid_argument);
  c.options["fallback"] = "none";
  c.options["timeout_s"] = "-1";
  EXPECT_THROW(make_device("browser", c), std::invalid_argument);
}

}  // namespace
}  // namespace haptree::device
