// Kinematics of the DCA (docs/algorithms.md §1, §2.3): what the passes read of every body and
// joint, in handle-point coordinates with world-aligned axes.
//   Poses: R_k = R_p R_J R(q_J), d_k = R_p (o_J + R_J t(q_J)), r_k = r_p + d_k (R_J, o_J: the
//   joint's fixed frame; R, t: its rotation and translation), from local offsets, never as a
//   difference of world positions.
//   Velocities: v_k = M(r_p → r_k) v_p + S_J q̇_J, c_J = v_k × (S_J q̇_J).
//   Inertias at r_k: I_k from m_k, R_k c_k and R_k I_c R_kᵀ, its inverse, and the bias force
//   p_k = f_ext,k + (gravity at the centre of mass) − v_k ×* (I_k v_k).
//   Joint subspaces at the handle point (§1 table): motion S, constraint T with Tᵀ S = 0, and D
//   with Dᵀ S = 1.
// Also the semi-implicit Euler step (q̇ += h q̈, then q from the new q̇, a quaternion by the
// exponential map) and the kinetic and gravitational energies of the drift checks.
#include <cmath>

#include "haptree/dca_detail.hpp"

namespace haptree {

namespace {

Mat3 quat_to_rot(const Eigen::VectorXd& q, int a) {
  Quat qu(q(a), q(a + 1), q(a + 2), q(a + 3));
  qu.normalize();
  return qu.toRotationMatrix();
}

}  // namespace

void joint_placement(const Model& m, int k, const Eigen::VectorXd& q, const Mat3& Rp, Mat3& Rk,
                     Vec3& dk) noexcept {
  const int a = m.q_adr[k];
  const Mat3 Rj = Rp * m.joint_rotation[k];
  Vec3 local = m.joint_offset[k];
  switch (m.joint_type[k]) {
    case JointType::kRevolute:
      Rk = Rj * Eigen::AngleAxisd(q(a), m.joint_axis[k]).toRotationMatrix();
      break;
    case JointType::kPrismatic:
      Rk = Rj;
      local += m.joint_rotation[k] * (m.joint_axis[k] * q(a));
      break;
    case JointType::kSpherical: Rk = Rj * quat_to_rot(q, a); break;
    case JointType::kFree:
      Rk = Rj * quat_to_rot(q, a + 3);
      local += m.joint_rotation[k] * q.segment<3>(a);
      break;
    case JointType::kFixed: Rk = Rj; break;
  }
  dk = Rp * local;
}

void forward_kinematics(const Model& m, Data& d, const Eigen::VectorXd& q) noexcept {
  d.R[0].setIdentity();
  d.r[0].setZero();
  d.d[0].setZero();
  for (int k = 1; k < m.nbodies; ++k) {
    const int p = m.parent[k];
    joint_placement(m, k, q, d.R[p], d.R[k], d.d[k]);
    d.r[k] = d.r[p] + d.d[k];
  }
}

Vec6 joint_motion_terms(const Model& m, Data& d, int k, const Eigen::VectorXd& qd,
                        const Vec6& v_parent) noexcept {
  if (m.joint_type[k] == JointType::kRevolute) {
    d.S[k] << d.R[k] * m.joint_axis[k], Vec3::Zero();
  } else if (m.joint_type[k] == JointType::kPrismatic) {
    d.S[k] << Vec3::Zero(), d.R[k] * m.joint_axis[k];
  }
  const Vec6 sq = joint_velocity(m, d, k, qd);
  d.v[k] = shift_motion(v_parent, d.d[k]) + sq;
  d.c[k] = cross_motion(d.v[k], sq);
  return d.v[k];
}

void body_dynamics_terms(const Model& m, Data& d, const State& st) noexcept {
  d.v[0].setZero();
  for (int k = 1; k < m.nbodies; ++k) {
    joint_motion_terms(m, d, k, st.qd, d.v[m.parent[k]]);
    body_inertia_terms(m, d, st, k);
  }
}

void joint_subspaces(const Model& m, const Data& d, int k, JointMat& S, JointMat& T,
                     JointMat& D) noexcept {
  switch (m.joint_type[k]) {
    case JointType::kRevolute:
    case JointType::kPrismatic: {
      const bool rev = m.joint_type[k] == JointType::kRevolute;
      const Vec3 u = rev ? d.S[k].head<3>() : d.S[k].tail<3>();
      Vec3 e1, e2;
      orthonormal_pair(u, e1, e2);
      S = d.S[k];
      D = d.S[k];
      T.setZero(6, 5);
      if (rev) {
        T.block<3, 1>(0, 0) = e1;
        T.block<3, 1>(0, 1) = e2;
        T.block<3, 3>(3, 2).setIdentity();
      } else {
        T.block<3, 3>(0, 0).setIdentity();
        T.block<3, 1>(3, 3) = e1;
        T.block<3, 1>(3, 4) = e2;
      }
      break;
    }
    case JointType::kSpherical:
      S.setZero(6, 3);
      S.topRows<3>() = d.R[k];
      D = S;
      T.setZero(6, 3);
      T.bottomRows<3>().setIdentity();
      break;
    case JointType::kFree:
      S.setZero(6, 6);
      S.topLeftCorner<3, 3>() = d.R[k];
      S.bottomRightCorner<3, 3>() = d.R[k];
      D = S;
      T.resize(6, 0);
      break;
    case JointType::kFixed:
      S.resize(6, 0);
      D.resize(6, 0);
      T.setIdentity(6, 6);
      break;
  }
}

void integrate_joint(const Model& m, int k, Eigen::VectorXd& q, const Eigen::VectorXd& qd,
                     double dt) noexcept {
  const int a = m.q_adr[k], v = m.v_adr[k];
  switch (m.joint_type[k]) {
    case JointType::kRevolute:
    case JointType::kPrismatic: q(a) += dt * qd(v); break;
    case JointType::kSpherical:
    case JointType::kFree: {
      const int qa = m.joint_type[k] == JointType::kFree ? a + 3 : a;
      Quat qu(q(qa), q(qa + 1), q(qa + 2), q(qa + 3));
      qu.normalize();
      if (m.joint_type[k] == JointType::kFree)
        q.segment<3>(a) += dt * (qu.toRotationMatrix() * qd.segment<3>(v + 3));
      const Vec3 w = qd.segment<3>(v) * dt;
      const double ang = w.norm();
      const Quat dq = ang > 1e-300 ? Quat(Eigen::AngleAxisd(ang, w / ang)) : Quat::Identity();
      qu = (qu * dq).normalized();
      q(qa) = qu.w(); q(qa + 1) = qu.x(); q(qa + 2) = qu.y(); q(qa + 3) = qu.z();
      break;
    }
    case JointType::kFixed: break;
  }
}

void integrate_positions(const Model& m, Eigen::VectorXd& q, const Eigen::VectorXd& qd,
                         double dt) noexcept {
  for (int k = 1; k < m.nbodies; ++k) integrate_joint(m, k, q, qd, dt);
}

void integrate(const Model& m, Eigen::VectorXd& q, Eigen::VectorXd& qd,
               const Eigen::VectorXd& qdd, double dt) noexcept {
  qd += dt * qdd;
  integrate_positions(m, q, qd, dt);
}

double kinetic_energy(const Model& m, const Data& d) noexcept {
  double e = 0;
  for (int k = 1; k < m.nbodies; ++k) e += 0.5 * d.v[k].dot(d.I[k] * d.v[k]);
  return e;
}
double potential_energy(const Model& m, const Data& d) noexcept {
  double e = 0;
  for (int k = 1; k < m.nbodies; ++k) e -= m.mass[k] * m.gravity.dot(d.r[k] + d.R[k] * m.com[k]);
  return e;
}


}  // namespace haptree
