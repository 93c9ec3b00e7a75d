// Closed haptic loop in one process, for the passivity / stiff-coupling stress test
// (tests/stress/passivity_test.cpp) and the sweep tool (tools/passivity_sweep.cpp).
//
//   user's hand  : haptree::device::VirtualHand (mass, arm spring to a target trajectory, damping b),
//                  integrated with substeps << T, feels the force written to it (no clamp here).
//   coupler      : haptree::coupler_feedback (the coupler process's own pure function: mapping,
//                  VirtualCoupling3 f_u = k_s (x_h − x_s) + b_s (ẋ_h − ẋ_s), coupling_forces on the
//                  latest CouplingSnapshot), evaluated every haptic period T; the force is held (ZOH).
//   simulation   : the same step as sim_server (SimServer::step_once + publish_snapshots): selection
//                  with the grabbed leaf's root path forced active, the latest f_u applied at the grab
//                  point, adaptive_step, update_all_body_poses, make_grab, make_coupling_snapshot, at
//                  its own period dt_sim (an integer multiple of T).
// Every run is deterministic (no threads, no clocks).
#pragma once

#include <algorithm>
#include <cmath>
#include <functional>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Eigenvalues>

#include "coupler/coupler.hpp"
#include "haptree/adaptive.hpp"
#include "haptree/coupling.hpp"
#include "haptree/dca.hpp"
#include "haptree/device/simulated.hpp"
#include "haptree/safety.hpp"
#include "haptree/scenes.hpp"

