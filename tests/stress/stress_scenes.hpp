// Scenario builders and measurements shared by the stress tests (tests/stress) and the longer
// report tool (tools/stress_report). Everything is deterministic (fixed seeds).
#pragma once

#include <chrono>
#include <cmath>
#include <functional>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "haptree/dca.hpp"
#include "haptree/integrators.hpp"
#include "haptree/scenes.hpp"
#include "tests/support/oracle.hpp"

namespace haptree::stress {

// A random unit vector from `rng`.
inline Vec3 random_unit(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1, 1);
  Vec3 v;
  do { v = Vec3(u(rng), u(rng), u(rng)); } while (v.norm() < 0.1 || v.norm() > 1);
  return v.normalized();
}

// Chain of n revolute links (0.3 m, COM mid-link, box inertia, random axes) whose masses alternate
// between neighbouring links with the given ratio (odd links : even links = 1 : ratio). The lighter
// links always weigh 1 kg (ratio > 1: even links weigh `ratio`; ratio < 1: odd links weigh
// 1/ratio), so no principal inertia falls under ModelBuilder's 1e-14 floor. Inertia scales with
// the mass.
inline std::shared_ptr<const Model> mass_ratio_chain(int n, double ratio, unsigned seed = 5) {
  std::mt19937 rng(seed);
  ModelBuilder b;
  int prev = 0;
  for (int i = 1; i <= n; ++i) {
    const double heavy = ratio >= 1 ? ratio : 1 / ratio;
    const bool odd = i % 2 == 1;
    const double m = ratio >= 1 ? (odd ? 1.0 : heavy) : (odd ? heavy : 1.0);
    const double L = 0.3, w = 0.04;
    const Vec3 moments(2 * w * w, L * L + w * w, L * L + w * w);
    const Mat3 Ic = (m / 12.0 * moments).asDiagonal();
    prev = b.add_body("l" + std::to_string(i), prev, JointType::kRevolute,
                      prev == 0 ? Vec3::Zero() : Vec3(L, 0, 0), Mat3::Identity(), random_unit(rng),
                      m, Vec3(L / 2, 0.01, 0), Ic);
  }
  return b.build();
}

// Light bodies next to heavy ones (the Cα–H body of a torsion-angle protein: smallest principal
// inertia ~1000× below its neighbours'): a chain of n revolute links (0.3 m, random axes, seed 17)
// whose every third link has its mass divided by √r and its smallest principal moment (about the
// link's own axis) by r.
inline std::shared_ptr<const Model> light_body_chain(int n, double r) {
  ModelBuilder b;
  std::mt19937 rng(17);
  int prev = 0;
  for (int i = 1; i <= n; ++i) {
    const bool light = i % 3 == 0;
    const double m = light ? 1.0 / std::sqrt(r) : 1.0, L = 0.3, w = 0.04;
    Vec3 mom(2 * w * w, L * L + w * w, L * L + w * w);
    mom *= m / 12;
    if (light) mom.x() /= std::sqrt(r);   // with m / √r: the smallest moment is / r
    prev = b.add_body("l" + std::to_string(i), prev, JointType::kRevolute,
                      prev == 0 ? Vec3::Zero() : Vec3(L, 0, 0), Mat3::Identity(), random_unit(rng), m,
                      Vec3(L / 2, 0.01, 0), Mat3(mom.asDiagonal()));
  }
  return b.build();
}

// Chain with aligned (coaxial) joint axes: every odd joint turns about the link's own x axis, the
// next one about the same line (joint offset along x), then a y joint, and so on. The body between
// two coaxial joints is a thin rod along that line whose axial inertia is `axial` × the normal
// box value: as axial → 0 the mass matrix becomes singular (the two joints act on the same line
// and only that rod's axial inertia tells them apart).
inline std::shared_ptr<const Model> coaxial_chain(int n, double axial) {
  ModelBuilder b;
  int prev = 0;
  for (int i = 1; i <= n; ++i) {
    const double m = 1.0, L = 0.3, w = 0.04;
    const int phase = (i - 1) % 3;   // 0: x joint, 1: coaxial x joint (thin rod), 2: y joint
    Vec3 moments(2 * w * w, L * L + w * w, L * L + w * w);
    Vec3 com(L / 2, 0.02, 0);
    if (phase == 0) {
      // Body between the two coaxial joints: COM on the axis, axial inertia scaled.
      moments.x() *= axial;
      com = Vec3(L / 2, 0, 0);
    }
    const Mat3 Ic = (m / 12.0 * moments).asDiagonal();
    const Vec3 axis = phase == 2 ? Vec3::UnitY() : Vec3::UnitX();
    prev = b.add_body("l" + std::to_string(i), prev, JointType::kRevolute,
                      prev == 0 ? Vec3::Zero() : Vec3(L, 0, 0), Mat3::Identity(), axis, m, com, Ic);
  }
  return b.build();
}

