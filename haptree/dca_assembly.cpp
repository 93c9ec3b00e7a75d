// The mobility form of the DCA (docs/algorithms.md §5, §7). A node's articulated-body equation
// over its handles x, y is a_x = Σ_y Φ_xy f_y + b_x, each block at its handle's point.
//   Leaf body k (§5.1): Φ_xy = M_x I_k⁻¹ M_yᵀ, b_x = M_x I_k⁻¹ p_k, M_x = M(r_k → handle x);
//   the ground: Φ = 0, b = 0.
//   Assembly of C from P (joint J at P's slot j) and Q (at Q's slot k) (§5.2):
//     Φ̂ = Φ^P_jj + Φ^Q_kk,  W = T (Tᵀ Φ̂ T)⁻¹ Tᵀ,  β = W (c_J − b^Q_k + b^P_j) + (1 − W Φ̂) D τ_J,
//     Φ^C_xy = Φ_xy − Z_xᵀ Z_y over the surviving handles (Φ_xy = 0 across the children), with
//     W = XᵀX, X = L⁻¹Tᵀ (L the Cholesky factor of Tᵀ Φ̂ T), Z_x = X Φ^P_jx on P's side and
//     −X Φ^Q_kx on Q's;  b^C_i = b^P_i − Φ^P_ij β,  b^C_l = b^Q_l + Φ^Q_lk β.
//   Disassembly (§7): f_c = W (s_P − s_Q) + β, s_P = Σ_i Φ^P_ji f_i, s_Q = Σ_l Φ^Q_kl f_l; P gets
//   f_j = −f_c, Q gets f_k = f_c, and q̈_J = Dᵀ(Φ̂ f_c + s_Q − s_P + b^Q_k − b^P_j − c_J).
// A pivot of Tᵀ Φ̂ T below 1e-13 of its diagonal entry is dropped and counted (§14). A node next
// to a light leaf body, or inside a welded cluster, takes the form of dca_light_leaf.cpp or
// dca_inertia_form.cpp instead.
#include <algorithm>
#include <cmath>

#include "haptree/dca_detail.hpp"