namespace haptree::stress {

struct CouplingLoopOptions {
  std::string scene = "wall";      // wall (grab on a revolute axis: f_feed = −f_u), chain, protein_like
  int n = 8;                       // bodies of chain / protein_like
  int grab_body = -1;              // -1: the last body (the launcher's pick for one user)
  bool gravity = false;
  int budget_dofs = 0;             // adaptive budget; 0: every DOF active
  int reselect_every = 10;
  double k_s = 100;                // coupling stiffness, scene units
  double b_s = 0;                  // coupling damping, scene units
  double position_scale = 1;       // scene length per device metre
  double force_scale = 1;          // N per scene force unit
  bool scripted_device = false;    // true: the hand follows its target exactly (launcher's ScriptedDevice)
  double hand_mass_kg = 0.2;
  double hand_stiffness_n_per_m = 200;
  double hand_damping_n_s_per_m = 8;   // b
  int hand_substeps = 20;          // hand integration substeps per haptic period
  double T = 1e-4;                 // haptic period, s
  double dt_sim = 1e-3;            // simulation step, s (rounded to a multiple of T)
  Vec3 pull_direction = Vec3::Zero();   // zero: x for "wall", else the grab point's most mobile
                                        // direction (largest eigenvalue of Λ⁻¹; a straight chain
                                        // pulled along itself would be anchored like the wall)
  double pull_distance_m = 0.01;
  double pull_s = 0.05;
  double hold_s = 0.4;
  double diverge_force_n = 1e6;    // stop early (unstable) above this device force
  bool growth_check = true;        // false: unstable only when diverged or non-finite
  // Optional, every tick: time, device force (N), f_u (scene), snapshot grab point and velocity.
  std::function<void(double, const Vec3&, const Vec6&, const Grab&)> trace;
};

struct CouplingLoopResult {
  bool finite = true;
  bool diverged = false;           // force or displacement ran past the caps
  bool stable = true;              // finite, not diverged, oscillation not growing
  double growth = 0;               // loop KE, max over the last 0.1 s / max over the first hold window
  double max_force_n = 0;          // max |device force|
  double max_fu = 0;               // max |f_u|, scene units
  double max_grab_disp = 0;        // max |x_s − x_s(0)|, scene units
  double env_min_energy = 0;       // passivity observer at the device port (energy into coupling + sim)
  double env_final_energy = 0;
  double damped_min_energy = 0;    // same, plus the energy the hand's damper b dissipated
  double final_time = 0;
  long long sim_steps = 0, ticks = 0;
  long long singular_pivots = 0;
  int coupling_errors = 0;         // coupling_forces returned != kOk
  double m_eff_min = 0;            // smallest effective mass at the grab point (1/λmax Λ⁻¹), scene units
};

// The model of a loop scene (gravity as requested).
inline std::shared_ptr<const Model> coupling_loop_model(const CouplingLoopOptions& o) {
  SceneOptions so;
  so.n = o.scene == "wall" ? 1 : o.n;
  const std::string name = o.scene == "wall" ? "chain" : o.scene;
  auto m = std::make_shared<Model>(*make_scene(name, so));
  if (!o.gravity) m->gravity = Vec3::Zero();
  return m;
}

// Linear (3×3) inverse operational-space inertia Λ⁻¹ at a body point, at rest: ẍ = Λ⁻¹ f for a force f
// at that point (velocity-free, gravity cancels in the difference). Columns from three DCA passes.
inline Mat3 point_mobility(const Model& m, const Eigen::VectorXd& q, int body, const Vec3& local) {
  Data d(m);
  State s(m);
  s.q = q;
  s.qd.setZero();
  forward_dynamics(m, d, s);
  const Eigen::VectorXd a0 = d.qdd;
  const Vec3 arm = d.R[body] * local;
  Mat3 L;
  for (int c = 0; c < 3; ++c) {
    State sf = s;
    Vec6 f = Vec6::Zero();
    f.tail<3>() = Vec3::Unit(c);
    f.head<3>() = arm.cross(f.tail<3>());   // unit force at the point, moved to r_k
    sf.f_ext[body] += f;
    forward_dynamics(m, d, sf);
    State sv = s;
    sv.qd = d.qdd - a0;   // the point's velocity is linear in q̇: J (q̈_f − q̈_0) = Λ⁻¹ e_c
    forward_dynamics(m, d, sv);
    L.col(c) = make_grab(d, body, local).velocity;
  }
  return L;
}

inline double min_effective_mass(const Mat3& mobility, Vec3* direction = nullptr) {
  const Eigen::SelfAdjointEigenSolver<Mat3> es(0.5 * (mobility + mobility.transpose()));
  const double lmax = es.eigenvalues()(2);   // ascending
  if (direction) *direction = es.eigenvectors().col(2);
  return lmax > 0 ? 1.0 / lmax : std::numeric_limits<double>::infinity();
}

inline CouplingLoopResult run_coupling_loop(const CouplingLoopOptions& o,
                                            std::shared_ptr<const Model> model = nullptr) {
  if (!model) model = coupling_loop_model(o);
  const Model& m = *model;
  CouplingLoopResult res;
  Data d(m);
  State st(m);
  AdaptiveData ad(m);
  AdaptiveOptions aopt;
  aopt.mode = AdaptiveOptions::Mode::kBudget;
  aopt.budget = o.budget_dofs > 0 ? o.budget_dofs : m.nv;
  aopt.reselect_every = std::numeric_limits<int>::max();   // we reselect, like sim_server
  const int body = o.grab_body > 0 ? o.grab_body : m.nbodies - 1;
  forward_kinematics(m, d, st.q);
  // Grab point: the body origin (for "wall": on the revolute axis, so the point cannot move).
  const Vec3 local = Vec3::Zero();
  Vec3 mobile_dir;
  res.m_eff_min = min_effective_mass(point_mobility(m, st.q, body, local), &mobile_dir);
  Vec3 pull_dir = o.pull_direction;
  if (pull_dir.norm() == 0) pull_dir = o.scene == "wall" ? Vec3::UnitX() : mobile_dir;
  pull_dir.normalize();
  const Vec3 x_s0 = d.r[body];

  // Coupler configuration (the coupler process's options and pure function).
  CouplerOptions co;
  co.stiffness = o.k_s;
  co.damping = o.b_s;
  co.position_scale = o.position_scale;
  co.force_scale = o.force_scale;
  // No clamp anywhere in this loop (it studies the stability limit): also none on the user force, whose
  // scene-side limit coupler_feedback derives from max_force_n.
  co.max_force_n = std::numeric_limits<double>::infinity();
  const Vec3 grab_m(0.0, 0.0, 0.01);
  co.offset = x_s0 - o.position_scale * grab_m;   // the device's start point maps onto x_s0

  // The hand's target: still at the grab point, pull, hold.
  const double t_pull0 = 0.01;
  std::vector<device::Waypoint> wp{{0.0, grab_m, device::kButtonGrab},
                                   {t_pull0, grab_m, device::kButtonGrab},
                                   {t_pull0 + o.pull_s,
                                    grab_m + o.pull_distance_m * pull_dir,
                                    device::kButtonGrab}};
  device::Trajectory target(wp);
  device::DeviceSpec spec;
  spec.max_force_n = std::numeric_limits<double>::infinity();
  device::VirtualHandParams hp;
  hp.mass_kg = o.hand_mass_kg;
  hp.stiffness_n_per_m = o.hand_stiffness_n_per_m;
  hp.damping_n_s_per_m = o.hand_damping_n_s_per_m;
  hp.max_substep_s = o.T / std::max(1, o.hand_substeps) * (1 + 1e-9);
  device::VirtualHand hand(spec, hp, target);

  // Simulation side.
  std::vector<char> mask;
  auto select = [&] {
    select_active_region(m, d, st, ad, aopt);
    mask = ad.active;
    for (int node = m.tree.up[m.tree.leaf_of_body[body]]; node >= 0; node = m.tree.up[node]) mask[node] = 1;
    set_active_region(m, d, st, ad, mask);
  };
  CouplingSnapshot snap;
  std::vector<Grab> grabs(1);
  std::vector<Vec6> fu_applied(1, Vec6::Zero());
  long long version = 0;
  const long long pivots0 = d.diag.singular_pivots;
  Data de(m);   // body kinetic + gravity potential energy of the simulation (loop-energy growth)
  double body_ke = 0;
  auto update_body_energy = [&] {
    forward_kinematics(m, de, st.q);
    body_dynamics_terms(m, de, st);
    body_ke = kinetic_energy(m, de);
  };
  auto sim_step = [&](const Vec6& f_u, bool advance) {
    if (ad.steps_since_selection >= std::max(1, o.reselect_every)) select();
    update_all_body_poses(m, d, ad);
    for (auto& f : st.f_ext) f.setZero();
    const Grab g = make_grab(d, body, local);
    Vec6 f0 = f_u;
    f0.head<3>() += (g.point - d.r[body]).cross(f_u.tail<3>());
    st.f_ext[body] += f0;
    if (advance) {
      adaptive_step(m, d, st, ad, aopt, o.dt_sim);
    } else {
      adaptive_forward_dynamics(m, d, st, ad);
    }
    update_all_body_poses(m, d, ad);
    grabs[0] = make_grab(d, body, local);
    fu_applied[0] = f_u;
    make_coupling_snapshot(m, d, grabs, fu_applied, ++version, st.t, snap);
    update_body_energy();
  };
  select();
  ad.steps_since_selection = 0;
  sim_step(Vec6::Zero(), false);
  CouplingWorkspace ws(snap);

  const int ratio = std::max(1, static_cast<int>(std::lround(o.dt_sim / o.T)));
  const double t_end = t_pull0 + o.pull_s + o.hold_s;
  const long long n_ticks = static_cast<long long>(std::ceil(t_end / o.T));
  // Kinetic-energy windows: first 0.1 s of the hold after 0.05 s, and the last 0.1 s. The loop's
  // kinetic energy is hand KE + simulated-body KE, in device J; in a settled hold it decays (hand
  // damping) or stays bounded (undamped internal motion of the body), in an unstable loop it grows.
  const double e_scale = o.force_scale / o.position_scale;
  const double wA0 = t_pull0 + o.pull_s + 0.05, wA1 = wA0 + 0.1, wB0 = t_end - 0.1;
  double ampA = 0, ampB = 0;
  PassivityObserver env, damped;
  device::DeviceReading rd;
  Vec6 f_u = Vec6::Zero(), f_feed = Vec6::Zero();
  for (long long i = 0; i < n_ticks; ++i) {
    const double t = static_cast<double>(i) * o.T;
    if (!hand.read(t, rd).ok()) {
      res.finite = false;
      break;
    }
    if (o.scripted_device) {
      rd.position_m = target.position(t);
      rd.linear_velocity_mps = target.velocity(t);
    }
    if (i > 0 && i % ratio == 0) {
      sim_step(f_u, true);
      ++res.sim_steps;
    }
    Vec3 F = Vec3::Zero();
    const CouplingStatus cs =
        coupler_feedback(co, snap, CouplingInputs{rd.position_m, rd.linear_velocity_mps}, ws, f_u, f_feed, F);
    if (cs != CouplingStatus::kOk) ++res.coupling_errors;
    if (!F.allFinite() || !f_u.allFinite() || cs == CouplingStatus::kNonFinite) {
      res.finite = false;
      break;
    }
    hand.write(o.scripted_device ? Vec3::Zero() : F, Vec3::Zero());
    if (o.trace) o.trace(t, F, f_u, snap.grabs[0]);
    // Exact energy into the ZOH environment over this period: −F · (x(t+T) − x(t)).
    const Vec3 x0 = rd.position_m;
    device::DeviceReading rn;
    if (!hand.read(t + o.T, rn).ok()) {
      res.finite = false;
      break;
    }
    if (o.scripted_device) rn.position_m = target.position(t + o.T);
    const Vec3 dx = rn.position_m - x0;
    env.add_power(-F.dot(dx) / o.T, o.T);
    const Vec3 vrel = dx / o.T - target.velocity(t + 0.5 * o.T);
    damped.add_power(-F.dot(dx) / o.T + (o.scripted_device ? 0.0 : o.hand_damping_n_s_per_m * vrel.squaredNorm()),
                     o.T);
    res.max_force_n = std::max(res.max_force_n, F.norm());
    res.max_fu = std::max(res.max_fu, f_u.tail<3>().norm());
    res.max_grab_disp = std::max(res.max_grab_disp, (snap.grabs[0].point - x_s0).norm());
    {
      const double e_loop =
          0.5 * o.hand_mass_kg * rn.linear_velocity_mps.squaredNorm() * (o.scripted_device ? 0.0 : 1.0) +
          e_scale * body_ke;
      if (t >= wA0 && t < wA1) ampA = std::max(ampA, e_loop);
      if (t >= wB0) ampB = std::max(ampB, e_loop);
    }
    ++res.ticks;
    res.final_time = t + o.T;
    if (res.max_force_n > o.diverge_force_n || res.max_grab_disp > 1e3 || !st.qd.allFinite()) {
      res.diverged = true;
      break;
    }
  }
  res.finite = res.finite && st.q.allFinite() && st.qd.allFinite();
  res.singular_pivots = d.diag.singular_pivots - pivots0;
  res.env_min_energy = env.min_energy();
  res.env_final_energy = env.energy();
  res.damped_min_energy = damped.min_energy();
  // Growing: the loop KE's maximum over the last 0.1 s exceeds 1.5× its maximum over the first hold
  // window (amplitude × 1.22), and is not negligible.
  res.growth = ampA > 0 ? ampB / ampA : (ampB > 1e-15 ? std::numeric_limits<double>::infinity() : 0.0);
  const bool growing = o.growth_check && !res.diverged && res.growth > 1.5 && ampB > 1e-15;
  res.stable = res.finite && !res.diverged && !growing;
  return res;
}

// Exact stability limit of the hand against a ZOH spring to a fixed point (Colgate's virtual wall),
// for the same hand integration (semi-implicit Euler with `substeps` per period): the largest K with
// spectral radius < 1 of the one-period map of (x, v), found by bisection on a log scale.
inline double zoh_wall_limit(double mass, double arm_k, double b, double T, int substeps) {
  auto rho = [&](double K) {
    // state (x, v, x_held): the force −K x_held is constant over the period.
    // Track x, v over one period as linear combinations of (x0, v0); the force uses the held x0.
    Eigen::Matrix2d M;
    const double h = T / substeps;
    Eigen::Vector2d x(1, 0), v(0, 1);
    for (int i = 0; i < substeps; ++i) {
      v += h * (-arm_k * x - b * v - K * Eigen::Vector2d(1, 0)) / mass;
      x += h * v;
    }
    M.row(0) = x.transpose();
    M.row(1) = v.transpose();
    return M.eigenvalues().cwiseAbs().maxCoeff();
  };
  double lo = 1, hi = 1e12;
  if (rho(hi) < 1) return hi;
  for (int it = 0; it < 100; ++it) {
    const double mid = std::sqrt(lo * hi);
    (rho(mid) < 1 ? lo : hi) = mid;
  }
  return lo;
}

}  // namespace haptree::stress
