/// @file
/// Inverse dynamics residual r = τ − ID(q, q̇, q̈) in a chosen precision S, kinematics included,
/// from the model's data and the state as given (RNEA at the joint points r_k, world axes, the
/// conventions of dca_kinematics.cpp). forward_dynamics uses S = long double for Refinement::kExtended; the
/// tests instantiate it with __float128 for their quad-precision reference (tests/support). Written
/// with explicit formulas (Rodrigues, quaternion matrix) so that S needs only + − × / and the three
/// functions of ScalarFunctions.
#pragma once

#include <cmath>
#include <vector>

#include "haptree/model.hpp"

namespace haptree {

/// sin, cos and sqrt in scalar type S; specialised for types std:: does not cover (tests: __float128).
template <class S>
struct ScalarFunctions {
  static S sin(S x) { return std::sin(x); }    ///< sine in S
  static S cos(S x) { return std::cos(x); }    ///< cosine in S
  static S sqrt(S x) { return std::sqrt(x); }  ///< square root in S
};

/// Per-body scratch of inverse_dynamics_residual in scalar type S, sized once.
template <class S>
struct InverseDynamicsScratch {
  using V3 = Eigen::Matrix<S, 3, 1>;   ///< 3-vector in S
  using M3 = Eigen::Matrix<S, 3, 3>;   ///< 3×3 matrix in S
  using V6 = Eigen::Matrix<S, 6, 1>;   ///< spatial vector in S
  std::vector<M3> R;   ///< (nbodies) body rotations
  std::vector<V3> d;   ///< (nbodies) offsets from the parent's origin
  std::vector<V6> v;   ///< (nbodies) spatial velocities
  std::vector<V6> a;   ///< (nbodies) spatial accelerations
  std::vector<V6> f;   ///< (nbodies) body forces
  /// Sizes every array for `nbodies` bodies (allocates).
  void resize(int nbodies) {
    R.resize(nbodies);
    d.resize(nbodies);
    v.resize(nbodies);
    a.resize(nbodies);
    f.resize(nbodies);
  }
  /// Whether resize(nbodies) was done.
  bool sized(int nbodies) const { return f.size() == static_cast<std::size_t>(nbodies); }
};

/// r (size nv, any scalar) = τ − ID(q, q̇, q̈) for a State st (q, qd, tau, f_ext); q̈ may be double
/// or wider. No allocation when `w` is sized for the model.
template <class S, class StateT, class Qdd, class Out>
void inverse_dynamics_residual_in(const Model& m, const StateT& st, const Qdd& qdd,
                                  InverseDynamicsScratch<S>& w, Out& r) {
  using Sc = ScalarFunctions<S>;
  using V3 = typename InverseDynamicsScratch<S>::V3;
  using M3 = typename InverseDynamicsScratch<S>::M3;
  using V6 = typename InverseDynamicsScratch<S>::V6;
  using OutS = typename Out::Scalar;
  auto cast3 = [](const Vec3& x) { return V3(S(x(0)), S(x(1)), S(x(2))); };
  auto castm = [](const Mat3& x) {
    M3 y;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) y(i, j) = S(x(i, j));
    return y;
  };
  auto seg3 = [](const auto& x, int a) { return V3(S(x(a)), S(x(a + 1)), S(x(a + 2))); };
  auto skew3 = [](const V3& u) {
    M3 K;
    K << S(0), -u(2), u(1), u(2), S(0), -u(0), -u(1), u(0), S(0);
    return K;
  };
  auto quat = [&](int a) {   // unit quaternion (w, x, y, z) of q(a..a+3) as a rotation matrix
    S qw = S(st.q(a)), qx = S(st.q(a + 1)), qy = S(st.q(a + 2)), qz = S(st.q(a + 3));
    const S n = Sc::sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
    qw /= n, qx /= n, qy /= n, qz /= n;
    M3 Rq;
    Rq << 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw),
        2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw),
        2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy);
    return Rq;
  };
  auto shift_m = [](const V6& x, const V3& e) {   // motion at a -> at a + e
    V6 y = x;
    y.template tail<3>() += x.template head<3>().cross(e);
    return y;
  };
  const V3 g = cast3(m.gravity);
  w.R[0].setIdentity();
  w.v[0].setZero();
  w.a[0].setZero();
  for (int k = 1; k < m.nbodies; ++k) {
    const int p = m.parent[k], qa = m.q_adr[k], va = m.v_adr[k];
    const M3& Rp = w.R[p];
    const M3 Jr = castm(m.joint_rotation[k]);
    const M3 Rj = Rp * Jr;
    V3 local = cast3(m.joint_offset[k]);
    M3& Rk = w.R[k];
    V6 sv = V6::Zero(), sa = V6::Zero();   // S q̇, S q̈ (world axes)
    const V3 u = cast3(m.joint_axis[k]);
    switch (m.joint_type[k]) {
      case JointType::kRevolute: {
        const S th = S(st.q(qa));
        const M3 K = skew3(u);
        Rk = Rj * (M3::Identity() + Sc::sin(th) * K + (1 - Sc::cos(th)) * (K * K));
        const V3 ax = Rk * u;
        sv.template head<3>() = ax * S(st.qd(va));
        sa.template head<3>() = ax * S(qdd(va));
        break;
      }
      case JointType::kPrismatic: {
        Rk = Rj;
        local += Jr * (u * S(st.q(qa)));
        const V3 ax = Rk * u;
        sv.template tail<3>() = ax * S(st.qd(va));
        sa.template tail<3>() = ax * S(qdd(va));
        break;
      }
      case JointType::kSpherical:
        Rk = Rj * quat(qa);
        sv.template head<3>() = Rk * seg3(st.qd, va);
        sa.template head<3>() = Rk * seg3(qdd, va);
        break;
      case JointType::kFree:
        Rk = Rj * quat(qa + 3);
        local += Jr * seg3(st.q, qa);
        sv << Rk * seg3(st.qd, va), Rk * seg3(st.qd, va + 3);
        sa << Rk * seg3(qdd, va), Rk * seg3(qdd, va + 3);
        break;
      case JointType::kFixed: Rk = Rj; break;
    }
    const V3 dk = Rp * local;
    w.d[k] = dk;
    const V6 v = shift_m(w.v[p], dk) + sv;
    V6 a = shift_m(w.a[p], dk) + sa;
    a.template head<3>() += v.template head<3>().cross(sv.template head<3>());   // c_k = v × S q̇
    a.template tail<3>() += v.template head<3>().cross(sv.template tail<3>()) +
                            v.template tail<3>().cross(sv.template head<3>());
    w.v[k] = v;
    w.a[k] = a;
    // f = I a + v ×* (I v) − gravity − f_ext, I at r_k from mass M, COM c, Ic about the COM.
    const S M = S(m.mass[k]);
    const V3 c = Rk * cast3(m.com[k]);
    const M3 Ic = Rk * castm(m.inertia[k]) * Rk.transpose();
    auto inertia_times = [&](const V6& x) {   // spatial_inertia(M, c, Ic) x without the 6×6
      const V3 om = x.template head<3>();
      const V3 pl = M * (V3(x.template tail<3>()) - c.cross(om));   // M × (velocity of the COM)
      V6 y;
      y << Ic * om + c.cross(pl), pl;
      return y;
    };
    const V6 h = inertia_times(v);
    V6 f = inertia_times(a);
    f.template head<3>() += v.template head<3>().cross(h.template head<3>()) +
                            v.template tail<3>().cross(h.template tail<3>());
    f.template tail<3>() += v.template head<3>().cross(h.template tail<3>());
    f.template head<3>() -= c.cross(M * g) + cast3(st.f_ext[k].template head<3>());
    f.template tail<3>() -= M * g + cast3(st.f_ext[k].template tail<3>());
    w.f[k] = f;
  }
  for (int k = m.nbodies - 1; k >= 1; --k) {
    const V6& f = w.f[k];
    const M3& Rk = w.R[k];
    const int a = m.v_adr[k];
    auto put3 = [&](int at, const V3& x) {
      for (int i = 0; i < 3; ++i) r(at + i) = OutS(S(st.tau(at + i)) - x(i));
    };
    switch (m.joint_type[k]) {
      case JointType::kRevolute:
        r(a) = OutS(S(st.tau(a)) - (Rk * cast3(m.joint_axis[k])).dot(f.template head<3>()));
        break;
      case JointType::kPrismatic:
        r(a) = OutS(S(st.tau(a)) - (Rk * cast3(m.joint_axis[k])).dot(f.template tail<3>()));
        break;
      case JointType::kSpherical: put3(a, Rk.transpose() * f.template head<3>()); break;
      case JointType::kFree:
        put3(a, Rk.transpose() * f.template head<3>());
        put3(a + 3, Rk.transpose() * f.template tail<3>());
        break;
      case JointType::kFixed: break;
    }
    const int p = m.parent[k];
    if (p > 0) {   // the force at r_k moved to r_p = r_k − d_k: n + d_k × f
      w.f[p].template head<3>() += f.template head<3>() + w.d[k].cross(f.template tail<3>());
      w.f[p].template tail<3>() += f.template tail<3>();
    }
  }
}

}  // namespace haptree
