// Energy drift of conservative 857-DOF protein-like runs (τ = 0), semi-implicit Euler against RK4.
// The numbers in the comments were measured with tools/stress_report --sections drift (and printed
// by these tests); docs/accuracy_and_stability.md has the 10⁵-step tables. Horizons stay ≤ 1 s:
// the falling tree is chaotic (largest real eigenvalue of the state Jacobian 8–60 /s), so later
// states depend on rounding, and the bounds below keep ≥ 5× headroom over the measured values.
// Tolerances: what is bounded is the integrators' truncation error of the energy,
// C·dtᵖ (p = 1 Euler, 4 RK4), not rounding, which is ≈ steps·ε ≈ 1e-13 of E here. A CPU's other
// rounding moves the (chaotic) trajectory, not the size of the energy error along it, so the
// constants C are taken from the measured runs (× 5 headroom) and the order tests bracket 2ᵖ
// (Euler 2 in (1.6, 2.6), RK4 16 in (10, 25)): these are not fits to round-off of one machine.
#include <gtest/gtest.h>

#include <cstdio>

#include "tests/stress/stress_scenes.hpp"

namespace haptree::stress {
namespace {

DriftResult run(const DriftScene& sc, Integrator method, double dt, double T) {
  DriftOptions o;
  o.method = method;
  o.blowup_J = 10 * sc.ke_bound;
  return energy_drift(*sc.model, sc.st0, dt, static_cast<int>(std::lround(T / dt)), o);
}

TEST(EnergyDrift, EulerIsFirstOrderOnTheFallingTree) {
  const DriftScene sc = drift_scene("fall");
  ASSERT_EQ(sc.model->nv, 857);
  const auto coarse = run(sc, Integrator::kSemiImplicitEuler, 1e-3, 0.25);
  const auto fine = run(sc, Integrator::kSemiImplicitEuler, 5e-4, 0.25);
  ASSERT_TRUE(coarse.survived);
  ASSERT_TRUE(fine.survived);
  EXPECT_GT(coarse.max_kinetic, 100.0);   // the run really moves (≈ 1.8e3 J measured)
  EXPECT_LE(coarse.rel_drift, 0.35);      // measured 0.222
  EXPECT_LE(fine.rel_drift, 0.18);        // measured 0.115
  // Semi-implicit Euler: halving dt halves the energy error (measured ratio 2.19).
  const double ratio = coarse.max_abs_drift / fine.max_abs_drift;
  EXPECT_GT(ratio, 1.6);
  EXPECT_LT(ratio, 2.6);
  std::printf("fall euler 0.25 s: rel %.4e (1 ms) %.4e (0.5 ms) ratio %.3f\n", coarse.rel_drift,
              fine.rel_drift, ratio);
}

TEST(EnergyDrift, Rk4IsFourthOrderOnTheFallingTree) {
  const DriftScene sc = drift_scene("fall");
  const auto coarse = run(sc, Integrator::kRk4, 2e-3, 0.25);
  const auto fine = run(sc, Integrator::kRk4, 1e-3, 0.25);
  ASSERT_TRUE(coarse.survived);
  ASSERT_TRUE(fine.survived);
  EXPECT_LE(coarse.rel_drift, 5e-6);   // measured 9.04e-7
  EXPECT_LE(fine.rel_drift, 3e-7);     // measured 5.66e-8 (Euler at the same dt: 0.222)
  const double ratio = coarse.max_abs_drift / fine.max_abs_drift;
  EXPECT_GT(ratio, 10.0);              // measured 16.0
  EXPECT_LT(ratio, 25.0);
  std::printf("fall rk4 0.25 s: rel %.4e (2 ms) %.4e (1 ms) ratio %.3f\n", coarse.rel_drift,
              fine.rel_drift, ratio);
}

// Over 1 s at dt = 1 ms semi-implicit Euler has already pumped in energy of the order of the
// kinetic energy (and blows up at ≈ 1.03 s); RK4 at the same dt keeps it to ≈ 3e-4 of it.
TEST(EnergyDrift, Rk4HoldsWhereEulerDivergesOnTheFallingTree) {
  const DriftScene sc = drift_scene("fall");
  EXPECT_GT(sc.ke_bound, 3.0e5);   // 3.1508e5 J: E0 minus the lowest possible potential
  EXPECT_LT(sc.ke_bound, 3.3e5);
  const auto euler = run(sc, Integrator::kSemiImplicitEuler, 1e-3, 1.0);
  const auto rk4 = run(sc, Integrator::kRk4, 1e-3, 1.0);
  ASSERT_TRUE(rk4.survived);
  EXPECT_LE(rk4.rel_drift, 3e-3);   // measured 2.95e-4
  EXPECT_TRUE(!euler.survived || euler.rel_drift > 0.3);   // measured rel 0.976, blow-up at 1.03 s
  std::printf("fall 1 s at 1 ms: euler rel %.4e survived %d; rk4 rel %.4e max KE %.4e J\n",
              euler.rel_drift, euler.survived, rk4.rel_drift, rk4.max_kinetic);
}

// The tumbling tree (no gravity, KE ≈ 22 J): a bounded conservative motion.
TEST(EnergyDrift, TumblingTreeBothIntegrators) {
  const DriftScene sc = drift_scene("tumble");
  EXPECT_NEAR(sc.ke_bound, 22.02, 0.01);   // = E0 = KE0
  const auto euler = run(sc, Integrator::kSemiImplicitEuler, 1e-2, 2.0);
  const auto rk4 = run(sc, Integrator::kRk4, 1e-2, 2.0);
  ASSERT_TRUE(euler.survived);
  ASSERT_TRUE(rk4.survived);
  EXPECT_LE(euler.rel_drift, 0.05);   // measured 3.40e-3
  EXPECT_LE(rk4.rel_drift, 1e-10);    // measured 2.95e-13
  std::printf("tumble 2 s at 10 ms: euler rel %.4e, rk4 rel %.4e\n", euler.rel_drift, rk4.rel_drift);
}

}  // namespace
}  // namespace haptree::stress
