// A 65 536-body chain: finite q̈, no singular pivots, and the same q̈ when the chain is shifted to
// another origin (the O(n^3) oracle cannot run at this size).
#include <gtest/gtest.h>

#include "tests/stress/stress_scenes.hpp"

namespace haptree::stress {
namespace {

TEST(LongChain, Chain65536FiniteAndShiftInvariant) {
  const int n = 65536;
  auto m = scene_at("chain", n, Vec3::Zero());
  const State st = clean_state(*m, 13);
  const auto a = dca(*m, st);
  ASSERT_EQ(a.qdd.size(), n);
  ASSERT_TRUE(all_finite(a.qdd));
  EXPECT_EQ(a.singular_pivots, 0);
  EXPECT_EQ(a.nonfinite, 0);
  auto shifted = scene_at("chain", n, Vec3(1e3, -2e3, 5e2));
  const auto b = dca(*shifted, st);
  ASSERT_TRUE(all_finite(b.qdd));
  // A translation changes no number the DCA uses (offsets are local): bit-identical but for
  // reordered sums (1e-14).
  EXPECT_LE(testing::rel_err(b.qdd, a.qdd), 1e-14);
  // A second evaluation of the same model is bit-identical (no hidden state in Data).
  EXPECT_EQ(dca(*m, st).qdd, a.qdd);
}

}  // namespace
}  // namespace haptree::stress
