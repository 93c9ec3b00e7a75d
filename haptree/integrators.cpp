#include "haptree/integrators.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace haptree {

const char* integrator_name(Integrator i) {
  switch (i) {
    case Integrator::kSemiImplicitEuler: return "euler";
    case Integrator::kRk4: return "rk4";
  }
  return "?";
}

Integrator parse_integrator(const std::string& name) {
  if (name == "euler" || name == "semi-implicit-euler") return Integrator::kSemiImplicitEuler;
  if (name == "rk4") return Integrator::kRk4;
  throw std::invalid_argument("unknown integrator '" + name + "' (known: euler, rk4)");
}

void configuration_rate(const Model& m, const Eigen::VectorXd& q, const Eigen::VectorXd& qd,
                        Eigen::VectorXd& out) noexcept {
  for (int k = 1; k < m.nbodies; ++k) {
    const int a = m.q_adr[k], v = m.v_adr[k];
    switch (m.joint_type[k]) {
      case JointType::kRevolute:
      case JointType::kPrismatic: out(a) = qd(v); break;
      case JointType::kSpherical:
      case JointType::kFree: {
        const bool free = m.joint_type[k] == JointType::kFree;
        const int qa = free ? a + 3 : a;
        Quat qu(q(qa), q(qa + 1), q(qa + 2), q(qa + 3));
        qu.normalize();
        if (free) out.segment<3>(a) = qu.toRotationMatrix() * qd.segment<3>(v + 3);
        // q' = ½ q ⊗ (0, ω), ω in the body frame (integrate_joint multiplies on the right).
        const Vec3 w = qd.segment<3>(v);
        const Vec3 qv(qu.x(), qu.y(), qu.z());
        out(qa) = -0.5 * qv.dot(w);
        out.segment<3>(qa + 1) = 0.5 * (qu.w() * w + qv.cross(w));
        break;
      }
      case JointType::kFixed: break;
    }
  }
}

void normalize_quaternions(const Model& m, Eigen::VectorXd& q) noexcept {
  for (int k = 1; k < m.nbodies; ++k) {
    const JointType t = m.joint_type[k];
    if (t != JointType::kSpherical && t != JointType::kFree) continue;
    const int qa = t == JointType::kFree ? m.q_adr[k] + 3 : m.q_adr[k];
    const double n = q.segment<4>(qa).norm();
    if (n > 0) q.segment<4>(qa) /= n;
  }
}

Rk4Workspace::Rk4Workspace(const Model& m) : stage(m) {
  q0.resize(m.nq);
  qd0.resize(m.nv);
  for (int i = 0; i < 4; ++i) {
    kq[i].setZero(m.nq);
    kv[i].setZero(m.nv);
  }
}

void rk4_step(const Model& m, Data& d, State& st, double dt, Rk4Workspace& ws) noexcept {
  ws.q0 = st.q;
  ws.qd0 = st.qd;
  State& s = ws.stage;
  s.tau = st.tau;
  s.f_ext = st.f_ext;   // same size: element-wise copy, no allocation
  s.t = st.t;
  static constexpr double kC[4] = {0.0, 0.5, 0.5, 1.0};
  for (int i = 0; i < 4; ++i) {
    if (i == 0) {
      s.q = ws.q0;
      s.qd = ws.qd0;
    } else {
      const double h = kC[i] * dt;
      s.q = ws.q0 + h * ws.kq[i - 1];
      s.qd = ws.qd0 + h * ws.kv[i - 1];
      normalize_quaternions(m, s.q);
    }
    s.t = st.t + kC[i] * dt;
    configuration_rate(m, s.q, s.qd, ws.kq[i]);
    ws.kv[i] = forward_dynamics(m, d, s);
  }
  const double w = dt / 6.0;
  st.q = ws.q0 + w * (ws.kq[0] + 2.0 * ws.kq[1] + 2.0 * ws.kq[2] + ws.kq[3]);
  st.qd = ws.qd0 + w * (ws.kv[0] + 2.0 * ws.kv[1] + 2.0 * ws.kv[2] + ws.kv[3]);
  normalize_quaternions(m, st.q);
  st.t += dt;
}

