#include <gtest/gtest.h>

#include <cmath>

#include "haptree/scenes.hpp"

namespace haptree {
namespace {

TEST(AssemblyTree, ChainDepthIsLogarithmicAndHandlesAtMostTwo) {
  for (int n : {1, 2, 3, 7, 16, 100, 1024, 65536}) {
    SceneOptions o;
    o.n = n;
    auto m = make_chain(o);
    const auto& t = m->tree;
    EXPECT_EQ(t.nnodes(), 2 * (n + 1) - 1);
    EXPECT_EQ(t.max_depth, static_cast<int>(std::ceil(std::log2(n + 1)))) << n;
    EXPECT_LE(t.max_handles, 2);
  }
}

TEST(AssemblyTree, PreOrderAndJointOwnersOnUpRegion) {
  SceneOptions o;
  o.n = 500;
  o.seed = 3;
  auto m = make_random_tree(o);
  const auto& t = m->tree;
  ASSERT_EQ(t.roots.size(), 1u);
  EXPECT_EQ(t.handle_num[t.roots[0]], 0);
  for (int node = 1; node < t.nnodes(); ++node) EXPECT_LT(t.up[node], node);
  for (int k = 0; k < m->nbodies; ++k) {
    const auto region = t.up_region(t.leaf_of_body[k]);
    // Every joint incident to body k is owned by a node of k's up-region (docs/algorithms.md §4.5).
    std::vector<int> joints;
    if (k > 0) joints.push_back(k);
    for (int c : m->children[k]) joints.push_back(c);
    for (int J : joints)
      EXPECT_NE(std::find(region.begin(), region.end(), t.owner_of_joint[J]), region.end());
  }
  EXPECT_LE(t.max_depth, 2 * std::log2(m->nbodies));
}

TEST(AssemblyTree, DegreeReductionMakesStarsLogarithmic) {
  SceneOptions o;
  o.n = 256;
  auto plain = make_star(o);
  EXPECT_GE(plain->tree.max_depth, 200);
  o.build.max_children = 2;
  auto reduced = make_star(o);
  EXPECT_LE(reduced->tree.max_depth, 2 * std::log2(reduced->nbodies));
  EXPECT_EQ(plain->nv, reduced->nv);
}

}  // namespace
}  // namespace haptree
