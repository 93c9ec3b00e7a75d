/// @file
/// Time integrators on top of forward_dynamics: semi-implicit Euler (haptree::integrate), classical
/// fourth-order Runge–Kutta on (q, q̇), and an energy-monitored adaptive RK4 for conservative runs.
///
/// RK4 treats the configuration as the ODE q̇_config = G(q) q̇ in the coordinates q is stored in:
/// revolute/prismatic q' = q̇; spherical (and the rotation of a free joint) quaternion
/// q' = ½ q ⊗ (0, ω) with ω the body-frame angular velocity (the convention of integrate_joint);
/// free-joint translation p' = R(q) v. That ODE is smooth in R^nq, so the classical tableau keeps
/// order 4 (an exponential-map update q ⊗ exp(h ω̄) of mixed-stage rates would need the dexp⁻¹
/// correction to stay above order 2). Quaternions are renormalised after every stage and step, a
/// projection that keeps the order. All workspaces are sized once; a step allocates nothing.
#pragma once

#include <string>

#include "haptree/dca.hpp"

namespace haptree {

/// Time integrators of the joint state (see the file's description).
enum class Integrator { kSemiImplicitEuler, kRk4 };

const char* integrator_name(Integrator i);       ///< "euler", "rk4"
/// "euler" / "semi-implicit-euler" / "rk4"; throws std::invalid_argument naming the bad value.
Integrator parse_integrator(const std::string& name);

/// ẋ of the configuration: qdot_config (nq) from q (nq) and q̇ (nv), see the header comment.
void configuration_rate(const Model& model, const Eigen::VectorXd& q, const Eigen::VectorXd& qd,
                        Eigen::VectorXd& qdot_config) noexcept;
/// Unit-normalises every quaternion in q (spherical and free joints).
void normalize_quaternions(const Model& model, Eigen::VectorXd& q) noexcept;

/// Preallocated RK4 workspace: one scratch State (its τ and f_ext are copied from the stepped state
/// at every step, so they are held constant over the step) and the four stage derivatives.
struct Rk4Workspace {
  explicit Rk4Workspace(const Model& model);   ///< sized for `model`
  State stage;                           ///< the state at which a stage is evaluated
  Eigen::VectorXd q0;                    ///< configuration at the start of the step
  Eigen::VectorXd qd0;                   ///< joint rates at the start of the step
  Eigen::VectorXd kq[4];                 ///< configuration rates of the four stages (nq)
  Eigen::VectorXd kv[4];                 ///< accelerations of the four stages (nv)
};

/// One classical RK4 step of length dt with τ and f_ext of `state` held constant. Four calls of
/// forward_dynamics; `data` is left holding the dynamics of the last stage (call forward_dynamics
/// on the new state for its energies). state.t advances by dt.
void rk4_step(const Model& model, Data& data, State& state, double dt, Rk4Workspace& ws) noexcept;

/// One step of `method` (semi-implicit Euler: forward_dynamics + integrate; RK4: rk4_step).
void step(Integrator method, const Model& model, Data& data, State& state, double dt,
          Rk4Workspace& ws) noexcept;

/// Energy-monitored adaptive RK4 for conservative runs (τ, f_ext held constant). Each attempted
/// step is compared with two half steps (step doubling): the difference estimates the local error
/// of the result, which is the Richardson-extrapolated combination (fifth order). A step is taken
/// when the estimate is ≤ rel_tol·(1 + |state|) component-wise AND the total energy moved by no more
/// than energy_tol_rel · (KE + energy_floor) over it; otherwise the step is halved and retried.
/// After an accepted step h grows by at most 2× following the error estimate. advance() integrates
/// exactly `duration` seconds (the last step is shortened), never with a step below min_dt_s.
struct AdaptiveRk4Options {
  double dt_init_s = 1e-3;         ///< first step, s
  double min_dt_s = 1e-7;          ///< below this the step is taken anyway and counted in `forced`
  double max_dt_s = 1e-2;          ///< longest step, s
  double rel_tol = 1e-8;           ///< local error per step (scaled max norm)
  double energy_tol_rel = 1e-6;    ///< |ΔE| per step / (KE + energy_floor_J)
  double energy_floor_J = 1e-3;    ///< keeps the energy test meaningful at rest, J
};
/// Counts of an AdaptiveRk4 run.
struct AdaptiveRk4Stats {
  long accepted = 0;               ///< steps taken
  long rejected = 0;               ///< steps halved and retried
  long forced = 0;                 ///< steps taken at min_dt_s although the tests failed
  long dynamics_calls = 0;         ///< forward_dynamics calls
  double min_dt = 0;               ///< shortest accepted step
  double max_dt = 0;               ///< longest accepted step
  double last_dt = 0;              ///< suggested next step
};
/// The adaptive RK4 integrator described above, with its own Data.
class AdaptiveRk4 {
 public:
  AdaptiveRk4(const Model& model, const AdaptiveRk4Options& options = {});   ///< keeps a reference to `model`
  /// Integrates `state` forward by `duration` seconds. Returns false if the state went non-finite.
  bool advance(State& state, double duration) noexcept;
  const AdaptiveRk4Stats& stats() const { return stats_; }   ///< counts since construction
  /// Total energy (kinetic + gravitational) of `state` (uses the internal Data).
  double energy(const State& state) noexcept;

 private:
  const Model& m_;
  AdaptiveRk4Options o_;
  Data d_;
  Rk4Workspace ws_;
  State full_, half_;
  double h_;
  AdaptiveRk4Stats stats_;
};

}  // namespace haptree