// A scene by name with its root placed at `offset`.
inline std::shared_ptr<const Model> scene_at(const std::string& name, int n, const Vec3& offset) {
  SceneOptions o;
  o.n = n;
  o.base_offset = offset;
  return make_scene(name, o);
}

// Random state without external forces.
inline State clean_state(const Model& m, unsigned seed, double vel_scale = 1.0) {
  State st = testing::random_state(m, seed, vel_scale);
  for (auto& f : st.f_ext) f.setZero();
  return st;
}

struct FdResult {
  Eigen::VectorXd qdd;
  std::int64_t singular_pivots = 0, nonfinite = 0;
};
inline FdResult dca(const Model& m, const State& st) {
  Data d(m);
  forward_dynamics(m, d, st);
  return {d.qdd, d.diag.singular_pivots, d.diag.nonfinite};
}

inline bool all_finite(const Eigen::VectorXd& v) { return v.allFinite(); }

// Energy drift of a conservative run (τ = 0, no external forces) with semi-implicit Euler
// (haptree::integrate) or RK4 (haptree::rk4_step). rel = max_t |E(t) − E(0)| / max_t KE(t): the
// energy error against the energy actually set in motion (a run released from rest starts with
// KE = 0). A run "blows up" when E or the state goes non-finite, or when |E − E0| exceeds
// DriftOptions::blowup_J (set it to a multiple of the physical kinetic-energy bound: a state whose
// energy error is larger than any kinetic energy physics allows is garbage even while finite).
struct DriftResult {
  double max_abs_drift = 0;    // max_t |E(t) − E(0)|  [J]
  double max_kinetic = 0;      // max_t KE(t)           [J]
  double rel_drift = 0;        // max_abs_drift / max_kinetic (inf if the run blew up)
  double final_drift = 0;      // E(T) − E(0)           [J]
  double t_nonfinite = -1;     // first time E or q̈ is non-finite [s] (−1: never)
  double t_blowup = -1;        // first time the run blew up (non-finite or |E − E0| > blowup_J)
  double max_qd = 0;           // max_t max_i |q̇_i|    [rad/s]
  bool finite = true;
  bool survived = true;        // no blow-up over all steps (false also when cut)
  bool cut = false;            // stopped by DriftOptions::max_wall_s before the last step
  int steps_done = 0;
};
struct DriftProgress {
  int step = 0, steps = 0;
  double t = 0, drift = 0, kinetic = 0, max_qd = 0;
};
struct DriftOptions {
  Integrator method = Integrator::kSemiImplicitEuler;
  double blowup_J = std::numeric_limits<double>::infinity();
  int progress_every = 0;                                  // steps between progress calls (0: none)
  std::function<void(const DriftProgress&)> progress;
  double max_wall_s = std::numeric_limits<double>::infinity();   // tools only: stop (cut) after this
};
inline DriftResult energy_drift(const Model& m, State st, double dt, int steps,
                                const DriftOptions& opt = {}) {
  Data d(m);
  Rk4Workspace ws(m);
  st.tau.setZero();
  for (auto& f : st.f_ext) f.setZero();
  DriftResult r;
  double E0 = 0;
  const bool rk4 = opt.method == Integrator::kRk4;
  const auto wall0 = std::chrono::steady_clock::now();
  for (int s = 0; s <= steps; ++s) {
    if (rk4) {   // energies need only kinematics and body terms; rk4_step runs the dynamics
      forward_kinematics(m, d, st.q);
      body_dynamics_terms(m, d, st);
    } else {
      forward_dynamics(m, d, st);   // also fills the kinematics/velocities the energies read
    }
    const double ke = kinetic_energy(m, d), E = ke + potential_energy(m, d);
    const bool fin = std::isfinite(E) && st.qd.allFinite() && (rk4 || d.qdd.allFinite());
    if (!fin || (s > 0 && std::abs(E - E0) > opt.blowup_J)) {
      if (!fin) {
        r.finite = false;
        r.t_nonfinite = s * dt;
      }
      r.survived = false;
      r.t_blowup = s * dt;
      r.rel_drift = std::numeric_limits<double>::infinity();
      break;
    }
    if (s == 0) E0 = E;
    r.max_kinetic = std::max(r.max_kinetic, ke);
    r.max_qd = std::max(r.max_qd, st.qd.cwiseAbs().maxCoeff());
    const double dE = std::abs(E - E0);
    r.max_abs_drift = std::max(r.max_abs_drift, dE);
    r.final_drift = E - E0;
    r.steps_done = s;
    if (opt.progress && opt.progress_every > 0 && s > 0 && s % opt.progress_every == 0)
      opt.progress({s, steps, s * dt, E - E0, ke, r.max_qd});
    if (s < steps && s % 100 == 99 && std::isfinite(opt.max_wall_s) &&
        std::chrono::duration<double>(std::chrono::steady_clock::now() - wall0).count() >
            opt.max_wall_s) {
      r.cut = true;
      r.survived = false;
      break;
    }
    if (s < steps) {
      if (rk4) rk4_step(m, d, st, dt, ws);
      else integrate(m, st.q, st.qd, d.qdd, dt);
    }
  }
  if (r.survived || r.cut) r.rel_drift = r.max_abs_drift / std::max(r.max_kinetic, 1e-300);
  return r;
}

