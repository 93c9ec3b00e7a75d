// Quad-precision reference q̈. The long-double oracle's Cholesky has a forward error
// of order κ₂(H)·u_LD (u_LD = 2⁻⁶⁴ ≈ 5.4e-20): ~1e-12 for a 1024-link chain (κ₂ ≈ 3e9), the size
// of the errors it is asked to measure there. Here its answer is refined with the residual
// τ − ID(q, q̇, q̈) computed in __float128 (haptree/inverse_dynamics.hpp, 113-bit significand) and
// the oracle's own H as the solver: the fixed point depends only on the quad residual, and each
// step multiplies the error by ≈ κ₂(H)·u_LD, so two steps leave the double rounding of the result.
#pragma once

#include "tests/support/oracle.hpp"

namespace haptree::testing {

struct QuadReference {
  Eigen::VectorXd qdd;          // the refined q̈, rounded to double
  double oracle_rel_change = 0;   // ‖q̈ − q̈_oracle‖ / ‖q̈‖: the long-double oracle's own error
  double last_rel_step = 0;       // ‖δ‖ / ‖q̈‖ of the last step (convergence)
};

QuadReference quad_reference(const Model& model, const State& state, const OracleResult& oracle,
                             int steps = 3);

// r = τ − ID(q, q̇, x) in __float128 (rounded to long double), for checks against the oracle's
// τ − C − H x.
VecXL quad_residual(const Model& model, const State& state, const VecXL& x);

}  // namespace haptree::testing
