// Tests for haptree/safety.cpp.
#include "haptree/safety.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>

namespace haptree {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

TEST(Safety, ClampNorm) {
  bool clamped = false;
  const Vec3 f(3, 4, 12);  // norm 13
  const Vec3 c = clamp_norm(f, 6.5, &clamped);
  EXPECT_TRUE(clamped);
  EXPECT_NEAR(c.norm(), 6.5, 1e-15);
  EXPECT_NEAR((c - 0.5 * f).norm(), 0, 1e-15);  // same direction
  EXPECT_EQ(clamp_norm(f, 13.5, &clamped), f);
  EXPECT_FALSE(clamped);
  EXPECT_EQ(clamp_norm(Vec3(kNaN, 0, 0), 10, &clamped), Vec3::Zero());
  EXPECT_TRUE(clamped);
  EXPECT_EQ(clamp_norm(Vec3(kInf, 0, 0), 10), Vec3::Zero());
  EXPECT_EQ(clamp_norm(f, kNaN), Vec3::Zero());
  // A finite vector whose squared norm overflows is clamped to the limit, not to zero.
  EXPECT_EQ(clamp_norm(Vec3(1e300, 0, 0), 3.0, &clamped), Vec3(3.0, 0, 0));
  EXPECT_TRUE(clamped);
  const Vec3 big = clamp_norm(Vec3(-1e300, 1e300, 0), 2.0);
  EXPECT_NEAR(big.norm(), 2.0, 1e-15);
  EXPECT_NEAR(big.x(), -std::sqrt(2.0), 1e-15);
  EXPECT_EQ(clamp_norm(f, -1), Vec3::Zero());
}

TEST(Safety, FiniteOrZero) {
  bool replaced = true;
  EXPECT_EQ(finite_or_zero(Vec3(1, 2, 3), &replaced), Vec3(1, 2, 3));
  EXPECT_FALSE(replaced);
  EXPECT_EQ(finite_or_zero(Vec3(1, -kInf, 3), &replaced), Vec3::Zero());
  EXPECT_TRUE(replaced);
  EXPECT_TRUE(all_finite(Vec6::Ones()));
  EXPECT_FALSE(all_finite(Vec3(0, kNaN, 0)));
}

// Simulated time: 10 kHz loop, inputs fresh until t_stop, stale until t_resume, fresh again.
TEST(Safety, WatchdogRampsDownWithinItsBudgetAndRecovers) {
  WatchdogParams p;
  p.stale_after_s = 0.004;
  p.ramp_down_s = 0.005;
  p.ramp_up_s = 0.050;
  Watchdog wd(p);
  const double dt = 1e-4, t_stop = 0.2, t_resume = 0.4;
  double last_input = 0, t_full = -1, t_zero = -1, t_back = -1, min_gain_fresh = 1;
  double prev_gain = 0, max_step_down = 0, max_step_up = 0;
  for (int k = 0; k <= 6000; ++k) {
    const double t = k * dt;
    const bool inputs_arrive = t < t_stop || t >= t_resume;
    if (inputs_arrive) last_input = t;
    const double g = wd.update(t, t - last_input);
    ASSERT_GE(g, 0.0);
    ASSERT_LE(g, 1.0);
    max_step_down = std::max(max_step_down, prev_gain - g);
    max_step_up = std::max(max_step_up, g - prev_gain);
    prev_gain = g;
    if (t_full < 0 && g == 1.0) t_full = t;
    if (t >= t_stop && t < t_stop + p.stale_after_s) min_gain_fresh = std::min(min_gain_fresh, g);
    if (t >= t_stop && t_zero < 0 && g == 0.0) t_zero = t;
    if (t >= t_resume && t_back < 0 && g == 1.0) t_back = t;
  }
  const double tol = 2 * dt;
  EXPECT_NEAR(t_full, p.ramp_up_s, tol);                       // initial ramp-in
  EXPECT_EQ(min_gain_fresh, 1.0);                               // not stale yet: full force
  EXPECT_LE(t_zero, t_stop + p.stale_after_s + p.ramp_down_s + tol);  // the budget
  EXPECT_GE(t_zero, t_stop + p.stale_after_s + p.ramp_down_s - tol);  // and linear, not a jump
  EXPECT_NEAR(t_back, t_resume + p.ramp_up_s, tol);
  EXPECT_NEAR(max_step_down, dt / p.ramp_down_s, 1e-12);       // linear ramps
  EXPECT_NEAR(max_step_up, dt / p.ramp_up_s, 1e-12);
  EXPECT_EQ(wd.trips(), 1);
  EXPECT_FALSE(wd.stale());
}

TEST(Safety, WatchdogTreatsNonFiniteAgeAsStale) {
  Watchdog wd;
  wd.update(0, 0);
  wd.update(1, 0);
  EXPECT_EQ(wd.gain(), 1.0);
  wd.update(1.0 + 1e-3, kNaN);
  EXPECT_TRUE(wd.stale());
  wd.update(2, -1);
  EXPECT_EQ(wd.gain(), 0.0);
}

TEST(Safety, ForceSafetyNeverPassesNonFiniteOrOverLimit) {
  ForceLimits lim;
  lim.max_force = 2.5;
  lim.max_torque = 0.1;
  WatchdogParams wp;
  wp.ramp_up_s = 0;  // full force as soon as fresh
  ForceSafety safety(lim, wp);
  std::mt19937 g(11);
  std::uniform_real_distribution<double> u(-100, 100);
  const double specials[] = {kNaN, kInf, -kInf, 1e308, -1e308, 0};
  int nonfinite_in = 0;
  for (int k = 0; k < 5000; ++k) {
    Vec3 f(u(g), u(g), u(g)), tau(u(g), u(g), u(g));
    if (k % 7 == 0) f[g() % 3] = specials[g() % 6];
    if (k % 11 == 0) tau[g() % 3] = specials[g() % 6];
    nonfinite_in += !(f.allFinite() && tau.allFinite());
    const GuardedForce out = safety.apply(k * 1e-4, 0.0, f, tau);
    ASSERT_TRUE(out.force.allFinite());
    ASSERT_TRUE(out.torque.allFinite());
    ASSERT_LE(out.force.norm(), lim.max_force * (1 + 1e-15));
    ASSERT_LE(out.torque.norm(), lim.max_torque * (1 + 1e-15));
    if (!(f.allFinite() && tau.allFinite())) {
      ASSERT_TRUE(out.flags & kSafetyNonFinite);
    }
  }
  EXPECT_EQ(safety.nonfinite_events(), nonfinite_in);
  EXPECT_GT(safety.clamp_events(), 0);
  // Within limits and fresh: passes unchanged.
  const GuardedForce ok = safety.apply(1.0, 0.0, Vec3(0.1, 0.2, 0.3), Vec3::Zero());
  EXPECT_EQ(ok.force, Vec3(0.1, 0.2, 0.3));
  EXPECT_EQ(ok.flags, 0);
  // Stale: flagged, and ramping.
  const GuardedForce st = safety.apply(1.001, 1.0, Vec3(0.1, 0.2, 0.3), Vec3::Zero());
  EXPECT_TRUE(st.flags & kSafetyStale);
  EXPECT_TRUE(st.flags & kSafetyWatchdog);
  EXPECT_LT(st.force.norm(), Vec3(0.1, 0.2, 0.3).norm());
}

// A pull far above the limit (30 N against a 3 N clamp, as a stiff spring stretched by a mouse) through a
// ramp-in, a stale spell and a recovery. What the device feels must follow the watchdog's linear ramps
// (|f| = gain x 3 N): with the gain applied before the clamp it reached 3 N at gain 0.1, i.e. after 10 ms
// of a 100 ms ramp-in, and the viewer's HUD showed "WATCHDOG" with |f| at the clamp.
TEST(Safety, ForceSafetyRampsTheClampedForceNotTheRawOne) {
  ForceLimits lim;
  lim.max_force = 3.0;
  WatchdogParams wp;
  wp.stale_after_s = 0.05;
  wp.ramp_down_s = 0.005;
  wp.ramp_up_s = 0.100;
  ForceSafety safety(lim, wp);
  const Vec3 raw(18.0, -24.0, 0.0);   // 30 N
  const double dt = 1e-4, t_stop = 0.3, t_resume = 0.5;
  double last_input = 0, t_full = -1, t_back = -1, prev = 0, max_up = 0, max_down = 0;
  int watchdog_at_clamp = 0;   // calls flagged WATCHDOG whose |f| the HUD shows as "3.000" (>= 2.9995 N)
  for (int k = 0; k <= 8000; ++k) {
    const double t = k * dt;
    if (t < t_stop || t >= t_resume) last_input = t;
    const GuardedForce g = safety.apply(t, t - last_input, raw, Vec3::Zero());
    const double fn = g.force.norm(), gain = safety.watchdog().gain();
    ASSERT_TRUE(g.flags & kSafetyClamped);
    // the direction is kept and the size is exactly gain x limit (a few ulps of 3)
    ASSERT_NEAR(fn, gain * lim.max_force, 1e-14);
    if (fn > 0) {
      ASSERT_NEAR(g.force.normalized().dot(raw.normalized()), 1.0, 1e-14);
    }
    if ((g.flags & kSafetyWatchdog) && fn >= 2.9995) ++watchdog_at_clamp;
    if (t_full < 0 && fn > lim.max_force - 1e-12) t_full = t;
    if (t >= t_resume && t_back < 0 && fn > lim.max_force - 1e-12) t_back = t;
    max_up = std::max(max_up, fn - prev);
    max_down = std::max(max_down, prev - fn);
    prev = fn;
  }
  const double tol = 2 * dt;
  EXPECT_NEAR(t_full, wp.ramp_up_s, tol);               // the whole ramp-in, not a tenth of it
  EXPECT_NEAR(t_back, t_resume + wp.ramp_up_s, tol);
  // A watchdog state shows the clamp only in the last step of a ramp-in (gain 1 - rounding; 2 ramp-ins
  // here), not for the last 90 % of each ramp-in as with the gain before the clamp (~1800 calls).
  EXPECT_LE(watchdog_at_clamp, 2);
  EXPECT_NEAR(max_up, lim.max_force * dt / wp.ramp_up_s, 1e-12);      // linear in the force felt
  EXPECT_NEAR(max_down, lim.max_force * dt / wp.ramp_down_s, 1e-12);
  EXPECT_EQ(safety.watchdog().trips(), 1);
}

// A port driven sinusoidally through a spring stores and returns energy (E back to ~0 over a period);
// through a damper it only absorbs (passive); through a negative damper it produces energy (active).
TEST(Safety, PassivityObserver) {
  const double w = 2 * M_PI, dt = 1e-5, k = 50, b = 3;
  PassivityObserver spring, damper, active;
  for (long i = 0; i < std::lround(1.0 / dt); ++i) {
    const double t = (i + 0.5) * dt;  // midpoint rule
    const Vec3 x(std::sin(w * t), 0, 0), v(w * std::cos(w * t), 0, 0);
    spring.add(k * x, v, dt);   // force on the element = k x: power k x v, E = k x²/2
    damper.add(b * v, v, dt);
    active.add(-b * v, v, dt);
  }
  EXPECT_NEAR(spring.energy(), 0.0, 1e-6);
  EXPECT_NEAR(spring.energy_in(), 2 * k / 2, 1e-3);  // two compressions of k*1²/2 per period
  EXPECT_NEAR(damper.energy(), b * w * w / 2, 1e-6);  // ∫ b v² over one period = b w² / 2
  EXPECT_TRUE(damper.passive());
  EXPECT_FALSE(active.passive());
  EXPECT_NEAR(active.energy(), -b * w * w / 2, 1e-6);
  EXPECT_LT(active.min_energy(), 0);
  const Vec3 v(1, 0, 0);
  EXPECT_NEAR(active.suggested_damping(v, 1e-3), b * w * w / 2 / 1e-3, 1e-3);
  EXPECT_EQ(damper.suggested_damping(v, 1e-3), 0.0);
  active.add(Vec3(kNaN, 0, 0), v, dt);
  EXPECT_EQ(active.ignored(), 1);
}


// When the coupling force is above the clamp (a deep pull), the watchdog ramp must still take
// the *felt* force to zero no faster than clamp / ramp_down_s. The gain used to be applied before the clamp:
// a raw 30 N under a 3 N clamp stayed at 3 N until the gain fell below 0.1 and then dropped to zero in 0.5 ms
// (600 N/s became 6000 N/s: a jerk at the hand), and it came back the same way after staleness.
TEST(Safety, WatchdogRampOfAClampedForceIsNoSteeperThanTheClampOverTheRamp) {
  ForceLimits lim;
  lim.max_force = 3.0;
  WatchdogParams wp;   // stale after 5 ms, down in 5 ms, up in 100 ms
  ForceSafety safety(lim, wp);
  const double dt = 1e-4;   // a 10 kHz coupler
  const Vec3 raw(30.0, 0, 0);
  Vec3 prev = Vec3::Zero();
  double max_step = 0, min_force = 1e9, max_force = 0;
  for (int k = 0; k < 4000; ++k) {   // 0.2 s fresh (ramp in), 0.1 s stale (ramp out), 0.1 s fresh again
    const double t = k * dt;
    const bool stale = k >= 2000 && k < 3000;
    const GuardedForce out = safety.apply(t, stale ? 1.0 : 0.0, raw, Vec3::Zero());
    if (k > 0) max_step = std::max(max_step, (out.force - prev).norm());
    if (k >= 2000 && k < 3000) min_force = std::min(min_force, out.force.norm());
    max_force = std::max(max_force, out.force.norm());
    prev = out.force;
  }
  // Per call the gain changes by at most dt / ramp_down_s (the faster ramp): the felt force by at most
  // max_force × dt / ramp_down_s = 0.06 N. Rounding: a few ulps of 3 N.
  const double bound = lim.max_force * dt / wp.ramp_down_s;
  std::printf("max step %.4f N per call (bound %.4f N), max |f| %.3f N, min while stale %.3f N\n", max_step, bound,
              max_force, min_force);
  EXPECT_LE(max_step, bound * (1 + 1e-9));
  EXPECT_NEAR(max_force, lim.max_force, 1e-15 * lim.max_force * 4);   // clamp_norm: v × (max / |v|), a few ulps
  EXPECT_EQ(min_force, 0.0);
}

}  // namespace
}  // namespace haptree
