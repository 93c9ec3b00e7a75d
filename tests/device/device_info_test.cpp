// Device table and the start-up gain check (haptree/device/device_info.*).
#include <gtest/gtest.h>

#include <cmath>

#include "haptree/device/device_info.hpp"

using namespace haptree::device;

namespace {

// The coupler's defaults (CouplerOptions): K = 20 · 0.5 · 10 = 100 N/m at 10 kHz, 1 ms snapshots.
CouplingGains defaults() {
  CouplingGains g;
  g.stiffness = 20;
  g.damping = 0;
  g.position_scale = 10;
  g.force_scale = 0.5;
  g.max_force_n = 3;
  g.rate_hz = 10000;
  g.sim_dt_s = 1e-3;
  return g;
}

bool contains(const std::string& s, const std::string& part) { return s.find(part) != std::string::npos; }

}  // namespace

TEST(DeviceInfo, TableHoldsTheCited3dSystemsNovintAndForceDimensionNumbers) {
  struct Row { const char* name; double f, k, b, r; };
  // The values of CHAI3D 3.3 (src/devices/CPhantomDevices.cpp, CDeltaDevices.cpp).
  for (const Row& e : {Row{"touch", 3.3, 400, 4, 0.075}, Row{"phantom_omni", 3.3, 700, 5, 0.10},
                       Row{"falcon", 8, 3000, 20, 0.04}, Row{"delta.3", 20, 5000, 30, 0.15},
                       Row{"omega.3", 12, 5000, 30, 0.075}, Row{"sigma.7", 12, 4000, 30, 0.075}}) {
    const DeviceInfo* d = find_device_info(e.name);
    ASSERT_NE(d, nullptr) << e.name;
    EXPECT_EQ(d->max_force_n, e.f) << e.name;
    EXPECT_EQ(d->max_stiffness_n_per_m, e.k) << e.name;
    EXPECT_EQ(d->max_damping_n_s_per_m, e.b) << e.name;
    EXPECT_EQ(d->workspace_radius_m, e.r) << e.name;
    EXPECT_TRUE(contains(d->source, "chai3d/chai3d src/devices/")) << d->source;
    EXPECT_TRUE(std::isnan(d->physical_damping_n_s_per_m)) << e.name << ": no table gives b";
  }
  for (const auto& d : device_table()) {
    EXPECT_FALSE(d.source.empty()) << d.name;
    EXPECT_TRUE(d.max_force_n > 0 && d.max_stiffness_n_per_m > 0 && d.max_damping_n_s_per_m > 0) << d.name;
  }
  EXPECT_EQ(find_device_info("Touch"), find_device_info("touch"));
  EXPECT_EQ(find_device_info("no_such_device"), nullptr);
  EXPECT_TRUE(contains(device_model_names(), "simulated, touch"));
  EXPECT_EQ(to_device_spec(*find_device_info("falcon")).max_force_n, 8.0);
}

TEST(DeviceInfo, DefaultGainsPassOnTheDefaultSimulatedDevice) {
  const GainCheck c = check_gains(*find_device_info("simulated"), defaults());
  EXPECT_TRUE(c.ok()) << (c.problems.empty() ? "" : c.problems[0]);
  EXPECT_DOUBLE_EQ(c.stiffness_n_per_m, 100.0);
  // b = 8 N s/m: min(2·8·10⁴, 2·8/10⁻³) = 1.6e4 N/m.
  EXPECT_DOUBLE_EQ(c.passivity_bound_n_per_m, 16000.0);
}

TEST(DeviceInfo, RealDeviceNeedsThePhysicalDampingForThePassivityBound) {
  const DeviceInfo& touch = *find_device_info("touch");
  GainCheck c = check_gains(touch, defaults());
  ASSERT_EQ(c.problems.size(), 1u);
  EXPECT_TRUE(contains(c.problems[0], "--device-damping-n-s-per-m")) << c.problems[0];
  EXPECT_FALSE(c.clampable);
  CouplingGains g = defaults();
  g.physical_damping_n_s_per_m = 2;   // bound min(4e4, 4e3) = 4000 N/m > K = 100
  c = check_gains(touch, g);
  EXPECT_TRUE(c.ok());
  EXPECT_DOUBLE_EQ(c.passivity_bound_n_per_m, 4000.0);
}

TEST(DeviceInfo, StiffnessAboveTheDeviceLimitIsRefusedWithTheFactorAndClampedToIt) {
  CouplingGains g = defaults();
  g.stiffness = 100;   // K = 500 N/m on a Touch (400 N/m)
  g.physical_damping_n_s_per_m = 2;
  const GainCheck c = check_gains(*find_device_info("touch"), g);
  ASSERT_EQ(c.problems.size(), 1u);
  EXPECT_TRUE(contains(c.problems[0], "500 N/m exceeds 400 N/m by a factor 1.25")) << c.problems[0];
  EXPECT_TRUE(contains(c.problems[0], "CPhantomDevices.cpp")) << c.problems[0];
  EXPECT_TRUE(c.clampable);
  EXPECT_DOUBLE_EQ(c.clamped.stiffness, 80.0);
  EXPECT_TRUE(check_gains(*find_device_info("touch"), c.clamped).ok());
}