void step(Integrator method, const Model& m, Data& d, State& st, double dt,
          Rk4Workspace& ws) noexcept {
  if (method == Integrator::kRk4) {
    rk4_step(m, d, st, dt, ws);
  } else {
    forward_dynamics(m, d, st);
    integrate(m, st.q, st.qd, d.qdd, dt);
    st.t += dt;
  }
}

AdaptiveRk4::AdaptiveRk4(const Model& m, const AdaptiveRk4Options& o)
    : m_(m), o_(o), d_(m), ws_(m), full_(m), half_(m), h_(o.dt_init_s) {
  if (!(o.min_dt_s > 0) || !(o.max_dt_s >= o.min_dt_s) || !(o.dt_init_s > 0) || !(o.rel_tol > 0) ||
      !(o.energy_tol_rel > 0))
    throw std::invalid_argument("AdaptiveRk4Options: need 0 < min_dt_s <= max_dt_s, dt_init_s > 0, "
                                "rel_tol > 0, energy_tol_rel > 0");
}

double AdaptiveRk4::energy(const State& st) noexcept {
  forward_kinematics(m_, d_, st.q);
  body_dynamics_terms(m_, d_, st);
  return kinetic_energy(m_, d_) + potential_energy(m_, d_);
}

bool AdaptiveRk4::advance(State& st, double duration) noexcept {
  const double t_end = st.t + duration;
  double E = energy(st);
  while (st.t < t_end) {
    const double left = t_end - st.t;
    if (left <= 1e-12 * std::max(1.0, std::abs(t_end))) break;
    const double h = std::min({h_, o_.max_dt_s, left});
    // One step of h and two of h/2 from the same start.
    full_ = st;
    rk4_step(m_, d_, full_, h, ws_);
    half_ = st;
    rk4_step(m_, d_, half_, 0.5 * h, ws_);
    rk4_step(m_, d_, half_, 0.5 * h, ws_);
    stats_.dynamics_calls += 12;
    // Scaled max-norm error estimate (Richardson: error of the half-step result ≈ diff / 15).
    double err = 0;
    for (int i = 0; i < m_.nq; ++i)
      err = std::max(err, std::abs(half_.q(i) - full_.q(i)) / (15.0 * (1.0 + std::abs(half_.q(i)))));
    for (int i = 0; i < m_.nv; ++i)
      err = std::max(err, std::abs(half_.qd(i) - full_.qd(i)) / (15.0 * (1.0 + std::abs(half_.qd(i)))));
    // Richardson-extrapolated result in full_.
    full_.q = half_.q + (half_.q - full_.q) / 15.0;
    full_.qd = half_.qd + (half_.qd - full_.qd) / 15.0;
    normalize_quaternions(m_, full_.q);
    full_.t = st.t + h;
    const double En = energy(full_);
    const double ke = kinetic_energy(m_, d_);
    const bool finite = std::isfinite(err) && std::isfinite(En);
    const double e_rel = std::abs(En - E) / (ke + o_.energy_floor_J);
    const bool ok = finite && err <= o_.rel_tol && e_rel <= o_.energy_tol_rel;
    if (ok || h <= o_.min_dt_s) {
      if (!finite) return false;
      if (!ok) ++stats_.forced;
      st.q = full_.q;
      st.qd = full_.qd;
      st.t = full_.t;
      E = En;
      ++stats_.accepted;
      if (stats_.accepted == 1 || h < stats_.min_dt) stats_.min_dt = h;
      stats_.max_dt = std::max(stats_.max_dt, h);
      // Grow by the error estimate (local error ∝ h⁵), at most 2×; never shrink after success.
      const double ratio = std::max(err / o_.rel_tol, e_rel / o_.energy_tol_rel);
      const double grow = ratio > 0 ? std::clamp(0.9 * std::pow(ratio, -0.2), 1.0, 2.0) : 2.0;
      if (h == std::min(h_, o_.max_dt_s)) h_ = std::min(o_.max_dt_s, h * grow);
    } else {
      ++stats_.rejected;
      const double ratio = finite ? std::max(err / o_.rel_tol, e_rel / o_.energy_tol_rel) : 1e9;
      h_ = std::max(o_.min_dt_s, h * std::clamp(0.9 * std::pow(ratio, -0.2), 0.1, 0.5));
    }
  }
  stats_.last_dt = h_;
  return st.q.allFinite() && st.qd.allFinite();
}

}  // namespace haptree
