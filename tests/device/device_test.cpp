// Tests for haptree/device: trajectory, scripted device, virtual hand, replay from an LCM log, registry,
// LCM conversions.
#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <unistd.h>

#include <cstdio>

#include "haptree/bus/wire.hpp"
#include "haptree/device/axes.hpp"
#include "haptree/device/buttons.hpp"
#include "haptree/device/convert.hpp"
#include "haptree/device/registry.hpp"
#include "haptree/device/replay.hpp"
#include "haptree/device/simulated.hpp"

namespace haptree::device {
namespace {

constexpr double kTol = 1e-12;

TEST(Trajectory, RejectsNonIncreasingTimes) {
  EXPECT_THROW(Trajectory({{0, Vec3::Zero(), 0}, {0, Vec3::Ones(), 0}}), std::invalid_argument);
}

TEST(ScriptedDevice, GrabPullReleaseSequence) {
  GrabPullRelease p;
  p.start_m = Vec3(0, 0, 0.05);
  p.grab_m = Vec3(0.01, 0, 0);
  p.pull_direction = Vec3(0, 2, 0);  // normalised to +y
  p.pull_distance_m = 0.04;
  ScriptedDevice dev(DeviceSpec{}, make_grab_pull_release(p));
  const double t_grab = p.approach_s, t_pull0 = t_grab + p.settle_s, t_pull1 = t_pull0 + p.pull_s,
               t_release = t_pull1 + p.hold_s;
  DeviceReading r;
  struct Expect {
    double t;
    Vec3 x;
    int32_t buttons;
  };
  const Vec3 pulled = p.grab_m + Vec3(0, 0.04, 0);
  const Expect expect[] = {
      {0.0, p.start_m, 0},
      {0.5 * t_grab, 0.5 * (p.start_m + p.grab_m), 0},  // approaching, button up
      {t_grab, p.grab_m, kButtonGrab},                  // grab
      {0.5 * (t_pull0 + t_pull1), 0.5 * (p.grab_m + pulled), kButtonGrab},
      {t_pull1 + 0.1, pulled, kButtonGrab},  // holding
      {t_release + 0.01, pulled, 0},         // released
      {100.0, pulled, 0},
  };
  int64_t seq = 0;
  for (const auto& e : expect) {
    ASSERT_TRUE(dev.read(e.t, r).ok());
    EXPECT_NEAR((r.position_m - e.x).norm(), 0, kTol) << "t = " << e.t;
    EXPECT_EQ(r.buttons, e.buttons) << "t = " << e.t;
    EXPECT_EQ(r.seq, ++seq);
  }
  ASSERT_TRUE(dev.read(0.5 * (t_pull0 + t_pull1), r).ok());
  EXPECT_NEAR((r.linear_velocity_mps - Vec3(0, 0.04 / p.pull_s, 0)).norm(), 0, kTol);
  EXPECT_TRUE(dev.write_force(Vec3(1, 2, 3)).ok());
  EXPECT_EQ(dev.last_force(), Vec3(1, 2, 3));
  EXPECT_EQ(dev.write_force(Vec3(NAN, 0, 0)).code, StatusCode::kError);
  EXPECT_EQ(dev.last_force(), Vec3(1, 2, 3));
}

Trajectory step_target(const Vec3& to) { return Trajectory({{0, Vec3::Zero(), 0}, {1e-3, to, kButtonGrab}}); }

TEST(VirtualHand, SpringConvergesToTargetAndToForceOffset) {
  VirtualHandParams p;  // m 0.2 kg, k 200 N/m, c 8 N s/m: damping ratio 0.63, decay time 0.05 s
  DeviceSpec spec;
  spec.max_force_n = 5;
  const Vec3 target(0.02, -0.01, 0.03);
  VirtualHand hand(spec, p, step_target(target));
  DeviceReading r;
  for (int k = 0; k <= 2000; ++k) ASSERT_TRUE(hand.read(k * 1e-3, r).ok());  // 2 s at 1 kHz
  EXPECT_NEAR((r.position_m - target).norm(), 0, 1e-9);
  EXPECT_NEAR(r.linear_velocity_mps.norm(), 0, 1e-8);
  // A constant device force F moves the equilibrium by F / k.
  const Vec3 F(1.0, 0.5, -2.0);
  ASSERT_TRUE(hand.write_force(F).ok());
  for (int k = 2001; k <= 4000; ++k) ASSERT_TRUE(hand.read(k * 1e-3, r).ok());
  EXPECT_NEAR((r.position_m - (target + F / p.stiffness_n_per_m)).norm(), 0, 1e-9);
  // The device saturates at its spec.
  ASSERT_TRUE(hand.write_force(Vec3(100, 0, 0)).ok());
  EXPECT_NEAR(hand.applied_force().norm(), spec.max_force_n, kTol);
  EXPECT_EQ(hand.write_force(Vec3(0, INFINITY, 0)).code, StatusCode::kError);
}

// Closed loop at 1 kHz: the hand reaches into a virtual wall at x = 0.01 (stiffness 500 N/m, force computed
// from the sampled position, held for one period). Equilibrium: k (x_t − x) = k_w (x − x_w).
TEST(VirtualHand, ClosedLoopWithSampledWallSettles) {
  VirtualHandParams p;
  const double kw = 500, xw = 0.01, xt = 0.03;
  VirtualHand hand(DeviceSpec{}, p, step_target(Vec3(xt, 0, 0)));
  DeviceReading r;
  for (int k = 0; k <= 3000; ++k) {
    ASSERT_TRUE(hand.read(k * 1e-3, r).ok());
    const double pen = r.position_m.x() - xw;
    ASSERT_TRUE(hand.write_force(Vec3(pen > 0 ? -kw * pen : 0.0, 0, 0)).ok());
  }
  const double k = p.stiffness_n_per_m;
  EXPECT_NEAR(r.position_m.x(), (k * xt + kw * xw) / (k + kw), 1e-9);
  EXPECT_NEAR(r.linear_velocity_mps.norm(), 0, 1e-7);
}

TEST(Convert, DeviceStateAndFeedbackRoundTrip) {
  DeviceReading a;
  a.seq = 99;
  a.position_m = Vec3(0.1, 0.2, 0.3);
  a.orientation = Quat(Eigen::AngleAxisd(0.3, Vec3(1, 2, 3).normalized()));
  a.linear_velocity_mps = Vec3(-1, 0, 1);
  a.buttons = 3;
  lcmt_device_state m;
  to_lcmt(a, 4, 1500000, m);
  EXPECT_EQ(m.schema_version, lcmt_device_state::SCHEMA_VERSION);
  EXPECT_EQ(m.device_id, 4);
  DeviceReading b;
  from_lcmt(m, b);
  EXPECT_EQ(b.seq, 99);
  EXPECT_EQ(b.position_m, a.position_m);
  EXPECT_EQ(b.linear_velocity_mps, a.linear_velocity_mps);
  EXPECT_EQ(b.orientation.coeffs(), a.orientation.coeffs());
  EXPECT_EQ(b.buttons, 3);
  EXPECT_DOUBLE_EQ(b.time_s, 1.5);

  FeedbackCommand c;
  c.echo_device_seq = 99;
  c.snapshot_version = 1234;
  c.force_n = Vec3(1, -2, 3);
  c.torque_nm = Vec3(0.1, 0, 0);
  c.flags = lcmt_feedback::FLAG_CLAMPED;
  lcmt_feedback f;
  to_lcmt(c, 4, 7, 1, f);
  EXPECT_EQ(f.seq, 7);
  FeedbackCommand d;
  from_lcmt(f, d);
  EXPECT_EQ(d.echo_device_seq, 99);
  EXPECT_EQ(d.snapshot_version, 1234);
  EXPECT_EQ(d.force_n, c.force_n);
  EXPECT_EQ(d.torque_nm, c.torque_nm);
  EXPECT_EQ(d.flags, c.flags);
}

struct TempLog {
  std::string path = "/tmp/haptree_replay_test_" + std::to_string(::getpid()) + ".lcm";
  ~TempLog() { std::remove(path.c_str()); }
};

TEST(ReplayDevice, PlaysLoggedPosesOnItsChannel) {
  TempLog log;
  {
    lcm::LogFile out(log.path, "w");
    ASSERT_TRUE(out.good());
    auto write = [&](const std::string& ch, const std::vector<uint8_t>& b, int64_t t) {
      lcm::LogEvent ev{};
      ev.timestamp = t;
      ev.channel = ch;
      ev.datalen = static_cast<int32_t>(b.size());
      ev.data = const_cast<uint8_t*>(b.data());
      ASSERT_EQ(out.writeEvent(&ev), 0);
    };
    for (int i = 0; i < 10; ++i) {
      DeviceReading r;
      r.seq = i + 1;
      r.position_m = Vec3(0.001 * i, 0, 0);
      r.buttons = i >= 5 ? kButtonGrab : 0;
      lcmt_device_state m;
      to_lcmt(r, 0, 1000000 + 10000 * i, m);  // 10 ms apart
      std::vector<uint8_t> b(static_cast<size_t>(m.getEncodedSize()));
      m.encode(b.data(), 0, static_cast<int>(b.size()));
      write("HAPTREE_DEVICE_STATE_0", b, 5 + i);
      write("HAPTREE_DEVICE_STATE_1", b, 5 + i);  // another device: ignored
      if (i == 3) write("HAPTREE_DEVICE_STATE_0", {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13}, 5 + i);
    }
  }
  ReplayDevice dev(DeviceSpec{}, log.path, "HAPTREE_DEVICE_STATE_0");
  EXPECT_EQ(dev.size(), 10u);
  EXPECT_EQ(dev.rejected(), 1);
  EXPECT_NEAR(dev.duration(), 0.09, kTol);
  DeviceReading r;
  ASSERT_TRUE(dev.read(0.0, r).ok());
  EXPECT_EQ(r.position_m.x(), 0.0);
  ASSERT_TRUE(dev.read(0.035, r).ok());  // newest sample at or before 35 ms: #3
  EXPECT_NEAR(r.position_m.x(), 0.003, kTol);
  EXPECT_EQ(r.buttons, 0);
  ASSERT_TRUE(dev.read(0.05, r).ok());
  EXPECT_NEAR(r.position_m.x(), 0.005, kTol);
  EXPECT_EQ(r.buttons, kButtonGrab);
  ASSERT_TRUE(dev.read(0.01, r).ok());  // time may go back (re-seek)
  EXPECT_NEAR(r.position_m.x(), 0.001, kTol);
  const Status end = dev.read(0.2, r);
  EXPECT_EQ(end.code, StatusCode::kDeactivate);
  EXPECT_NEAR(r.position_m.x(), 0.009, kTol);

  ReplayDevice looping(DeviceSpec{}, log.path, "HAPTREE_DEVICE_STATE_0", true);
  ASSERT_TRUE(looping.read(0.09 + 0.035, r).ok());
  EXPECT_NEAR(r.position_m.x(), 0.003, kTol);

  EXPECT_THROW(ReplayDevice(DeviceSpec{}, log.path, "NO_SUCH_CHANNEL"), std::runtime_error);
  EXPECT_THROW(ReplayDevice(DeviceSpec{}, "/nonexistent/x.lcm", "C"), std::runtime_error);
}

TEST(Registry, BuiltInsPlugInsAndErrors) {
  const auto names = device_names();
  for (const char* n : {"scripted", "virtual_hand", "replay"})
    EXPECT_NE(std::find(names.begin(), names.end(), n), names.end()) << n;
  DeviceConfig cfg;
  cfg.spec.name = "sim0";
  cfg.options = {{"grab_m", "0.01,0,0"}, {"pull_distance_m", "0.02"}, {"pull_direction", "0,0,1"}};
  auto dev = make_device("scripted", cfg);
  ASSERT_NE(dev, nullptr);
  EXPECT_EQ(dev->spec().name, "sim0");
  DeviceReading r;
  ASSERT_TRUE(dev->read(1000.0, r).ok());
  EXPECT_NEAR((r.position_m - Vec3(0.01, 0, 0.02)).norm(), 0, kTol);
  EXPECT_NE(make_device("virtual_hand", cfg), nullptr);

  try {
    make_device("phantom_omni", cfg);
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("virtual_hand"), std::string::npos) << e.what();
  }
  cfg.options["pull_s"] = "fast";
  EXPECT_THROW(make_device("scripted", cfg), std::invalid_argument);
  EXPECT_THROW(make_device("replay", DeviceConfig{}), std::invalid_argument);

