// Adaptive dynamics switching ε or the budget k at every step (smoke version of tools/adaptive_stress):
// 2000 steps on the 857-DOF protein-like tree under gravity, every step checked, oracle twice.
#include <gtest/gtest.h>

#include <cstdio>

#include "tests/stress/adaptive_switching.hpp"

namespace haptree::stress {
namespace {

TEST(AdaptiveSwitching, ProteinLike2000StepsEveryStepSwitches) {
  SwitchingOptions o;
  o.scene = "protein_like";
  o.steps = 2000;
  o.dt = 1e-3;
  o.schedule = "random";
  o.modes = "both";
  o.seed = 1;
  o.oracle_every = 1000;
  const SwitchingResult r = run_adaptive_switching(o);
  EXPECT_EQ(r.first_failure_step, -1) << r.failure;
  EXPECT_EQ(r.steps_done, 2000);
  EXPECT_EQ(r.selections, 2000);   // every step reselected
  EXPECT_GT(r.budget_steps, 800);
  EXPECT_GT(r.threshold_steps, 800);
  EXPECT_EQ(r.budget_violations, 0);
  EXPECT_EQ(r.threshold_violations, 0);
  EXPECT_EQ(r.nonfinite_steps, 0);
  EXPECT_EQ(r.singular_pivots, 0);
  EXPECT_EQ(r.nonfinite_qdd, 0);
  EXPECT_LE(r.min_active, 16);     // the schedule really spans small and large regions
  EXPECT_GE(r.max_active, 500);
  // Energy: locking only removes energy and the explicit step's gain over 2 s is first order in
  // dt; 0.01 × the largest possible gravity swing is a physical bound (measured 6.7e-4 × scale).
  EXPECT_LT(r.max_energy_gain, 0.01 * r.energy_scale);
  EXPECT_EQ(r.oracle_checks, 2);
  EXPECT_LE(r.worst_oracle_ratio, 1.0) << r.worst_oracle_err;   // err ≤ B (adaptive_switching.hpp)
  std::printf("[ switching ] oracle %.2e, err/B %.2e\n", r.worst_oracle_err, r.worst_oracle_ratio);
}

TEST(AdaptiveSwitching, CyclicBudgetOnlyChain) {
  SwitchingOptions o;
  o.scene = "chain";
  o.n = 256;
  o.steps = 1000;
  o.dt = 1e-3;
  o.schedule = "cyclic";
  o.modes = "budget";
  o.k_min = 4;
  o.k_max = 256;
  o.oracle_every = 500;
  const SwitchingResult r = run_adaptive_switching(o);
  EXPECT_EQ(r.first_failure_step, -1) << r.failure;
  EXPECT_EQ(r.selections, 1000);
  EXPECT_EQ(r.budget_violations, 0);
  EXPECT_EQ(r.singular_pivots, 0);
  EXPECT_LE(r.min_active, 4);
  EXPECT_EQ(r.max_active, 256);
  EXPECT_LT(r.max_energy_gain, 0.01 * r.energy_scale);
  EXPECT_EQ(r.oracle_checks, 2);
  EXPECT_LE(r.worst_oracle_ratio, 1.0) << r.worst_oracle_err;
  std::printf("[ switching ] oracle %.2e, err/B %.2e\n", r.worst_oracle_err, r.worst_oracle_ratio);
}

}  // namespace
}  // namespace haptree::stress