// Upper bound of the kinetic energy a conservative run can reach: E0 − (a lower bound of the
// gravitational potential), the lowest COM height of body k being the root joint's height minus
// the path length of joint offsets to it minus |com_k|. Only for trees whose root body cannot
// translate and whose joints are revolute/spherical/fixed (otherwise +inf). Gravity off: E0.
inline double kinetic_energy_bound(const Model& m, const State& st) {
  for (int k = 1; k < m.nbodies; ++k) {
    const JointType t = m.joint_type[k];
    if (t == JointType::kPrismatic || t == JointType::kFree)
      return std::numeric_limits<double>::infinity();
  }
  Data d(m);
  forward_kinematics(m, d, st.q);
  body_dynamics_terms(m, d, st);
  const double E0 = kinetic_energy(m, d) + potential_energy(m, d);
  const double gn = m.gravity.norm();
  if (gn == 0) return E0;
  const Vec3 up = -m.gravity / gn;
  std::vector<double> path(m.nbodies, 0.0);
  double pe_min = 0;
  for (int k = 1; k < m.nbodies; ++k) {
    const int p = m.parent[k];
    path[k] = p == 0 ? 0.0 : path[p] + m.joint_offset[k].norm();
    // Root joints sit at fixed points: their height is known from the state.
    int root = k;
    while (m.parent[root] != 0) root = m.parent[root];
    pe_min += m.mass[k] * gn * (up.dot(d.r[root]) - path[k] - m.com[k].norm());
  }
  return E0 - pe_min;
}

// The conservative drift scenes, both on the 857-DOF protein-like tree (root body welded):
//   fall    gravity on, released from rest at random_state(seed 11) angles: the 103-m-long floppy
//           tree collapses and whips (the original stress scene);
//   tumble  gravity off, joint rates random_state(seed 11) × 0.01 rad/s (KE ≈ 22 J): the tree
//           tumbles freely; E = KE is constant, so speeds stay bounded (|v| ≤ √(2E/m_min)).
struct DriftScene {
  std::string name, description;
  std::shared_ptr<const Model> model;
  State st0;
  double ke_bound = 0;   // kinetic_energy_bound(model, st0)
};
inline DriftScene drift_scene(const std::string& name) {
  SceneOptions o;
  auto base = make_protein_like(o);
  if (name == "fall") {
    State st = clean_state(*base, 11, 0.0);
    DriftScene s{name, "857-DOF protein-like tree, gravity on, released from rest (seed 11 angles)",
                 base, st, 0};
    s.ke_bound = kinetic_energy_bound(*s.model, s.st0);
    return s;
  }
  if (name == "tumble") {
    o.gravity.setZero();   // built without gravity, so the fingerprint matches the model
    std::shared_ptr<const Model> m = make_protein_like(o);
    State st = clean_state(*m, 11, 0.01);
    DriftScene s{name, "857-DOF protein-like tree, gravity off, joint rates (seed 11) x 0.01 rad/s",
                 m, st, 0};
    s.ke_bound = kinetic_energy_bound(*s.model, s.st0);
    return s;
  }
  throw std::invalid_argument("unknown drift scene '" + name + "' (known: fall, tumble)");
}

}  // namespace haptree::stress
