// After set-up, a molecular step (kinematics, force field incl. neighbour-list rebuilds and rigid
// regions, DCA, integration) allocates nothing: count every operator new in this binary.
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <cstdlib>
#include <new>

#include "haptree/dca.hpp"
#include "haptree/molecule/scene.hpp"

#include "tests/support/count_allocations.hpp"


namespace haptree {
namespace {

TEST(MoleculeAllocation, ForceFieldAndStepAllocateNothing) {
  for (const char* name : {"ala20", "polyaniline", "bacteriorhodopsin"}) {
    mol::MolecularScene sc = mol::load_molecular_scene(name);
    const Model& m = *sc.model;
    State st(m);
    Data d(m);
    std::vector<int> region(m.nbodies);
    for (int b = 0; b < m.nbodies; ++b) region[b] = b / 4;
    forward_kinematics(m, d, st.q);
    sc.compute(d, st.f_ext);   // warm-up
    const long before = haptree::testing::allocation_count();
    const int rebuilds0 = sc.force_field->neighbour_rebuilds();
    for (int i = 0; i < 6; ++i) {
      // Small torsion moves (no clashes) that still move far atoms beyond skin/2: list rebuilds.
      for (int k = 0; k < st.q.size(); ++k) st.q(k) += 0.003 * std::sin(k + i);
      forward_kinematics(m, d, st.q);
      const double E = sc.compute(d, st.f_ext);
      EXPECT_TRUE(std::isfinite(E)) << name << " step " << i;
      if (i == 2) sc.force_field->set_rigid_regions(region);
      if (i == 4) sc.force_field->clear_rigid_regions();
      forward_dynamics(m, d, st);
      integrate(m, st.q, st.qd, d.qdd, 1e-5);
    }
    // Work follows motion: still steps, then one joint moving, then all: the groups are formed,
    // re-formed and dropped (regroups, list splits, group caches) without allocating.
    const int regroups0 = sc.force_field->regroups();
    for (int i = 0; i < 8; ++i) {
      if (i >= 3) st.q(st.q.size() / 2) += 1e-3;
      if (i >= 6) st.q.array() += 1e-5;
      forward_kinematics(m, d, st.q);
      EXPECT_TRUE(std::isfinite(sc.compute(d, st.f_ext))) << name << " motion step " << i;
    }
    EXPECT_GE(sc.force_field->regroups() - regroups0, 2) << name;
    EXPECT_TRUE(st.q.allFinite()) << name;
    EXPECT_EQ(haptree::testing::allocation_count() - before, 0) << name;
    EXPECT_GT(sc.force_field->neighbour_rebuilds(), rebuilds0) << name;
  }
}

}  // namespace
}  // namespace haptree
