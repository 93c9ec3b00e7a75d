// Integrators (haptree/integrators.hpp): RK4 convergence order against the closed-form period of a
// large-amplitude physical pendulum, conservation on chains with spherical joints and on a tumbling
// free body (quaternions), the energy-monitored adaptive RK4, and no allocation per step.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>

#include "haptree/integrators.hpp"
#include "haptree/scenes.hpp"

#include "tests/support/count_allocations.hpp"

namespace haptree {
namespace {

constexpr double kPi = 3.14159265358979323846;

// Physical pendulum: one revolute joint about y, COM at distance l below the axis (gravity −z).
struct Pendulum {
  double m = 1.0, l = 0.5, Iy = 0.01;
  std::shared_ptr<const Model> model;
  Pendulum() {
    ModelBuilder b;
    b.add_body("p", 0, JointType::kRevolute, Vec3::Zero(), Mat3::Identity(), Vec3::UnitY(), m,
               Vec3(0, 0, -l), Vec3(Iy, Iy, Iy).asDiagonal());
    model = b.build();
  }
  // Closed-form period from rest at amplitude th0: T = 4 K(k) / ω0, k = sin(th0/2),
  // K(k) = π / (2 AGM(1, √(1−k²))).
  double period(double th0) const {
    const double w0 = std::sqrt(m * 9.81 * l / (Iy + m * l * l));
    const double k = std::sin(th0 / 2);
    double a = 1, g = std::sqrt(1 - k * k);
    for (int i = 0; i < 40; ++i) {
      const double an = 0.5 * (a + g);
      g = std::sqrt(a * g);
      a = an;
    }
    return 4 * (kPi / (2 * a)) / w0;
  }
};

// Error of the state after exactly one period (the closed form says it returns to (th0, 0)).
double period_error(Integrator method, const Pendulum& p, double th0, int steps) {
  const Model& m = *p.model;
  State st(m);
  st.q(0) = th0;
  Data d(m);
  Rk4Workspace ws(m);
  const double T = p.period(th0), dt = T / steps;
  for (int s = 0; s < steps; ++s) step(method, m, d, st, dt, ws);
  const double w0 = std::sqrt(p.m * 9.81 * p.l / (p.Iy + p.m * p.l * p.l));
  return std::hypot(st.q(0) - th0, st.qd(0) / w0);
}

TEST(Integrators, Rk4IsFourthOrderOnTheLargeAmplitudePendulum) {
  const Pendulum p;
  const double th0 = 2.0;   // 115°: far from the linear regime
  const double e128 = period_error(Integrator::kRk4, p, th0, 128);
  const double e256 = period_error(Integrator::kRk4, p, th0, 256);
  const double e512 = period_error(Integrator::kRk4, p, th0, 512);
  const double o1 = std::log2(e128 / e256), o2 = std::log2(e256 / e512);
  EXPECT_NEAR(o1, 4.0, 0.35) << e128 << " " << e256;   // measured 3.80
  EXPECT_NEAR(o2, 4.0, 0.25) << e256 << " " << e512;   // measured 3.90
  EXPECT_LT(e256, 1e-6);                               // measured 2.7e-8
  // Semi-implicit Euler at the same step: orders of magnitude worse. (Over a full period of this
  // 1-DOF separable system its error falls at order 2, measured 2.0006: it is symplectic there.)
  const double u128 = period_error(Integrator::kSemiImplicitEuler, p, th0, 128);
  const double u256 = period_error(Integrator::kSemiImplicitEuler, p, th0, 256);
  EXPECT_LT(std::log2(u128 / u256), 2.3);
  EXPECT_GT(u256, 1e3 * e256);
  std::printf("period errors: rk4 N=128 %.3e, 256 %.3e, 512 %.3e (orders %.3f %.3f); euler 128 %.3e, 256 %.3e\n",
              e128, e256, e512, o1, o2, u128, u256);
}

TEST(Integrators, ParseAndNames) {
  EXPECT_EQ(parse_integrator("rk4"), Integrator::kRk4);
  EXPECT_EQ(parse_integrator("euler"), Integrator::kSemiImplicitEuler);
  EXPECT_STREQ(integrator_name(Integrator::kRk4), "rk4");
  EXPECT_THROW(parse_integrator("rk45"), std::invalid_argument);
}

// Chain with spherical joints under gravity: total energy error of RK4 falls ~16× per halving.
std::shared_ptr<const Model> spherical_chain(int n) {
  ModelBuilder b;
  int prev = 0;
  for (int i = 1; i <= n; ++i) {
    const double L = 0.3, mass = 1.0 + 0.3 * i;
    const Vec3 mom(0.02, L * L / 12 + 0.01, L * L / 12 + 0.02);
    prev = b.add_body("s" + std::to_string(i), prev, JointType::kSpherical,
                      prev == 0 ? Vec3::Zero() : Vec3(L, 0, 0), Mat3::Identity(), Vec3::UnitZ(),
                      mass, Vec3(L / 2, 0.02, 0), (mass * mom).asDiagonal());
  }
  return b.build();
}

struct EnergyRun { double max_drift = 0, max_ke = 0, max_quat_norm_err = 0; };
EnergyRun energy_run(const Model& m, const State& st0, double dt, double T) {
  State st = st0;
  Data d(m);
  Rk4Workspace ws(m);
  const int steps = static_cast<int>(std::lround(T / dt));
  EnergyRun r;
  double E0 = 0;
  for (int s = 0; s <= steps; ++s) {
    forward_kinematics(m, d, st.q);
    body_dynamics_terms(m, d, st);
    const double ke = kinetic_energy(m, d), E = ke + potential_energy(m, d);
    if (s == 0) E0 = E;
    r.max_drift = std::max(r.max_drift, std::abs(E - E0));
    r.max_ke = std::max(r.max_ke, ke);
    for (int k = 1; k < m.nbodies; ++k) {
      if (m.joint_type[k] != JointType::kSpherical && m.joint_type[k] != JointType::kFree) continue;
      const int qa = m.q_adr[k] + (m.joint_type[k] == JointType::kFree ? 3 : 0);
      r.max_quat_norm_err = std::max(r.max_quat_norm_err, std::abs(st.q.segment<4>(qa).norm() - 1));
    }
    if (s < steps) rk4_step(m, d, st, dt, ws);
  }
  return r;
}

TEST(Integrators, Rk4ConservesEnergyOfASphericalChain) {
  auto m = spherical_chain(4);
  State st(*m);
  for (int k = 1; k <= 4; ++k) {
    const Quat qk(Eigen::AngleAxisd(0.4 * k, Vec3(1, 1 - 0.5 * k, 0.3).normalized()));
    st.q.segment<4>(m->q_adr[k]) << qk.w(), qk.x(), qk.y(), qk.z();
    st.qd.segment<3>(m->v_adr[k]) = Vec3(0.5, -1.0, 0.3 * k);
  }
  const auto coarse = energy_run(*m, st, 2e-3, 2.0);
  const auto fine = energy_run(*m, st, 1e-3, 2.0);
  EXPECT_GT(coarse.max_ke, 1.0);
  EXPECT_LT(coarse.max_drift / coarse.max_ke, 1e-5);
  EXPECT_LT(fine.max_drift / fine.max_ke, 1e-6);
  EXPECT_GT(coarse.max_drift / fine.max_drift, 10.0);   // order 4: 16 ideally
  EXPECT_LT(fine.max_quat_norm_err, 1e-14);
  std::printf("spherical chain: rel drift %.3e (dt 2 ms), %.3e (1 ms), ratio %.2f, max KE %.3f J\n",
              coarse.max_drift / coarse.max_ke, fine.max_drift / fine.max_ke,
              coarse.max_drift / fine.max_drift, coarse.max_ke);
}

// Torque-free asymmetric body on a free joint, spinning near its intermediate axis (it tumbles):
// kinetic energy and world angular momentum are invariants; the state converges at order 4.
struct FreeBody {
  std::shared_ptr<const Model> model;
  FreeBody() {
    ModelBuilder b;
    b.set_gravity(Vec3::Zero());
    b.add_body("top", 0, JointType::kFree, Vec3::Zero(), Mat3::Identity(), Vec3::UnitZ(), 2.0,
               Vec3(0.05, -0.02, 0.03), Vec3(0.10, 0.20, 0.28).asDiagonal());
    model = b.build();
  }
  State initial() const {
    State st(*model);
    const Quat q0(Eigen::AngleAxisd(0.7, Vec3(0.2, 1, -0.4).normalized()));
    st.q.segment<4>(3) << q0.w(), q0.x(), q0.y(), q0.z();
    st.qd << 0.05, 4.0, 0.1, 0.3, -0.2, 0.1;   // ω (body frame), then origin velocity (body frame)
    return st;
  }
};

Vec3 world_angular_momentum(const Model& m, const Data& d) {
  const Vec6 h = d.I[1] * d.v[1];   // [moment about r_1; linear], world axes
  return h.head<3>() + d.r[1].cross(h.tail<3>());
}

TEST(Integrators, Rk4TumblingFreeBodyKeepsInvariantsAndOrder) {
  const FreeBody fb;
  const Model& m = *fb.model;
  auto run = [&](int steps, double T, double* dL, double* dE) {
    State st = fb.initial();
    Data d(m);
    Rk4Workspace ws(m);
    forward_kinematics(m, d, st.q);
    body_dynamics_terms(m, d, st);
    const Vec3 L0 = world_angular_momentum(m, d);
    const double E0 = kinetic_energy(m, d);
    for (int s = 0; s < steps; ++s) {
      rk4_step(m, d, st, T / steps, ws);
      forward_kinematics(m, d, st.q);
      body_dynamics_terms(m, d, st);
      if (dL) *dL = std::max(*dL, (world_angular_momentum(m, d) - L0).norm() / L0.norm());
      if (dE) *dE = std::max(*dE, std::abs(kinetic_energy(m, d) - E0) / E0);
    }
    return st;
  };
  double dL = 0, dE = 0;
  const double T = 3.0;   // several flips of the intermediate axis at ω ≈ 4 rad/s
  const State a = run(1500, T, &dL, &dE);
  EXPECT_LT(dL, 1e-7);
  EXPECT_LT(dE, 1e-7);
  EXPECT_NEAR(a.q.segment<4>(3).norm(), 1.0, 1e-14);
  const State b = run(3000, T, nullptr, nullptr);
  const State ref = run(24000, T, nullptr, nullptr);
  auto err = [&](const State& s) {
    // Compare orientations by the rotation between them (sign-free), plus rates and position.
    const Quat qs(s.q(3), s.q(4), s.q(5), s.q(6)), qr(ref.q(3), ref.q(4), ref.q(5), ref.q(6));
    return qs.angularDistance(qr) + (s.q.head<3>() - ref.q.head<3>()).norm() +
           (s.qd - ref.qd).norm();
  };
  const double ea = err(a), eb = err(b);
  EXPECT_NEAR(std::log2(ea / eb), 4.0, 0.4) << ea << " " << eb;
  std::printf("free body: dL %.3e dE %.3e, state error %.3e (2 ms) %.3e (1 ms), order %.3f\n", dL, dE,
              ea, eb, std::log2(ea / eb));
}

TEST(Integrators, AdaptiveRk4HitsThePendulumPeriodAndBoundsEnergy) {
  const Pendulum p;
  const Model& m = *p.model;
  const double th0 = 2.0, T = p.period(th0);
  State st(m);
  st.q(0) = th0;
  AdaptiveRk4Options o;
  o.dt_init_s = 0.05;
  o.rel_tol = 1e-10;
  o.energy_tol_rel = 1e-8;
  AdaptiveRk4 integ(m, o);
  const double E0 = integ.energy(st);
  ASSERT_TRUE(integ.advance(st, T));
  EXPECT_NEAR(st.t, T, 1e-12);
  EXPECT_NEAR(st.q(0), th0, 1e-6);
  EXPECT_NEAR(st.qd(0), 0.0, 1e-5);
  EXPECT_LT(std::abs(integ.energy(st) - E0), 1e-6 * std::abs(E0));
  const auto& s = integ.stats();
  EXPECT_GT(s.accepted, 10);
  EXPECT_EQ(s.forced, 0);
  EXPECT_LT(s.min_dt, s.max_dt);   // the step really adapts over the swing
  std::printf("adaptive: q err %.3e qd %.3e, dE/E0 %.3e, accepted %ld rejected %ld, dt %.3e … %.3e\n",
              st.q(0) - th0, st.qd(0), (integ.energy(st) - E0) / E0, s.accepted, s.rejected, s.min_dt,
              s.max_dt);
}

TEST(Integrators, StepsAllocateNothing) {
  SceneOptions o;
  o.n = 200;
  o.seed = 3;
  o.mixed_joints = true;
  o.free_root = true;
  auto model = make_random_tree(o);
  State st(*model);
  st.qd.setConstant(0.1);
  Data d(*model);
  Rk4Workspace ws(*model);
  AdaptiveRk4 adaptive(*model);
  rk4_step(*model, d, st, 1e-3, ws);   // warm-up
  adaptive.advance(st, 1e-3);
  const long before = haptree::testing::allocation_count();
  for (int i = 0; i < 5; ++i) {
    rk4_step(*model, d, st, 1e-3, ws);
    step(Integrator::kSemiImplicitEuler, *model, d, st, 1e-3, ws);
  }
  adaptive.advance(st, 2e-3);
  EXPECT_EQ(haptree::testing::allocation_count() - before, 0);
  EXPECT_TRUE(st.q.allFinite());
}

}  // namespace
}  // namespace haptree