  register_device("test_plugin", [](const DeviceConfig& c) -> std::unique_ptr<Device> {
    return std::make_unique<ScriptedDevice>(c.spec, Trajectory({{0, Vec3(1, 2, 3), 0}}));
  });
  EXPECT_THROW(register_device("test_plugin", [](const DeviceConfig&) { return std::unique_ptr<Device>(); }),
               std::invalid_argument);
  auto plug = make_device("test_plugin", DeviceConfig{});
  ASSERT_TRUE(plug->read(0.0, r).ok());
  EXPECT_EQ(r.position_m, Vec3(1, 2, 3));
  EXPECT_TRUE(unregister_device("test_plugin"));
  EXPECT_FALSE(unregister_device("test_plugin"));
  EXPECT_THROW(make_device("test_plugin", DeviceConfig{}), std::invalid_argument);
}


TEST(AxisMap, ParsesSignedPermutationsAndRefusesMirrorsAndTypos) {
  const AxisMap id = AxisMap::parse("x,y,z");
  EXPECT_TRUE(id.matrix().isIdentity());
  // Force Dimension (x towards the user, y right, z up) onto haptree (x right, y up, z towards the user).
  const AxisMap fd = AxisMap::parse("y,z,x");
  const Vec3 towards_user(1, 0, 0), right(0, 1, 0), up(0, 0, 1);
  EXPECT_TRUE(fd.to_frame(towards_user).isApprox(Vec3(0, 0, 1)));
  EXPECT_TRUE(fd.to_frame(right).isApprox(Vec3(1, 0, 0)));
  EXPECT_TRUE(fd.to_frame(up).isApprox(Vec3(0, 1, 0)));
  const Vec3 f(0.3, -1.2, 2.5);
  EXPECT_TRUE(fd.to_vendor(fd.to_frame(f)).isApprox(f));
  const AxisMap s = AxisMap::parse("-x,y,-z");
  EXPECT_TRUE(s.to_frame(Vec3(1, 2, 3)).isApprox(Vec3(-1, 2, -3)));
  EXPECT_EQ(s.str(), "-x,y,-z");
  // An orientation: a quarter turn about the vendor's up (z) is a quarter turn about haptree's up (y).
  const Mat3 Rz = Eigen::AngleAxisd(M_PI / 2, Vec3::UnitZ()).toRotationMatrix();
  EXPECT_TRUE(fd.to_frame(Rz).isApprox(Eigen::AngleAxisd(M_PI / 2, Vec3::UnitY()).toRotationMatrix()));
  for (const char* bad : {"x,y", "x,y,z,", "x,x,z", "x,y,w", "-x,y,z", "y,x,z", "", "x;y;z"})
    EXPECT_THROW(AxisMap::parse(bad), std::invalid_argument) << bad;
}

TEST(ButtonStage, ClutchFreezesTheProxyAndIndexesTheWorkspace) {
  ButtonStage b;
  DeviceReading r;
  auto step = [&](const Vec3& x, int32_t buttons) {
    r.position_m = x;
    r.linear_velocity_mps = Vec3(0.1, 0, 0);
    r.buttons = buttons;
    r.grab_seq = 0;
    b.apply(r);
    return r.position_m;
  };
  EXPECT_TRUE(step(Vec3(0.01, 0, 0), 0).isApprox(Vec3(0.01, 0, 0)));   // no clutch: the device position
  // Clutch held at x = 0.01, the hand moves back to -0.03: the proxy stays at 0.01, no velocity.
  EXPECT_TRUE(step(Vec3(0.01, 0, 0), kButtonClutch).isApprox(Vec3(0.01, 0, 0)));
  EXPECT_TRUE(step(Vec3(-0.03, 0.02, 0), kButtonClutch).isApprox(Vec3(0.01, 0, 0)));
  EXPECT_TRUE(r.linear_velocity_mps.isZero());
  EXPECT_TRUE(b.clutched());
  // Released: the proxy moves with the device again, from where it was (offset 0.04, -0.02, 0).
  EXPECT_TRUE(step(Vec3(-0.03, 0.02, 0), 0).isApprox(Vec3(0.01, 0, 0)));
  EXPECT_TRUE(step(Vec3(0.0, 0.02, 0), 0).isApprox(Vec3(0.04, 0, 0)));
  EXPECT_TRUE(r.linear_velocity_mps.isApprox(Vec3(0.1, 0, 0)));
  // A second indexing stroke adds up: proxy 0.04 held while the device goes back to 0 -> offset 0.04 more.
  step(Vec3(0.0, 0.02, 0), kButtonClutch);
  step(Vec3(-0.04, 0.02, 0), kButtonClutch);
  EXPECT_TRUE(step(Vec3(0.0, 0.02, 0), 0).isApprox(Vec3(0.08, 0, 0)));
  // Grab presses are counted (devices that count none), a device's own count is kept.
  EXPECT_EQ(b.presses(), 0);
  step(Vec3::Zero(), kButtonGrab);
  EXPECT_EQ(r.grab_seq, 1);
  step(Vec3::Zero(), kButtonGrab | kButtonClutch);   // grab held through a clutch stroke: same grab
  EXPECT_EQ(r.grab_seq, 1);
  step(Vec3::Zero(), 0);
  step(Vec3::Zero(), kButtonGrab);
  EXPECT_EQ(r.grab_seq, 2);
  r.position_m.setZero();
  r.buttons = kButtonGrab;
  r.grab_seq = 7;
  b.apply(r);
  EXPECT_EQ(r.grab_seq, 7);
}

}  // namespace
}  // namespace haptree::device
