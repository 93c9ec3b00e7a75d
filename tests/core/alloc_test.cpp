// After set-up, a DCA step allocates nothing: count every operator new in this binary.
#include <gtest/gtest.h>

#include <atomic>
#include <cstdlib>
#include <new>

#include "haptree/adaptive.hpp"
#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"

#include "tests/support/count_allocations.hpp"

namespace haptree {
namespace {

TEST(Allocation, ForwardDynamicsAndIntegrationAllocateNothing) {
  for (const char* scene : {"chain", "random_tree", "protein_like", "star"}) {
    SceneOptions o;
    o.n = 300;
    o.seed = 2;
    o.mixed_joints = std::string(scene) == "random_tree" || std::string(scene) == "star";
    o.free_root = o.mixed_joints;
    if (std::string(scene) == "star") o.build.max_children = 4;   // inertia-form hub nodes
    auto model = make_scene(scene, o);
    State st(*model);
    // Data::refine: the refinement step's buffers too (kExtended's sized by set_refinement).
    for (Refinement refine : {Refinement::kOff, Refinement::kDouble, Refinement::kExtended}) {
      Data d(*model);
      set_refinement(*model, d, refine);
      forward_dynamics(*model, d, st);   // warm-up
      const long before = haptree::testing::allocation_count();
      for (int i = 0; i < 5; ++i) {
        forward_dynamics(*model, d, st);
        integrate(*model, st.q, st.qd, d.qdd, 1e-3);
      }
      EXPECT_EQ(haptree::testing::allocation_count() - before, 0) << scene << " refine " << int(refine);
    }
  }
}

TEST(Allocation, HybridStepWithoutReselectionAllocatesNothing) {
  auto model = make_protein_like({});
  State st(*model);
  Data d(*model);
  AdaptiveData ad(*model);
  AdaptiveOptions opt;
  opt.budget = 48;
  opt.reselect_every = 1000;
  adaptive_step(*model, d, st, ad, opt, 1e-3);   // selection (O(n), allowed to allocate)
  const long before = haptree::testing::allocation_count();
  for (int i = 0; i < 20; ++i) adaptive_step(*model, d, st, ad, opt, 1e-3);
  EXPECT_EQ(haptree::testing::allocation_count() - before, 0);
  EXPECT_FALSE(ad.report.reselected);
}

TEST(Allocation, SelectionAllocatesNothing) {
  // Reselection may now come at any step (error-controlled interval): it must not allocate either.
  auto model = make_protein_like({});
  State st(*model);
  Data d(*model);
  AdaptiveData ad(*model);
  AdaptiveOptions opt;
  opt.budget = 48;
  opt.reselect_every = 1;   // select at every step
  opt.background_selection = false;
  adaptive_step(*model, d, st, ad, opt, 1e-3);
  const long before = haptree::testing::allocation_count();
  for (int i = 0; i < 5; ++i) adaptive_step(*model, d, st, ad, opt, 1e-3);
  EXPECT_EQ(haptree::testing::allocation_count() - before, 0);
  EXPECT_TRUE(ad.report.reselected);
  EXPECT_EQ(ad.report.selections, 6);
}

TEST(Allocation, BackgroundSelectionAndHandoverAllocateNothing) {
  // The worker starts with the first selection; after that neither the steps that ask for a
  // selection, nor the worker, nor the steps that install its region allocate.
  auto model = make_protein_like({});
  State st(*model);
  Data d(*model);
  AdaptiveData ad(*model);
  AdaptiveOptions opt;
  opt.budget = 48;
  opt.reselect_every = 3;
  ASSERT_TRUE(opt.background_selection);
  st.f_ext[model->nbodies - 1](4) = 1.0;
  adaptive_step(*model, d, st, ad, opt, 1e-3);
  const long before = haptree::testing::allocation_count();
  const std::int64_t selections = ad.report.selections;
  for (int i = 0; i < 30; ++i) {
    adaptive_selection_wait(ad);
    adaptive_step(*model, d, st, ad, opt, 1e-3);
  }
  EXPECT_EQ(haptree::testing::allocation_count() - before, 0);
  EXPECT_GE(ad.report.selections - selections, 5);
}

}  // namespace
}  // namespace haptree
