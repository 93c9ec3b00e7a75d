#include "haptree/dca.hpp"

#include <cmath>

namespace haptree {

namespace {

Mat3 quat_to_rot(const Eigen::VectorXd& q, int a) {
  Quat qu(q(a), q(a + 1), q(a + 2), q(a + 3));
  qu.normalize();
  return qu.toRotationMatrix();
}

// Two unit vectors orthogonal to u.
void orthonormal_pair(const Vec3& u, Vec3& e1, Vec3& e2) {
  const Vec3 a = std::abs(u.x()) < 0.9 ? Vec3::UnitX() : Vec3::UnitY();
  e1 = u.cross(a).normalized();
  e2 = u.cross(e1);
}

// Joint motion (world axes) for joint k given S and q̇: S q̇.
Vec6 joint_velocity(const Model& m, const Data& d, int k, const Eigen::VectorXd& qd) {
  const int a = m.v_adr[k];
  Vec6 s = Vec6::Zero();
  switch (m.joint_type[k]) {
    case JointType::kRevolute:
    case JointType::kPrismatic: s = d.S[k] * qd(a); break;
    case JointType::kSpherical: s.head<3>() = d.R[k] * qd.segment<3>(a); break;
    case JointType::kFree:
      s.head<3>() = d.R[k] * qd.segment<3>(a);
      s.tail<3>() = d.R[k] * qd.segment<3>(a + 3);
      break;
    case JointType::kFixed: break;
  }
  return s;
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
    const Mat3& Rk = d.R[k];
    const Vec3 cw = Rk * m.com[k];
    const Mat3 Ic = Rk * m.inertia[k] * Rk.transpose();
    d.I[k] = spatial_inertia(m.mass[k], cw, Ic);
    d.Iinv[k] = spatial_inertia_inverse(m.mass[k], cw, Ic);
    d.f_total[k] = gravity_force(m.mass[k], cw, m.gravity) + st.f_ext[k];
    d.p_bias[k] = d.f_total[k] - cross_force(d.v[k], d.I[k] * d.v[k]);
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

namespace {

// M(d) A for a 6×6 A: rows [A_top; A_bot − [d]× A_top] (3×3 block work instead of 6×6 products).
inline Mat6 shift_rows(const Vec3& dv, const Mat6& A) {
  Mat6 B = A;
  const Mat3 D = skew(dv);
  B.bottomRows<3>() -= D * A.topRows<3>();
  return B;
}
// A M(d)ᵀ with M(d)ᵀ = [[1, [d]×],[0, 1]]: columns [A_left, A_right + A_left [d]×].
inline Mat6 shift_cols(const Mat6& A, const Vec3& dv) {
  Mat6 B = A;
  const Mat3 D = skew(dv);
  B.rightCols<3>() += A.leftCols<3>() * D;
  return B;
}

}  // namespace

void dca_leaf(const Model& m, Data& d, int node) noexcept {
  const auto& t = m.tree;
  const int k = t.body[node];
  const int h = t.handle_num[node];
  if (k == 0) {   // the ground: immovable, Φ = 0, b = 0
    for (int x = 0; x < h; ++x) {
      for (int y = 0; y < h; ++y) d.Phi(node, h, x, y).setZero();
      d.b(node, x).setZero();
    }
    return;
  }
  // M_x = M(r_k → point of handle x); the handle point of child joint c is r_c = r_k + d_c.
  const Vec6 a0 = d.Iinv[k] * d.p_bias[k];
  for (int x = 0; x < h; ++x) {
    const int jx = t.handle(node, x);
    const bool own_x = jx == k;
    const Mat6 MxI = own_x ? d.Iinv[k] : shift_rows(d.d[jx], d.Iinv[k]);
    for (int y = x; y < h; ++y) {
      const int jy = t.handle(node, y);
      const Mat6 blk = jy == k ? MxI : shift_cols(MxI, d.d[jy]);
      d.Phi(node, h, x, y) = blk;
      if (y != x) d.Phi(node, h, y, x) = blk.transpose();
    }
    d.b(node, x) = own_x ? a0 : shift_motion(a0, d.d[jx]);
  }
}

namespace {

// W = T (Tᵀ Φ̂ T)^{-1} Tᵀ = Xᵀ X with X = L^{-1} Tᵀ, L the Cholesky factor of the nc × nc joint
// system (hand-rolled for fixed nc: Eigen's generic triangular solve is not inlined at this size).
// Returns false when a pivot is not positive relative to the trace (a modelling error, §14.4).
template <int NC>
bool constraint_inverse(const Mat6& Phat, const JointMat& Tdyn, Mat6& W) {
  const Eigen::Matrix<double, 6, NC> T = Tdyn;
  const Eigen::Matrix<double, NC, NC> A = T.transpose() * Phat * T;
  const double tol = 1e-13 * A.trace();
  bool ok = true;
  double L[NC][NC] = {};
  for (int j = 0; j < NC; ++j) {
    double s = A(j, j);
    for (int k = 0; k < j; ++k) s -= L[j][k] * L[j][k];
    if (!(s > tol)) {   // reported; a tiny positive pivot is kept, only s <= 0 is replaced
      ok = false;
      if (!(s > 0)) s = tol > 0 ? tol : 1e-300;
    }
    L[j][j] = std::sqrt(s);
    const double inv = 1.0 / L[j][j];
    for (int i = j + 1; i < NC; ++i) {
      double v = A(i, j);
      for (int k = 0; k < j; ++k) v -= L[i][k] * L[j][k];
      L[i][j] = v * inv;
    }
  }
  Eigen::Matrix<double, NC, 6> X;
  for (int c = 0; c < 6; ++c)
    for (int i = 0; i < NC; ++i) {
      double v = T(c, i);
      for (int k = 0; k < i; ++k) v -= L[i][k] * X(k, c);
      X(i, c) = v / L[i][i];
    }
  W.noalias() = X.transpose() * X;
  return ok;
}

}  // namespace

void dca_assemble(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) noexcept {
  const auto& t = m.tree;
  const int P = t.P[node], Q = t.Q[node], J = t.joint[node];
  const int j = t.slot_j[node], k = t.slot_k[node];
  const int hP = t.handle_num[P], hQ = t.handle_num[Q], hC = t.handle_num[node];
  const Mat6 Phat = d.Phi(P, hP, j, j) + d.Phi(Q, hQ, k, k);

  JointMat S, T, D;
  joint_subspaces(m, d, J, S, T, D);
  Mat6& W = d.W[node];
  const int nc = static_cast<int>(T.cols());
  bool ok = true;
  switch (nc) {
    case 0: W.setZero(); break;
    case 3: ok = constraint_inverse<3>(Phat, T, W); break;
    case 5: ok = constraint_inverse<5>(Phat, T, W); break;
    case 6: ok = constraint_inverse<6>(Phat, T, W); break;
    default: W.setZero(); ok = false;   // no joint type has 1, 2 or 4 constraints
  }
  if (!ok) {
    ++d.diag.singular_pivots;
    d.diag.last_bad_node = node;
  }
  const int nJ = static_cast<int>(S.cols());
  Vec6& taut = d.taut[node];
  if (nJ > 0) {
    const Vec6 Dtau = D * tau.segment(m.v_adr[J], nJ);
    taut = Dtau - W * (Phat * Dtau);
  } else {
    taut.setZero();
  }
  Vec6& beta = d.beta[node];
  beta = W * (d.c[J] - d.b(Q, k) + d.b(P, j)) + taut;

  // Surviving handles: C slots 0..hP-2 come from P' in order, then Q'.
  int ci = 0;
  for (int i = 0; i < hP; ++i) {
    if (i == j) continue;
    const Mat6 XW = d.Phi(P, hP, i, j) * W;
    int ci2 = ci;
    for (int i2 = i; i2 < hP; ++i2) {
      if (i2 == j) continue;
      Mat6 blk = d.Phi(P, hP, i, i2) - XW * d.Phi(P, hP, i2, j).transpose();
      if (i2 == i) blk = 0.5 * (blk + blk.transpose());
      d.Phi(node, hC, ci, ci2) = blk;
      if (ci2 != ci) d.Phi(node, hC, ci2, ci) = blk.transpose();
      ++ci2;
    }
    int cl = hP - 1;
    for (int l = 0; l < hQ; ++l) {
      if (l == k) continue;
      const Mat6 blk = XW * d.Phi(Q, hQ, l, k).transpose();
      d.Phi(node, hC, ci, cl) = blk;
      d.Phi(node, hC, cl, ci) = blk.transpose();
      ++cl;
    }
    d.b(node, ci) = d.b(P, i) - d.Phi(P, hP, i, j) * beta;
    ++ci;
  }
  int cl = hP - 1;
  for (int l = 0; l < hQ; ++l) {
    if (l == k) continue;
    const Mat6 YW = d.Phi(Q, hQ, l, k) * W;
    int cl2 = cl;
    for (int l2 = l; l2 < hQ; ++l2) {
      if (l2 == k) continue;
      Mat6 blk = d.Phi(Q, hQ, l, l2) - YW * d.Phi(Q, hQ, l2, k).transpose();
      if (l2 == l) blk = 0.5 * (blk + blk.transpose());
      d.Phi(node, hC, cl, cl2) = blk;
      if (cl2 != cl) d.Phi(node, hC, cl2, cl) = blk.transpose();
      ++cl2;
    }
    d.b(node, cl) = d.b(Q, l) + d.Phi(Q, hQ, l, k) * beta;
    ++cl;
  }
}

void dca_top_down_node(const Model& m, Data& d, int node) noexcept {
  const auto& t = m.tree;
  const int P = t.P[node], Q = t.Q[node], J = t.joint[node];
  const int j = t.slot_j[node], k = t.slot_k[node];
  const int hP = t.handle_num[P], hQ = t.handle_num[Q], hC = t.handle_num[node];
  (void)hC;
  Vec6 sP = Vec6::Zero(), sQ = Vec6::Zero();
  int ci = 0;
  for (int i = 0; i < hP; ++i) {
    if (i == j) continue;
    const Vec6 fi = d.f(node, ci++);
    d.f(P, i) = fi;
    sP.noalias() += d.Phi(P, hP, j, i) * fi;
  }
  for (int l = 0; l < hQ; ++l) {
    if (l == k) continue;
    const Vec6 fl = d.f(node, ci++);
    d.f(Q, l) = fl;
    sQ.noalias() += d.Phi(Q, hQ, k, l) * fl;
  }
  const Vec6 fc = d.W[node] * (sP - sQ) + d.beta[node];
  d.f(P, j) = -fc;
  d.f(Q, k) = fc;
  const int nJ = m.v_num[J];
  if (nJ > 0 && d.kind[node] == NodeKind::kActive) {
    // Relative acceleration across J minus c_J, then q̈ = Dᵀ(...).
    const Vec6 arel = (d.Phi(P, hP, j, j) + d.Phi(Q, hQ, k, k)) * fc + (sQ - sP) + d.b(Q, k) -
                      d.b(P, j) - d.c[J];
    const int a = m.v_adr[J];
    switch (m.joint_type[J]) {
      case JointType::kRevolute:
      case JointType::kPrismatic: d.qdd(a) = d.S[J].dot(arel); break;
      case JointType::kSpherical: d.qdd.segment<3>(a) = d.R[J].transpose() * arel.head<3>(); break;
      case JointType::kFree:
        d.qdd.segment<3>(a) = d.R[J].transpose() * arel.head<3>();
        d.qdd.segment<3>(a + 3) = d.R[J].transpose() * arel.tail<3>();
        break;
      case JointType::kFixed: break;
    }
  }
}

void dca_bottom_up(const Model& m, Data& d, const State& st) noexcept {
  const auto& t = m.tree;
  std::int64_t count = 0;
  for (int node = t.nnodes() - 1; node >= 0; --node) {
    if (t.is_leaf(node)) dca_leaf(m, d, node);
    else dca_assemble(m, d, node, st.tau);
    ++count;
  }
  d.diag.nodes_bottom_up = count;
}

void dca_top_down(const Model& m, Data& d) noexcept {
  const auto& t = m.tree;
  for (int root : t.roots)
    for (int s = 0; s < t.handle_num[root]; ++s) d.f(root, s).setZero();
  std::int64_t count = 0;
  for (int node = 0; node < t.nnodes(); ++node) {
    if (t.is_leaf(node)) continue;
    dca_top_down_node(m, d, node);
    ++count;
  }
  d.diag.nodes_top_down = count;
  for (int i = 0; i < m.nv; ++i)
    if (!std::isfinite(d.qdd(i))) { ++d.diag.nonfinite; break; }
}

const Eigen::VectorXd& forward_dynamics(const Model& m, Data& d, const State& st) noexcept {
  forward_kinematics(m, d, st.q);
  body_dynamics_terms(m, d, st);
  dca_bottom_up(m, d, st);
  dca_top_down(m, d);
  return d.qdd;
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
