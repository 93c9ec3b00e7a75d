// The inverse3 device in this process against the fake Inverse Service: axes, units, the protocol's
// dialects, the link checks, and a zero force as the last command.
#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <thread>
#include <vector>

#include "haptree/device/inverse3.hpp"
#include "haptree/device/registry.hpp"
#include "tests/device/inverse3/fake_inverse_service.hpp"
#include "tests/device/vendor_test_util.hpp"

namespace haptree::device {
namespace {

using testing::FakeFault;
using testing::FakeInverseOptions;
using testing::FakeInverseService;

using vendor_test::free_port;
using vendor_test::sleep_s;

std::unique_ptr<Device> make(const std::string& url, std::map<std::string, std::string> extra = {}) {
  DeviceConfig c;
  c.spec.max_force_n = 3.0;
  c.options = std::move(extra);
  c.options["url"] = url;
  c.options.emplace("timeout_s", "0.5");   // a loaded test machine never looks like a lost link
  return make_device("inverse3", c);
}

// Reads until ok (the I/O thread has state from the first reply on; open() already waited for it).
DeviceReading read_ok(Device& d) {
  DeviceReading r;
  const Status s = d.read(0, r);
  EXPECT_TRUE(s.ok()) << s.reason;
  return r;
}

TEST(Inverse3Axes, DefaultMapsUpAndTowardsTheUser) {
  const Mat3 a = AxisMap::parse(Inverse3Params{}.axes).matrix();
  // Haply +z (up) -> haptree +y; Haply +y (forward, away from the user) -> haptree -z; +x -> +x
  EXPECT_EQ(a * Vec3(0, 0, 1), Vec3(0, 1, 0));
  EXPECT_EQ(a * Vec3(0, 1, 0), Vec3(0, 0, -1));
  EXPECT_EQ(a * Vec3(1, 0, 0), Vec3(1, 0, 0));
  EXPECT_DOUBLE_EQ(a.determinant(), 1.0);
  DeviceConfig c;
  c.options["axes"] = "x,z,y";   // a mirror
  EXPECT_THROW(make_device("inverse3", c), std::invalid_argument);
}

TEST(Inverse3Device, PoseInMetresViewAxesAndForceInDeviceAxes) {
  FakeInverseOptions o;
  o.rest_m = Vec3(0.03, -0.12, 0.15);
  o.grip_orientation = Quat(Eigen::AngleAxisd(0.5, Vec3::UnitZ()));   // 0.5 rad about device up
  FakeInverseService svc(o);
  auto d = make(svc.url());
  ASSERT_TRUE(d->open().ok());
  auto* inv = dynamic_cast<Inverse3Device*>(d.get());
  ASSERT_NE(inv, nullptr);
  EXPECT_EQ(inv->device_id(), "049D");
  EXPECT_EQ(inv->grip_id(), "61548");
  const DeviceDescription desc = d->describe();
  EXPECT_EQ(desc.model, "Haply Inverse3 (version 7.4, right-handed)");
  EXPECT_EQ(desc.serial, "049D");
  EXPECT_EQ(desc.buttons, 3);
  EXPECT_TRUE(desc.orientation);
  EXPECT_FALSE(desc.torque);
  EXPECT_EQ(desc.max_torque_nm, 0.0);
  EXPECT_TRUE(std::isnan(desc.max_force_n)) << "the service reports no force limit";
  EXPECT_EQ(desc.axes, "x,z,-y");
  DeviceReading r = read_ok(*d);
  // (x, y, z) device -> (x, z, -y) view, metres as sent (JSON keeps every digit of a double).
  EXPECT_EQ(r.position_m, Vec3(0.03, 0.15, 0.12));
  // The grip's rotation about device up is a rotation about view up (+y), by the same angle.
  const Eigen::AngleAxisd aa(r.orientation);
  EXPECT_NEAR(aa.angle(), 0.5, 1e-12);
  EXPECT_NEAR(std::abs(aa.axis().y()), 1.0, 1e-12);
  EXPECT_GT(aa.axis().y(), 0.0);

  // Force output is off after open(): what write() asks is not sent, a zero force is.
  for (int i = 0; i < 100; ++i) {
    ASSERT_TRUE(d->write_force(Vec3(0, 1, 0)).ok());
    sleep_s(1e-3);
  }
  auto off = svc.forces();
  ASSERT_GT(off.size(), 20u);
  for (const auto& rec : off) ASSERT_EQ(rec.force_n, Vec3::Zero());
  ASSERT_TRUE(d->enable_force(true).ok());
  // 1 N up in the view = 1 N along device +z; the fake's spring (200 N/m) settles 5 mm higher.
  for (int i = 0; i < 600; ++i) {
    ASSERT_TRUE(d->write_force(Vec3(0, 1, 0)).ok());
    sleep_s(1e-3);
  }
  const auto log = svc.forces();
  ASSERT_GT(log.size(), 100u);
  EXPECT_TRUE(log.back().applied);
  EXPECT_NEAR((log.back().force_n - Vec3(0, 0, 1)).norm(), 0.0, 1e-15);
  r = read_ok(*d);
  EXPECT_NEAR(r.position_m.y(), 0.15 + 1.0 / 200, 2e-4) << "spring equilibrium 5 mm up";
  EXPECT_NEAR(r.position_m.x(), 0.03, 1e-6);
  EXPECT_NEAR(r.position_m.z(), 0.12, 1e-6);
  // Above the device's force limit: the I/O thread's own clamp (3 N) after the bridge's.
  for (int i = 0; i < 50; ++i) {
    ASSERT_TRUE(d->write_force(Vec3(0, 0, 30)).ok());
    sleep_s(1e-3);
  }
  const double fmax = [&] {
    double m = 0;
    for (const auto& rec : svc.forces()) m = std::max(m, rec.force_n.norm());
    return m;
  }();
  EXPECT_NEAR(fmax, 3.0, 1e-12);
  EXPECT_EQ(svc.forces().back().force_n, Vec3(0, -3, 0)) << "view +z (towards the user) = device -y";
  // Off again: zero from the next tick on, whatever the mailbox holds.
  ASSERT_TRUE(d->enable_force(false).ok());
  sleep_s(0.05);
  EXPECT_EQ(svc.forces().back().force_n, Vec3::Zero());
  ASSERT_TRUE(d->enable_force(true).ok());
  sleep_s(0.05);
  EXPECT_EQ(svc.forces().back().force_n, Vec3(0, -3, 0));
  d->close();
  const auto end = svc.forces();
  EXPECT_EQ(end.back().force_n, Vec3::Zero()) << "the last command on close is a zero force";
  EXPECT_TRUE(end.back().applied);
  EXPECT_FALSE(d->read(0, r).ok());
  EXPECT_FALSE(d->write_force(Vec3::Zero()).ok());
}

TEST(Inverse3Device, ButtonsOfTheWirelessAndTheWiredGrip) {
  for (bool wireless : {true, false}) {
    FakeInverseOptions o;
    o.wireless_grip = wireless;
    o.buttons = {{0.0, 0.5, 1}, {0.5, 1.0, 2}};   // a, then b (a wired grip has one button: b is not there)
    FakeInverseService svc(o);
    auto d = make(svc.url());
    ASSERT_TRUE(d->open().ok());
    EXPECT_EQ(d->describe().buttons, wireless ? 3 : 1);
    // The sequence of distinct button states read (timing-free: a loaded machine may read rarely).
    std::vector<int32_t> seq;
    const auto t0 = std::chrono::steady_clock::now();
    while (std::chrono::steady_clock::now() - t0 < std::chrono::milliseconds(1300)) {
      d->write_force(Vec3::Zero());
      DeviceReading r;
      if (d->read(0, r).ok() && (seq.empty() || seq.back() != r.buttons)) seq.push_back(r.buttons);
      sleep_s(2e-3);
    }
    const std::vector<int32_t> expected = wireless ? std::vector<int32_t>{1, 2, 0} : std::vector<int32_t>{1, 0};
    EXPECT_EQ(seq, expected) << "wireless " << wireless << ": a = bit 0 (grab), b = bit 1 (clutch)";
  }
}

TEST(Inverse3Device, OlderServiceReadsValues) {
  FakeInverseOptions o;
  o.old_dialect = true;
  FakeInverseService svc(o);
  {
    auto d = make(svc.url());   // writes "vector": an older service ignores it
    ASSERT_TRUE(d->open().ok());
    ASSERT_TRUE(d->enable_force(true).ok());
    for (int i = 0; i < 50; ++i, sleep_s(1e-3)) d->write_force(Vec3(0.5, 0, 0));
    d->close();
    const auto log = svc.forces();
    ASSERT_FALSE(log.empty());
    EXPECT_FALSE(log.back().applied);
  }
  auto d = make(svc.url(), {{"force_key", "values"}});
  ASSERT_TRUE(d->open().ok());
  ASSERT_TRUE(d->enable_force(true).ok());
  for (int i = 0; i < 50; ++i, sleep_s(1e-3)) d->write_force(Vec3(0.5, 0, 0));
  const auto log = svc.forces();
  ASSERT_TRUE(log.back().applied);
  EXPECT_EQ(log.back().connection, 2);
  EXPECT_EQ(log.back().force_n, Vec3(0.5, 0, 0));
}

// Each fault: read() fails within a few timeouts; where the socket is still open the last command
// the service got is a zero force.
TEST(Inverse3Device, LinkFaultsFailReadAndEndWithZeroForce) {
  for (FakeFault fault : {FakeFault::kStopReplying, FakeFault::kMalformed, FakeFault::kClose}) {
    FakeInverseOptions o;
    o.fault = fault;
    o.fault_after_s = 0.3;
    FakeInverseService svc(o);
    auto d = make(svc.url(), {{"timeout_s", "0.2"}});
    ASSERT_TRUE(d->open().ok());
    ASSERT_TRUE(d->enable_force(true).ok());
    const auto t0 = std::chrono::steady_clock::now();
    double failed_at = -1;
    const char* reason = "";
    while (std::chrono::steady_clock::now() - t0 < std::chrono::seconds(2) && failed_at < 0) {
      d->write_force(Vec3(1, 0, 0));
      DeviceReading r;
      const Status s = d->read(0, r);
      if (!s.ok()) {
        failed_at = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        reason = s.reason;
      }
      sleep_s(1e-3);
    }
    ASSERT_GT(failed_at, 0.25) << "fault " << int(fault) << ": read() kept failing or never failed";
    sleep_s(0.2);
    const auto log = svc.forces();
    ASSERT_FALSE(log.empty());
    if (fault != FakeFault::kClose) {
      EXPECT_EQ(log.back().force_n, Vec3::Zero()) << "fault " << int(fault) << ": " << reason;
      EXPECT_TRUE(log.back().applied);
      EXPECT_GT(log[log.size() - 2].force_n.norm(), 0.9) << "a force was being rendered before";
    }
    const size_t n = log.size();
    d->close();
    EXPECT_EQ(svc.forces().size(), n) << "nothing is sent after the link is lost";
    EXPECT_FALSE(d->write_force(Vec3(1, 0, 0)).ok());
    EXPECT_FALSE(d->enable_force(true).ok());
  }
}

TEST(Inverse3Device, OpenSaysWhatIsWrong) {
  auto d = make("ws://127.0.0.1:" + std::to_string(free_port()));
  Status s = d->open();
  ASSERT_FALSE(s.ok());
  EXPECT_NE(std::string(s.reason).find("cannot connect to the Inverse Service"), std::string::npos) << s.reason;
  EXPECT_NE(std::string(s.reason).find("refused"), std::string::npos) << s.reason;

  FakeInverseService svc;
  d = make(svc.url(), {{"device_id", "0BAD"}});
  s = d->open();
  ASSERT_FALSE(s.ok());
  EXPECT_NE(std::string(s.reason).find("no Inverse3 with device_id=0BAD"), std::string::npos) << s.reason;
  EXPECT_NE(std::string(s.reason).find("049D"), std::string::npos) << s.reason;

  FakeInverseOptions o;
  o.no_inverse3 = true;
  FakeInverseService empty(o);
  d = make(empty.url());
  s = d->open();
  ASSERT_FALSE(s.ok());
  EXPECT_NE(std::string(s.reason).find("reports no Inverse3"), std::string::npos) << s.reason;

  for (const auto& kv : std::map<std::string, std::string>{
           {"url", "http://127.0.0.1:1"}, {"axes", "x,y"}, {"origin_m", "0,0"}, {"force_key", "vec"}, {"timeout_s", "0"}}) {
    DeviceConfig c;
    c.options[kv.first] = kv.second;
    EXPECT_THROW(make_device("inverse3", c), std::invalid_argument) << kv.first;
  }
}

}  // namespace
}  // namespace haptree::device