namespace haptree {

namespace {

// In-place M(d) A (bottom rows − [d]× top rows, i.e. + top × d per column) and A M(d)ᵀ (right
// columns + left columns [d]×), for the leaf: whole-column work instead of 3×3 skew products.
inline void shift_rows_in_place(Mat6& A, const Vec3& dv) {
  for (int c = 0; c < 6; ++c) A.col(c).tail<3>() += A.col(c).head<3>().cross(dv);
}
inline void shift_cols_in_place(Mat6& A, const Vec3& dv) {
  const Vec6 l0 = A.col(0), l1 = A.col(1), l2 = A.col(2);
  A.col(3) += dv.z() * l1 - dv.y() * l2;
  A.col(4) += dv.x() * l2 - dv.z() * l0;
  A.col(5) += dv.y() * l0 - dv.x() * l1;
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
  // Φ(x, y) = M_x I⁻¹ M_yᵀ, shifted in place column by column (no 6×6 products, no temporaries).
  const Mat6& Ii = d.Iinv[k];
  const Vec6 a0 = Ii * d.p_bias[k];
  for (int x = 0; x < h; ++x) {
    const int jx = t.handle(node, x);
    const bool own_x = jx == k;
    Mat6 MxI = Ii;
    if (!own_x) shift_rows_in_place(MxI, d.d[jx]);
    for (int y = x; y < h; ++y) {
      const int jy = t.handle(node, y);
      BlockMap out = d.Phi(node, h, x, y);
      if (jy == k) {
        out = MxI;
      } else {
        Mat6 blk = MxI;
        shift_cols_in_place(blk, d.d[jy]);
        out = blk;
      }
      if (y != x) d.Phi(node, h, y, x) = out.transpose();
    }
    d.b(node, x) = own_x ? a0 : shift_motion(a0, d.d[jx]);
  }
}

namespace {

// SIMD-friendly layout: a 6-vector sits in the top of an 8-row column whose rows 6, 7
// are zero, so one column is one AVX-512 register (two AVX2, four SSE2 ones) and a product with a
// 6×N matrix is N·6 broadcast multiply-adds over whole columns. A 6-row column fits no packet
// (Eigen then falls back to 2-wide or scalar code; 5-row ones are always scalar).
template <int N>
using Pad = Eigen::Matrix<double, 8, N>;

template <typename Block>
inline Pad<6> pad_rows(const Block& B) {
  Pad<6> P;
  P.template topRows<6>() = B;
  P.template bottomRows<2>().setZero();
  return P;
}

// W = T (Tᵀ Φ̂ T)^{-1} Tᵀ = Xᵀ X with X = L^{-1} Tᵀ, L the Cholesky factor of A = Tᵀ Φ̂ T (nc × nc;
// only its lower triangle is read). Tp: T padded; Xt = Xᵀ padded (8 × nc) goes to the block
// assembly. Returns false when a pivot is not positive relative to its own diagonal entry (a
// modelling error, §14.4).
template <int NC>
bool constraint_inverse(const Eigen::Matrix<double, NC, NC>& A, const Pad<NC>& Tp, Mat6& W,
                        Pad<NC>& Xt) {
  bool ok = true;
  double L[NC][NC] = {}, Linv[NC];
  for (int j = 0; j < NC; ++j) {
    double s = A(j, j);
    for (int k = 0; k < j; ++k) s -= L[j][k] * L[j][k];
    // A pivot that is not positive relative to its diagonal entry is round-off of a singular or
    // indefinite system (e.g. two coaxial joints around a near-massless rod): that constraint
    // direction is dropped (pseudo-inverse) and reported, instead of dividing by noise, which
    // overflowed W. The pivot's round-off is O(ε·A_jj) (Cholesky: s = A_jj − Σ L_jk² ≥ 0 with
    // every term ≤ A_jj), so A_jj is its scale, not the trace: Tᵀ Φ̂ T mixes units (1/(kg m²),
    // 1/kg), and at a 1 km weld off a light body on a moving joint the trace (≈ 1e8, the far
    // point's translational mobility) dropped the heavy welded side's rotational pivot (≈ 1e-7,
    // its own scale): O(1) errors, 1.5e3 × the bound. A pivot kept by the old test
    // is kept by this one (A_jj ≤ trace): where none was dropped, the bits are unchanged.
    const double tol = 1e-13 * A(j, j);
    const bool drop = !(s > tol);
    if (drop) ok = false;
    L[j][j] = drop ? 0.0 : std::sqrt(s);
    const double inv = drop ? 0.0 : 1.0 / L[j][j];
    Linv[j] = inv;
    for (int i = j + 1; i < NC; ++i) {
      double v = A(i, j);
      for (int k = 0; k < j; ++k) v -= L[i][k] * L[j][k];
      L[i][j] = v * inv;
    }
  }
  // Row i of X (column i of Xt), all six columns at once: forward substitution on whole columns,
  // scaled by the reciprocal pivot (0 for a dropped direction) instead of a divide per column.
  for (int i = 0; i < NC; ++i) {
    Pad<1> v = Tp.col(i);
    for (int k = 0; k < i; ++k) v -= L[i][k] * Xt.col(k);
    Xt.col(i) = Linv[i] * v;
  }
  // W = Xt Xtᵀ (entries (r, c) and (c, r) are the same sums with the factors swapped).
  const Pad<6> Wp = Xt.lazyProduct(Xt.template topRows<6>().transpose());
  W = Wp.template topRows<6>();
  return ok;
}

// A = Tᵀ Φ̂ T (lower triangle) and T padded for a 1-DOF joint with unit axis u (S = [u; 0] for a
// revolute, [0; u] for a prismatic joint) and T = [e1 e2 | I] on the constrained half-spaces:
// 3×3 block work instead of two 6×6×5 products.
inline void one_dof_system(const Mat6& Ph, const Vec3& u, bool rev, Eigen::Matrix<double, 5, 5>& A,
                           Pad<5>& Tp) {
  Vec3 e1, e2;
  orthonormal_pair(u, e1, e2);
  Eigen::Matrix<double, 3, 2> E;
  E << e1, e2;
  Tp.setZero();
  if (rev) {   // T = [[E, 0], [0, I]]
    Tp.block<3, 2>(0, 0) = E;
    Tp.block<3, 3>(3, 2).setIdentity();
    A.block<2, 2>(0, 0) = E.transpose() * Ph.topLeftCorner<3, 3>() * E;
    A.block<3, 2>(2, 0) = Ph.bottomLeftCorner<3, 3>() * E;
    A.block<3, 3>(2, 2) = Ph.bottomRightCorner<3, 3>();
  } else {     // T = [[I, 0], [0, E]]
    Tp.block<3, 3>(0, 0).setIdentity();
    Tp.block<3, 2>(3, 3) = E;
    A.block<3, 3>(0, 0) = Ph.topLeftCorner<3, 3>();
    A.block<2, 3>(3, 0) = E.transpose() * Ph.bottomLeftCorner<3, 3>();
    A.block<2, 2>(3, 3) = E.transpose() * Ph.bottomRightCorner<3, 3>() * E;
  }
}

template <int NC>
bool constraint_inverse(const Mat6& Ph, const JointMat& T, Mat6& W, Pad<NC>& Xt) {
  const Eigen::Matrix<double, 6, NC> Tf = T;
  const Eigen::Matrix<double, NC, NC> A = Tf.transpose() * Ph * Tf;
  Pad<NC> Tp;
  Tp.template topRows<6>() = Tf;
  Tp.template bottomRows<2>().setZero();
  return constraint_inverse<NC>(A, Tp, W, Xt);
}

// X of the last assemble_joint (Xᵀ padded, 8 × nc; nc = 0 leaves zeros: W = 0).
struct JointX {
  alignas(64) double buf[8 * 6];
  template <int NC>
  Eigen::Map<Pad<NC>, Eigen::Aligned64> get() { return Eigen::Map<Pad<NC>, Eigen::Aligned64>(buf); }
};

// The joint part of §5.2: W, τ̃ and β of `node` from its children's Φ and b. Returns nc, the
// number of constraint directions; Xᵀ padded (W = XᵀX, X = L⁻¹Tᵀ) goes to Xb.
int assemble_joint(const Model& m, Data& d, int node, const Eigen::VectorXd& tau,
                   JointX& Xb) noexcept {
  const auto& t = m.tree;
  const int P = t.P[node], Q = t.Q[node], J = t.joint[node];
  const int j = t.slot_j[node], k = t.slot_k[node];
  const int hP = t.handle_num[P], hQ = t.handle_num[Q];
  const Mat6 Phat = d.Phi(P, hP, j, j) + d.Phi(Q, hQ, k, k);

  Mat6& W = d.W[node];
  Vec6& taut = d.taut[node];
  int nc = 0;
  bool ok = true;
  const JointType type = m.joint_type[J];
  if (type == JointType::kRevolute || type == JointType::kPrismatic) {
    // 1 DOF (the common case): structured Tᵀ Φ̂ T, no joint_subspaces matrices.
    const bool rev = type == JointType::kRevolute;
    const Vec6& S = d.S[J];
    Eigen::Matrix<double, 5, 5> A;
    Pad<5> Tp, Xt;
    one_dof_system(Phat, rev ? Vec3(S.head<3>()) : Vec3(S.tail<3>()), rev, A, Tp);
    ok = constraint_inverse<5>(A, Tp, W, Xt);
    Xb.get<5>() = Xt;
    nc = 5;
    const Vec6 Dtau = S * tau(m.v_adr[J]);
    taut = Dtau - W * (Phat * Dtau);
  } else {
    JointMat S, T, D;
    joint_subspaces(m, d, J, S, T, D);
    nc = static_cast<int>(T.cols());
    switch (nc) {
      case 0: W.setZero(); break;
      case 3: {
        Pad<3> Xt;
        ok = constraint_inverse<3>(Phat, T, W, Xt);
        Xb.get<3>() = Xt;
        break;
      }
      case 6: {
        Pad<6> Xt;
        ok = constraint_inverse<6>(Phat, T, W, Xt);
        Xb.get<6>() = Xt;
        break;
      }
      default: W.setZero(); ok = false; nc = 0;   // no joint type has 1, 2 or 4 constraints
    }
    const int nJ = static_cast<int>(S.cols());
    if (nJ > 0) {
      const Vec6 Dtau = D * tau.segment(m.v_adr[J], nJ);
      taut = Dtau - W * (Phat * Dtau);
    } else {
      taut.setZero();
    }
  }
  if (!ok) {   // atomic: parallel passes (set_dca_threads) may assemble two bad nodes at once
    __atomic_fetch_add(&d.diag.singular_pivots, 1, __ATOMIC_RELAXED);
    __atomic_store_n(&d.diag.last_bad_node, node, __ATOMIC_RELAXED);
  }
  d.beta[node] = W * (d.c[J] - d.b(Q, k) + d.b(P, j)) + taut;
  return nc;
}

// Blocks of Φ_C for nc constraint directions: with Z_x = X Φ(P, j, x) for P's surviving handles
// and Z_x = −X Φ(Q, k, x) for Q's, Φ_C(x, y) = Φ_child(x, y) − Z_xᵀ Z_y (Φ_child = 0 across
// children): Φ_xj W Φ_jy = (XΦ_jx)ᵀ(XΦ_jy) without forming two 6×6 products per block. Held as
// Z_xᵀ = Φ_xj Xᵀ in the padded layout, so both products run over whole 8-row columns; a diagonal
// block is written from its upper triangle, averaged with the lower one (symmetric by
// construction).
constexpr int kMaxZHandles = 8;

template <int NC>
void assemble_blocks(const Model& m, Data& d, int node, const Pad<NC>& Xt) {
  const auto& t = m.tree;
  const int P = t.P[node], Q = t.Q[node];
  const int j = t.slot_j[node], k = t.slot_k[node];
  const int hP = t.handle_num[P], hQ = t.handle_num[Q], hC = t.handle_num[node];
  const Eigen::Matrix<double, 6, NC> XT = Xt.template topRows<6>();   // Xᵀ
  Pad<NC> Z[kMaxZHandles];
  int side[kMaxZHandles], slot[kMaxZHandles];
  int n = 0;
  for (int i = 0; i < hP; ++i)
    if (i != j) {
      Z[n].noalias() = pad_rows(d.Phi(P, hP, i, j)).lazyProduct(XT);
      side[n] = P;
      slot[n++] = i;
    }
  for (int l = 0; l < hQ; ++l)
    if (l != k) {
      Z[n].noalias() = -pad_rows(d.Phi(Q, hQ, l, k)).lazyProduct(XT);
      side[n] = Q;
      slot[n++] = l;
    }
  for (int c = 0; c < hC; ++c) {
    const int hs = side[c] == P ? hP : hQ;
    for (int c2 = c; c2 < hC; ++c2) {
      Pad<6> B;
      if (side[c2] == side[c]) B = pad_rows(d.Phi(side[c], hs, slot[c], slot[c2]));
      else B.setZero();
      B.noalias() -= Z[c].lazyProduct(Z[c2].template topRows<6>().transpose());
      BlockMap out = d.Phi(node, hC, c, c2);
      if (c2 == c) {
        for (int q = 0; q < 6; ++q)
          for (int r = 0; r <= q; ++r) out(r, q) = out(q, r) = 0.5 * (B(r, q) + B(q, r));
      } else {
        out = B.topRows<6>();
        d.Phi(node, hC, c2, c) = B.topRows<6>().transpose();
      }
    }
  }
}

// The previous general form (two 6×6 products per block), for nodes with many handles.
void assemble_blocks_general(const Model& m, Data& d, int node) {
  const auto& t = m.tree;
  const int P = t.P[node], Q = t.Q[node];
  const int j = t.slot_j[node], k = t.slot_k[node];
  const int hP = t.handle_num[P], hQ = t.handle_num[Q], hC = t.handle_num[node];
  const Mat6& W = d.W[node];
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
    ++cl;
  }
}

}  // namespace

namespace detail {

void assemble_joint_terms(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) noexcept {
  JointX X;
  assemble_joint(m, d, node, tau, X);
}

}  // namespace detail

void dca_assemble(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) noexcept {
  const auto& t = m.tree;
  d.cluster_live[node] = 0;
  if (!d.leaf_side.empty()) d.leaf_side[node] = 0;
  if (const int side = detail::leaf_form_side(m, d, node)) {
    detail::leaf_form_assemble(m, d, node, side, tau);
    return;
  }
  JointX X;
  const int nc = assemble_joint(m, d, node, tau, X);
  const int P = t.P[node], Q = t.Q[node];
  const int j = t.slot_j[node], k = t.slot_k[node];
  const int hP = t.handle_num[P], hQ = t.handle_num[Q], hC = t.handle_num[node];

  if (hC <= kMaxZHandles) {
    switch (nc) {
      case 0:
        std::fill(X.buf, X.buf + 8, 0.0);
        assemble_blocks<1>(m, d, node, X.get<1>());
        break;
      case 3: assemble_blocks<3>(m, d, node, X.get<3>()); break;
      case 5: assemble_blocks<5>(m, d, node, X.get<5>()); break;
      default: assemble_blocks<6>(m, d, node, X.get<6>()); break;
    }
  } else {
    assemble_blocks_general(m, d, node);
  }

  // Surviving handles: C slots 0..hP-2 come from P' in order, then Q'.
  const Vec6& beta = d.beta[node];
  int ci = 0;
  for (int i = 0; i < hP; ++i)
    if (i != j) {
      d.b(node, ci++).noalias() = d.b(P, i) - d.Phi(P, hP, i, j) * beta;
    }
  for (int l = 0; l < hQ; ++l)
    if (l != k) {
      d.b(node, ci++).noalias() = d.b(Q, l) + d.Phi(Q, hQ, l, k) * beta;
    }
}

void dca_top_down_node(const Model& m, Data& d, int node) noexcept {
  const auto& t = m.tree;
  if (d.cluster_live[node]) {
    detail::top_down_inertia_form(m, d, node);
    return;
  }
  if (!d.leaf_side.empty() && d.leaf_side[node]) {
    detail::leaf_form_top_down(m, d, node, d.leaf_side[node]);
    return;
  }
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
    const int a = m.v_adr[J];
    const Vec6 rest = (sQ - sP) + d.b(Q, k) - d.b(P, j) - d.c[J];
    if (m.joint_type[J] == JointType::kRevolute || m.joint_type[J] == JointType::kPrismatic) {
      // 1 DOF: Sᵀ Φ̂ f_c from the three rows of Φ̂ that S selects, instead of all of Φ̂ f_c.
      const Vec6& S = d.S[J];
      const bool rev = m.joint_type[J] == JointType::kRevolute;
      const Vec3 u = rev ? Vec3(S.head<3>()) : Vec3(S.tail<3>());
      const int r0 = rev ? 0 : 3;
      const Vec6 SPh = d.Phi(P, hP, j, j).middleRows<3>(r0).transpose() * u +
                       d.Phi(Q, hQ, k, k).middleRows<3>(r0).transpose() * u;
      d.qdd(a) = SPh.dot(fc) + S.dot(rest);
      return;
    }
    const Vec6 arel = (d.Phi(P, hP, j, j) + d.Phi(Q, hQ, k, k)) * fc + rest;
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

}  // namespace haptree
