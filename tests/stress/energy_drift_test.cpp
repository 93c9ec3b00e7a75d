// Energy drift of the conservative 857-DOF protein-like run (gravity on, τ = 0) with semi-implicit
// Euler, released from rest, over a 0.25 s horizon. Measured (tools/stress_report --sections drift):
// rel = max|E−E0| / max KE = 0.222 (dt 1e-3), 0.115 (5e-4), 0.0585 (2.5e-4): first order in dt.
#include <gtest/gtest.h>

#include "tests/stress/stress_scenes.hpp"

namespace haptree::stress {
namespace {

TEST(EnergyDrift, ProteinLikeBoundedAndFirstOrder) {
  SceneOptions o;
  auto m = make_protein_like(o);
  ASSERT_EQ(m->nv, 857);
  const State st0 = clean_state(*m, 11, 0.0);
  const auto coarse = energy_drift(*m, st0, 1e-3, 250);
  const auto fine = energy_drift(*m, st0, 5e-4, 500);
  ASSERT_TRUE(coarse.finite);
  ASSERT_TRUE(fine.finite);
  EXPECT_GT(coarse.max_kinetic, 100.0);   // the run really moves (≈ 2.3e3 J measured)
  EXPECT_LE(coarse.rel_drift, 0.35);      // measured 0.222
  EXPECT_LE(fine.rel_drift, 0.18);        // measured 0.115
  // Semi-implicit Euler: halving dt halves the energy error (measured ratio 2.19).
  const double ratio = coarse.max_abs_drift / fine.max_abs_drift;
  EXPECT_GT(ratio, 1.6);
  EXPECT_LT(ratio, 2.6);
}

}  // namespace
}  // namespace haptree::stress
