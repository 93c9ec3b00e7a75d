// Scenario builders and measurements shared by the stress tests (tests/stress) and the longer
// report tool (tools/stress_report). Everything is deterministic (fixed seeds).
#pragma once

#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "haptree/dca.hpp"
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

// Energy drift of a conservative run (gravity on, τ = 0, no external forces) with
// haptree::integrate (semi-implicit Euler). rel = max_t |E(t) − E(0)| / max_t KE(t): the energy
// error against the energy actually set in motion (a run released from rest starts with KE = 0).
struct DriftResult {
  double max_abs_drift = 0;    // max_t |E(t) − E(0)|  [J]
  double max_kinetic = 0;      // max_t KE(t)           [J]
  double rel_drift = 0;        // max_abs_drift / max_kinetic (inf if the run went non-finite)
  double final_drift = 0;      // E(T) − E(0)           [J]
  double t_nonfinite = -1;     // first time E or q̈ is non-finite [s] (−1: never)
  bool finite = true;
  int steps_done = 0;
};
inline DriftResult energy_drift(const Model& m, State st, double dt, int steps) {
  Data d(m);
  st.tau.setZero();
  for (auto& f : st.f_ext) f.setZero();
  DriftResult r;
  double E0 = 0;
  for (int s = 0; s <= steps; ++s) {
    forward_dynamics(m, d, st);   // also fills the kinematics/velocities the energies read
    const double ke = kinetic_energy(m, d), E = ke + potential_energy(m, d);
    if (!std::isfinite(E) || !d.qdd.allFinite()) {
      r.finite = false;
      r.t_nonfinite = s * dt;
      r.rel_drift = std::numeric_limits<double>::infinity();
      break;
    }
    if (s == 0) E0 = E;
    r.max_kinetic = std::max(r.max_kinetic, ke);
    const double dE = std::abs(E - E0);
    r.max_abs_drift = std::max(r.max_abs_drift, dE);
    r.final_drift = E - E0;
    r.steps_done = s;
    if (s < steps) integrate(m, st.q, st.qd, d.qdd, dt);
  }
  if (r.finite) r.rel_drift = r.max_abs_drift / std::max(r.max_kinetic, 1e-300);
  return r;
}

}  // namespace haptree::stress
