// Models placed 1e3 m and 1e6 m from the origin: q̈ must equal the model at the origin. DCA never
// subtracts far positions (relative offsets come from local data), so the measured difference is
// exactly 0; the bound (1e-14) leaves room for nothing but reordered floating-point sums. The near
// model against the oracle: the error analysis' c·n·ε·κ(H)·cancel (tests/support/oracle.hpp).
// The random models of origin_independence_test.cpp cover every joint type, welds and URDF.
#include <gtest/gtest.h>

#include "tests/stress/stress_scenes.hpp"

namespace haptree::stress {
namespace {

struct FarCase {
  const char* scene;
  int n;
};

class FarOrigin : public ::testing::TestWithParam<FarCase> {};

TEST_P(FarOrigin, SameAccelerationsAsNearModel) {
  const auto c = GetParam();
  auto near = scene_at(c.scene, c.n, Vec3::Zero());
  const State st = clean_state(*near, 3);
  const auto qn = dca(*near, st);
  ASSERT_TRUE(all_finite(qn.qdd));
  // The near model itself is right (measured ≤ 8e-12 vs the long-double oracle).
  const auto orc = testing::oracle_forward_dynamics(*near, st);
  EXPECT_LE(testing::rel_err(qn.qdd, orc.qdd), testing::qdd_error_bound(orc, st, testing::kBoundC));
  for (double D : {1e3, 1e6}) {
    auto far = scene_at(c.scene, c.n, D * Vec3(1, 1, 1).normalized());
    const auto qf = dca(*far, st);
    ASSERT_TRUE(all_finite(qf.qdd)) << D;
    EXPECT_EQ(qf.singular_pivots, 0) << D;
    EXPECT_LE(testing::rel_err(qf.qdd, qn.qdd), 1e-14) << c.scene << " at " << D << " m";
  }
}

INSTANTIATE_TEST_SUITE_P(Scenes, FarOrigin,
                         ::testing::Values(FarCase{"chain", 64}, FarCase{"binary_tree", 63},
                                           FarCase{"protein_like", 857}),
                         [](const auto& info) { return std::string(info.param.scene); });

}  // namespace
}  // namespace haptree::stress
