// Protein-grade accuracy: full DCA on the bacteriorhodopsin torsion model against the
// long-double oracle, at the peer benchmark's state (crystal torsions, rates U(−1, 1) rad/ps) with
// the ff14SB force field applied as external body forces.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <limits>
#include <random>

#include "haptree/dca.hpp"
#include "haptree/molecule/scene.hpp"
#include "tests/support/oracle.hpp"
#include "tests/support/quad_reference.hpp"

namespace haptree {
namespace {

TEST(ProteinAccuracy, BacteriorhodopsinDcaMatchesOracle) {
  mol::MolecularScene sc = mol::load_molecular_scene("bacteriorhodopsin");
  const Model& m = *sc.model;
  State st(m);
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int i = 0; i < m.nv; ++i) st.qd(i) = u(rng);
  Data d(m);
  forward_kinematics(m, d, st.q);
  sc.compute(d, st.f_ext);
  set_refinement(m, d, Refinement::kOff);   // the single pass first; the default refines
  forward_dynamics(m, d, st);
  const Eigen::VectorXd plain = d.qdd;
  EXPECT_EQ(d.diag.singular_pivots, 0);
  const auto orc = testing::oracle_forward_dynamics(m, st);
  const double err = testing::rel_err(d.qdd, orc.qdd);
  // Tolerance from the error analysis: B = c·n·ε·κ(H)·cancel, the normwise backward-error bound
  // (tests/support/oracle.hpp; printed below), is far above 1e-12 for a 786-DOF protein. A
  // recursion without element growth has error ≈ c·n·ε (10·786·2.2e-16 = 1.7e-12). The
  // mobility-form join of the light Cα–H leaves had growth ~ r² (r ≈ 10³) and measured 4.8e-10;
  // the light-leaf form measures 8.4e-13 at this state (2.7e-12 = 1.6·c·n·ε at bench_peers' state, τ
  // from the force field; the rest: light bodies whose joint meets
  // another light side, still in mobility form). tol = 6·c·n·ε = 1.0e-11 leaves 4× for other
  // CPUs' operation orders. The plain pass does not reach 1e-12 here (Bullet, Simbody: 8e-14); the
  // refined q̈ below does.
  const double c_n_eps = testing::kBoundC * m.nv * std::numeric_limits<double>::epsilon();
  const double tol = std::min(6 * c_n_eps, testing::qdd_error_bound(orc, st, testing::kBoundC));
  std::printf("[bR] err %.3e, kappa(H) %.3e, bound B %.3e, tol %.3e\n", err,
              testing::mass_matrix_condition(orc), testing::qdd_error_bound(orc, st, testing::kBoundC),
              tol);
  EXPECT_LE(err, tol);

  // Data::refine (kDouble, the default): one refinement step with a backward-stable
  // residual (RNEA) removes the assembly's element growth, so the growth-free estimate c·n·ε = 1.7e-12 is the tolerance
  // (measured at bench_peers' state: 6.9e-14, docs/accuracy_and_stability.md).
  set_refinement(m, d, Refinement::kDouble);
  forward_dynamics(m, d, st);
  const double err_ref = testing::rel_err(d.qdd, orc.qdd);
  std::printf("[bR] refined err %.3e, tol %.3e\n", err_ref, std::min(c_n_eps, tol));
  EXPECT_LE(err_ref, std::min(c_n_eps, tol));

  // Refinement::kExtended (residual in long double from q) against the quad-precision reference:
  // one mixed-precision step leaves 2ε + B·e0 + B·2⁻¹¹ (tests/core/dca_test.cpp, DcaRefine), e0 the
  // plain pass's error; and the long-double oracle is inside its own bound (B with ε → 2⁻⁶⁴).
  const auto quad = testing::quad_reference(m, st, orc);
  const double B = testing::qdd_error_bound(orc, st, testing::kBoundC);
  set_refinement(m, d, Refinement::kExtended);
  forward_dynamics(m, d, st);
  const double err_x = testing::rel_err(d.qdd, quad.qdd);
  std::printf("[bR] vs quad reference: plain %.3e, extended %.3e (tol %.3e); oracle's own %.3e\n",
              testing::rel_err(plain, quad.qdd), err_x, 2 * testing::kEps + B * err + B * std::ldexp(1.0, -11),
              quad.oracle_rel_change);
  EXPECT_LE(err_x, 2 * testing::kEps + B * err + B * std::ldexp(1.0, -11));
  EXPECT_LE(quad.oracle_rel_change, B * std::ldexp(1.0, -11));
}

}  // namespace
}  // namespace haptree