TEST(DeviceInfo, PassivityBoundNamesTheTermThatLimitsAndClampsK) {
  CouplingGains g = defaults();
  g.stiffness = 4000;   // K = 20000 N/m > 2·8/1e-3 = 16000 (2b/T = 1.6e5 is not the limit)
  GainCheck c = check_gains(*find_device_info("simulated"), g);
  ASSERT_EQ(c.problems.size(), 1u);
  EXPECT_TRUE(contains(c.problems[0], "2e+04 N/m exceeds 1.6e+04 N/m by a factor 1.25")) << c.problems[0];
  EXPECT_TRUE(contains(c.problems[0], "(the 2b/dt_sim term")) << c.problems[0];
  EXPECT_DOUBLE_EQ(device_stiffness_n_per_m(c.clamped), 16000.0);
  EXPECT_TRUE(check_gains(*find_device_info("simulated"), c.clamped).ok());
  // Snapshots as fast as the haptic loop: the 2b/T term limits (T = 1e-4 > dt_sim = 5e-5).
  g.sim_dt_s = 5e-5;
  g.stiffness = 40000;   // K = 2e5 > 1.6e5
  c = check_gains(*find_device_info("simulated"), g);
  ASSERT_EQ(c.problems.size(), 1u);
  EXPECT_TRUE(contains(c.problems[0], "(the 2b/T term")) << c.problems[0];
}

TEST(DeviceInfo, DampingAndForceClampAboveTheDeviceAreClampedTogether) {
  CouplingGains g = defaults();
  g.damping = 5;          // B = 25 N s/m on a Falcon (20)
  g.max_force_n = 10;     // > 8 N
  g.physical_damping_n_s_per_m = 1;
  const GainCheck c = check_gains(*find_device_info("falcon"), g);
  ASSERT_EQ(c.problems.size(), 2u);
  EXPECT_TRUE(contains(c.problems[0], "--max-force-n 10 N exceeds 8 N")) << c.problems[0];
  EXPECT_TRUE(contains(c.problems[1], "25 N s/m exceeds 20 N s/m")) << c.problems[1];
  EXPECT_DOUBLE_EQ(c.clamped.damping, 4.0);
  EXPECT_DOUBLE_EQ(c.clamped.max_force_n, 8.0);
  EXPECT_DOUBLE_EQ(c.clamped.stiffness, g.stiffness);   // K = 100 < 2000 and < 3000: untouched
  EXPECT_TRUE(check_gains(*find_device_info("falcon"), c.clamped).ok());
}

TEST(DeviceInfo, NonFiniteOrNonPositiveInputsAreRefusedNotClamped) {
  CouplingGains g = defaults();
  g.stiffness = std::nan("");
  g.force_scale = 0;
  const GainCheck c = check_gains(*find_device_info("simulated"), g);
  EXPECT_EQ(c.problems.size(), 2u);
  EXPECT_FALSE(c.clampable);
}

TEST(DeviceInfo, ClampedGainsPassForEveryDeviceOverASweep) {
  for (const auto& d : device_table())
    for (double k : {1.0, 50.0, 500.0, 5e4})
      for (double b : {0.0, 1.0, 10.0})
        for (double fs : {0.1, 1.0}) {
          CouplingGains g = defaults();
          g.stiffness = k;
          g.damping = b;
          g.force_scale = fs;
          g.max_force_n = 30;
          g.physical_damping_n_s_per_m = 3;
          const GainCheck c = check_gains(d, g);
          ASSERT_TRUE(c.clampable) << d.name;
          const GainCheck again = check_gains(d, c.clamped);
          EXPECT_TRUE(again.ok()) << d.name << " k " << k << ": " << (again.ok() ? "" : again.problems[0]);
          EXPECT_LE(c.clamped.stiffness, k);
          EXPECT_LE(c.clamped.damping, b);
        }
}

TEST(DeviceInfo, LimitsReportedByTheDeviceReplaceTheTableAndTheRestStays) {
  const DeviceInfo* touch = find_device_info("touch");
  ASSERT_NE(touch, nullptr);
  DeviceDescription r;
  r.model = "Touch (reported)";
  r.max_force_n = 2.5;            // below the table's 3.3 N
  r.max_stiffness_n_per_m = 300;  // below the table's 400 N/m
  const DeviceInfo m = with_reported_limits(*touch, r);
  EXPECT_EQ(m.max_force_n, 2.5);
  EXPECT_EQ(m.max_stiffness_n_per_m, 300);
  EXPECT_EQ(m.max_damping_n_s_per_m, touch->max_damping_n_s_per_m);   // not reported: the table's
  EXPECT_EQ(m.model, "Touch (reported)");
  EXPECT_TRUE(contains(m.source, "max force, max stiffness reported by the device")) << m.source;
  // The gain check now refuses what the table allowed: K = 350 N/m passes the table's 400, not the device's 300.
  CouplingGains g = defaults();
  g.stiffness = 70;               // K = 70 · 0.5 · 10 = 350 N/m
  g.max_force_n = 2.0;
  g.physical_damping_n_s_per_m = 10;
  EXPECT_TRUE(check_gains(*touch, g).ok());
  const GainCheck c = check_gains(m, g);
  ASSERT_EQ(c.problems.size(), 1u);
  EXPECT_TRUE(contains(c.problems[0], "exceeds 300 N/m")) << c.problems[0];
  // Nothing reported: the table entry unchanged.
  EXPECT_EQ(with_reported_limits(*touch, DeviceDescription{}).source, touch->source);
}
