#include "tests/support/oracle.hpp"

#include <random>

#include <Eigen/Eigenvalues>

namespace haptree::testing {

namespace {

using V3 = Eigen::Matrix<LD, 3, 1>;
using M3 = Eigen::Matrix<LD, 3, 3>;
using V6 = Eigen::Matrix<LD, 6, 1>;
using M6 = Eigen::Matrix<LD, 6, 6>;
using MS = Eigen::Matrix<LD, 6, Eigen::Dynamic>;

M3 hat(const V3& a) {
  M3 s;
  s << 0, -a(2), a(1), a(2), 0, -a(0), -a(1), a(0), 0;
  return s;
}
V6 vx(const V6& v, const V6& m) {   // motion cross product
  V6 r;
  r.template head<3>() = v.template head<3>().cross(m.template head<3>());
  r.template tail<3>() = v.template head<3>().cross(m.template tail<3>()) +
                         v.template tail<3>().cross(m.template head<3>());
  return r;
}
V6 fx(const V6& v, const V6& f) {   // force cross product
  V6 r;
  r.template head<3>() = v.template head<3>().cross(f.template head<3>()) +
                         v.template tail<3>().cross(f.template tail<3>());
  r.template tail<3>() = v.template head<3>().cross(f.template tail<3>());
  return r;
}
M3 rot_of(const Eigen::VectorXd& q, int a) {
  Eigen::Quaternion<LD> qu((LD)q(a), (LD)q(a + 1), (LD)q(a + 2), (LD)q(a + 3));
  qu.normalize();
  return qu.toRotationMatrix();
}
M3 axis_angle(const V3& u, LD ang) {
  // Rodrigues in long double.
  const M3 K = hat(u);
  return M3::Identity() + std::sin(ang) * K + (1 - std::cos(ang)) * K * K;
}

}  // namespace

OracleResult oracle_forward_dynamics(const Model& m, const State& st,
                                     const std::vector<bool>& locked) {
  const int nb = m.nbodies;
  std::vector<M3> R(nb, M3::Identity());
  std::vector<V3> p(nb, V3::Zero());
  std::vector<MS> S(nb);
  std::vector<M6> I(nb, M6::Zero());
  std::vector<V6> v(nb, V6::Zero()), a(nb, V6::Zero()), f(nb, V6::Zero());
  const V3 g = m.gravity.cast<LD>();
  // Coordinates about o = body 1's joint point instead of the world origin: a model translated by
  // D keeps its positions relative to o exactly (offset − o of two doubles is exact in long
  // double), so the oracle's own error does not grow like (D/L)²·ε_LD (1e-5 at 10⁶ m).
  const V3 o = nb > 1 ? V3(m.joint_offset[1].cast<LD>()) : V3(V3::Zero());

  for (int k = 1; k < nb; ++k) {
    const int par = m.parent[k], qa = m.q_adr[k];
    const M3 Rj = R[par] * m.joint_rotation[k].cast<LD>();
    V3 local = m.joint_offset[k].cast<LD>();
    if (par == 0) local -= o;   // the ground's frame is the world's (R_0 = 1)
    const V3 ax = m.joint_axis[k].cast<LD>();
    switch (m.joint_type[k]) {
      case JointType::kRevolute: R[k] = Rj * axis_angle(ax, (LD)st.q(qa)); break;
      case JointType::kPrismatic:
        R[k] = Rj;
        local += m.joint_rotation[k].cast<LD>() * (ax * (LD)st.q(qa));
        break;
      case JointType::kSpherical: R[k] = Rj * rot_of(st.q, qa); break;
      case JointType::kFree:
        R[k] = Rj * rot_of(st.q, qa + 3);
        local += m.joint_rotation[k].cast<LD>() * st.q.segment<3>(qa).cast<LD>();
        break;
      case JointType::kFixed: R[k] = Rj; break;
    }
    p[k] = p[par] + R[par] * local;
    // Motion subspace at the world origin: rotation about an axis through p is [u; p × u].
    const int n = m.v_num[k];
    S[k].setZero(6, n);
    switch (m.joint_type[k]) {
      case JointType::kRevolute: {
        const V3 u = R[k] * ax;
        S[k].col(0) << u, p[k].cross(u);
        break;
      }
      case JointType::kPrismatic: S[k].col(0) << V3::Zero(), R[k] * ax; break;
      case JointType::kSpherical:
        S[k].topRows(3) = R[k];
        S[k].bottomRows(3) = hat(p[k]) * R[k];
        break;
      case JointType::kFree:
        S[k].block(0, 0, 3, 3) = R[k];
        S[k].block(3, 0, 3, 3) = hat(p[k]) * R[k];
        S[k].block(3, 3, 3, 3) = R[k];
        break;
      case JointType::kFixed: break;
    }
    // Inertia at the world origin from (m, COM, Ic) in long double.
    const LD mass = m.mass[k];
    const V3 c = p[k] + R[k] * m.com[k].cast<LD>();
    const M3 Ic = R[k] * m.inertia[k].cast<LD>() * R[k].transpose();
    const M3 C = hat(c);
    I[k].topLeftCorner(3, 3) = Ic + mass * C * C.transpose();
    I[k].topRightCorner(3, 3) = mass * C;
    I[k].bottomLeftCorner(3, 3) = mass * C.transpose();
    I[k].bottomRightCorner(3, 3) = mass * M3::Identity();
  }

  // RNEA with q̈ = 0 and the fictitious base acceleration −g: f_k is then the bias force.
  std::vector<V6> cJ(nb, V6::Zero());
  a[0] << V3::Zero(), -g;
  for (int k = 1; k < nb; ++k) {
    const int par = m.parent[k], n = m.v_num[k];
    V6 sq = V6::Zero();
    if (n > 0) sq = S[k] * st.qd.segment(m.v_adr[k], n).cast<LD>();
    v[k] = v[par] + sq;
    cJ[k] = vx(v[k], sq);
    a[k] = a[par] + cJ[k];
    // External force given at r_k = p_k with world axes → at o.
    const V6 fe = st.f_ext[k].cast<LD>();
    V6 fe0;
    fe0 << fe.template head<3>() + p[k].cross(fe.template tail<3>()), fe.template tail<3>();
    f[k] = I[k] * a[k] + fx(v[k], I[k] * v[k]) - fe0;
  }
  std::vector<M6> Ic = I;
  for (int k = nb - 1; k >= 1; --k) {
    const int par = m.parent[k];
    if (par > 0) {
      f[par] += f[k];
      Ic[par] += Ic[k];
    }
  }
  // Mass matrix: H_ij = S_iᵀ Ic_i S_j for j an ancestor of i (or i itself).
  MatXL H = MatXL::Zero(m.nv, m.nv);
  VecXL C = VecXL::Zero(m.nv);
  for (int i = 1; i < nb; ++i) {
    const int ni = m.v_num[i];
    if (ni == 0) continue;
    const int ai = m.v_adr[i];
    C.segment(ai, ni) = S[i].transpose() * f[i];
    const MS F = Ic[i] * S[i];
    for (int j = i; j > 0; j = m.parent[j]) {
      const int nj = m.v_num[j];
      if (nj == 0) continue;
      const int aj = m.v_adr[j];
      const MatXL blk = F.transpose() * S[j];
      H.block(ai, aj, ni, nj) = blk;
      if (j != i) H.block(aj, ai, nj, ni) = blk.transpose();
    }
  }
  // Solve only the free DOFs.
  std::vector<int> freeidx;
  for (int i = 0; i < m.nv; ++i)
    if (locked.empty() || !locked[i]) freeidx.push_back(i);
  const int nf = static_cast<int>(freeidx.size());
  MatXL Hf(nf, nf);
  VecXL rhs(nf);
  for (int x = 0; x < nf; ++x) {
    rhs(x) = (LD)st.tau(freeidx[x]) - C(freeidx[x]);
    for (int y = 0; y < nf; ++y) Hf(x, y) = H(freeidx[x], freeidx[y]);
  }
  const VecXL sol = Hf.llt().solve(rhs);
  VecXL qdd = VecXL::Zero(m.nv);
  for (int x = 0; x < nf; ++x) qdd(freeidx[x]) = sol(x);

  OracleResult out;
  out.qdd = qdd.cast<double>();
  out.H = H;
  out.C = C;
  // True body accelerations (no gravity trick), expressed at r_k.
  std::vector<V6> acc(nb, V6::Zero());
  out.body_acc.assign(nb, Vec6::Zero());
  out.r.assign(nb, Vec3::Zero());
  for (int k = 1; k < nb; ++k) {
    const int n = m.v_num[k];
    acc[k] = acc[m.parent[k]] + cJ[k];
    if (n > 0) acc[k] += S[k] * qdd.segment(m.v_adr[k], n);
    V6 at;
    at << acc[k].template head<3>(),
        acc[k].template tail<3>() + acc[k].template head<3>().cross(p[k]);
    out.body_acc[k] = at.cast<double>();
    out.r[k] = (p[k] + o).cast<double>();
  }
  return out;
}

namespace {
std::vector<int> free_dofs(int nv, const std::vector<bool>& locked) {
  std::vector<int> f;
  for (int i = 0; i < nv; ++i)
    if (locked.empty() || !locked[i]) f.push_back(i);
  return f;
}
}  // namespace

double mass_matrix_condition(const OracleResult& r, const std::vector<bool>& locked) {
  const auto f = free_dofs(static_cast<int>(r.H.rows()), locked);
  const int n = static_cast<int>(f.size());
  if (n == 0) return 1;
  Eigen::MatrixXd Hf(n, n);
  for (int x = 0; x < n; ++x)
    for (int y = 0; y < n; ++y) Hf(x, y) = static_cast<double>(r.H(f[x], f[y]));
  const Eigen::VectorXd ev = Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(Hf).eigenvalues();
  // The smallest eigenvalue from a double eigensolver is good to ~ε·λ_max: clamp there.
  return ev(n - 1) / std::max(ev(0), ev(n - 1) * 1e-16);
}

double qdd_error_bound(const OracleResult& r, const State& st, double c,
                       const std::vector<bool>& locked) {
  const auto f = free_dofs(static_cast<int>(r.H.rows()), locked);
  LD tn = 0, cn = 0, dn = 0;
  for (int i : f) {
    const LD t = st.tau(i), cc = r.C(i);
    tn += t * t;
    cn += cc * cc;
    dn += (t - cc) * (t - cc);
  }
  const double cancel =
      dn > 0 ? static_cast<double>((std::sqrt(tn) + std::sqrt(cn)) / std::sqrt(dn)) : 1.0;
  return c * static_cast<double>(std::max<std::size_t>(f.size(), 1)) * kEps *
         mass_matrix_condition(r, locked) * std::max(1.0, cancel);
}

double dca_error_bound(const Model& m, const State& st, double c, const std::vector<bool>& locked) {
  return qdd_error_bound(oracle_forward_dynamics(m, st, locked), st, c, locked);
}

double rel_err(const Eigen::VectorXd& a, const Eigen::VectorXd& b, double floor) {
  return (a - b).norm() / std::max(b.norm(), floor);
}

State random_state(const Model& m, unsigned seed, double vel_scale) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  State st(m);
  for (int k = 1; k < m.nbodies; ++k) {
    const int a = m.q_adr[k];
    switch (m.joint_type[k]) {
      case JointType::kRevolute:
      case JointType::kPrismatic: st.q(a) = u(rng); break;
      case JointType::kSpherical:
      case JointType::kFree: {
        const int qa = m.joint_type[k] == JointType::kFree ? a + 3 : a;
        if (m.joint_type[k] == JointType::kFree)
          for (int i = 0; i < 3; ++i) st.q(a + i) += 0.3 * u(rng);
        Eigen::Vector4d qq(u(rng), u(rng), u(rng), u(rng));
        qq.normalize();
        st.q.segment<4>(qa) = qq;
        break;
      }
      case JointType::kFixed: break;
    }
  }
  for (int i = 0; i < m.nv; ++i) {
    st.qd(i) = vel_scale * u(rng);
    st.tau(i) = u(rng);
  }
  for (int k = 1; k < m.nbodies; ++k)
    for (int i = 0; i < 6; ++i) st.f_ext[k](i) = 0.5 * u(rng);
  return st;
}

}  // namespace haptree::testing
