// Independent O(n^3) forward-dynamics oracle for tests: composite-rigid-body mass matrix and
// recursive Newton–Euler bias, coordinates about body 1's joint point (world axes), Cholesky — all
// in long double. It shares only the Model's *description* with the DCA code (no kinematics, no
// spatial helpers).
#pragma once

#include <vector>

#include "haptree/data.hpp"

namespace haptree::testing {

using LD = long double;
using VecXL = Eigen::Matrix<LD, Eigen::Dynamic, 1>;
using MatXL = Eigen::Matrix<LD, Eigen::Dynamic, Eigen::Dynamic>;

struct OracleResult {
  Eigen::VectorXd qdd;
  MatXL H;                        // mass matrix
  VecXL C;                        // bias (velocity products, gravity, external forces): H q̈ = τ − C
  std::vector<Vec6> body_acc;     // spatial acceleration of each body at its origin r_k (world axes)
  std::vector<Vec3> r;            // body origins
};

// Forward dynamics. `locked` (optional, size nv): DOFs locked (q̈ = 0) — their rows/columns are
// removed from H; their q̇ still counts in the bias.
OracleResult oracle_forward_dynamics(const Model& model, const State& state,
                                     const std::vector<bool>& locked = {});

// Tolerances from error analysis instead of from one machine. q̈ solves H q̈ = τ − C;
// an algorithm whose result is the exact solution of a problem perturbed by c·n·ε relative to its
// data (backward stable, as the DCA/ABA recursions are) has a normwise relative forward error
//   ≤ c · n · ε · κ₂(H) · max(1, (‖τ‖ + ‖C‖) / ‖τ − C‖),
// κ₂(H) the mass matrix's condition number and the last factor the cancellation in the right-hand
// side. Both are computed by the oracle (free DOFs only when `locked` is given).
double mass_matrix_condition(const OracleResult& r, const std::vector<bool>& locked = {});
double qdd_error_bound(const OracleResult& r, const State& st, double c,
                       const std::vector<bool>& locked = {});
constexpr double kEps = 2.220446049250313e-16;   // double's machine epsilon
// The constant c used by the suite: the largest err/(n·ε·κ·cancel) measured over the random
// sweep of tests/stress/origin_independence_test.cpp is 0.4 (err/bound 0.04 with c = 10), so
// c = 10 leaves 25× for other CPUs' orderings (FMA, vector width), not for one machine's luck.
constexpr double kBoundC = 10;
// qdd_error_bound of (model, state) in one call (runs the oracle: O(n³), fine to ~1000 DOFs).
double dca_error_bound(const Model& model, const State& state, double c = kBoundC,
                       const std::vector<bool>& locked = {});

// Relative error ‖a − b‖ / max(‖b‖, floor).
double rel_err(const Eigen::VectorXd& a, const Eigen::VectorXd& b, double floor = 1e-12);

// Random state: angles in [-1, 1], velocities in [-1, 1], torques in [-1, 1], random unit
// quaternions, small random external forces.
State random_state(const Model& model, unsigned seed, double vel_scale = 1.0);

}  // namespace haptree::testing
