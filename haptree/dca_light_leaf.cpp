// The light-leaf form of a node (docs/accuracy_and_stability.md), for a child L that is a leaf body
// (not the ground) at least twice as mobile at the joint J as the other child O (traces of Φ).
// Joining a leaf body L to a subassembly O across J by the mobility formula Φ_L − Φ_L W Φ_L
// subtracts two mobilities of size 1/I_L to leave one of size ~1/I_O: next to a light body (the
// Cα–H body, smallest principal inertia 1000× below its neighbours') it loses digits like
// ‖Φ_L‖/‖Φ_C‖, and q̈ loses them twice (Φ_C and W both carry the error): err ∝ r² at a light-body
// ratio r (`stress_report --sections light`). In the spirit of Featherstone's more accurate DCA
// (1999, part 2: keep an inertia where its inverse would cancel), the leaf enters through its
// inertia K at the joint point, and O through B = Tᵀ Φ_O T: with a = Sα + Tγ ([S T] orthonormal),
// f_J = Tλ + Sτ' on L and Tᵀ(a − a_O − c') = 0,
//   λ = E(K_ts α + K_tt g − Tᵀ(f_L + p)),  E = (1 + K_tt B)⁻¹,  γ = g − Bλ,
//   N α = V(f_L + p) + τ' − K_st Eᵀ g,     N = K_ss − K_st G K_ts,  G = B E,  V = Sᵀ − K_st G Tᵀ,
// g = Tᵀ(s_O + b_O + c' − B̂ S τ'). Every matrix formed is a sum of like-signed terms when L is the
// more mobile side (K_tt B small): L's mobility at J is R = Vᵀ N⁻¹ V + T G Tᵀ, the W of the
// mobility form is Y = T E (K_tt − K_ts N⁻¹ K_st Eᵀ) Tᵀ, and ∂f_J/∂f_L = F = T E (K_ts N⁻¹ V − Tᵀ).
// Signs: σ = +1 when L = Q, −1 when L = P (c' = σc, τ' = στ, q̈' = σq̈, f_J = σ f_c).
// Back-substitution: f_J = F f_L + Y s_O + f_J0, then q̈' from L's joint-space equation
// K_ss q̈' = Sᵀ(f_J + f_L + p) − Sᵀ K (a_O + c').
#include <cmath>
#include <type_traits>

#include "haptree/dca_detail.hpp"

namespace haptree {

namespace {

using DynVec = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, 6, 1>;

struct LeafSides {
  int L, O, sL, sO, b;   // leaf node, other node, their slots at J, the leaf's body
  double sigma;
};

inline LeafSides leaf_sides(const Model& m, int node, int side) {
  const auto& t = m.tree;
  const bool q = side == 2;
  const int L = q ? t.Q[node] : t.P[node], O = q ? t.P[node] : t.Q[node];
  return {L, O, q ? t.slot_k[node] : t.slot_j[node], q ? t.slot_j[node] : t.slot_k[node],
          t.body[L], q ? 1.0 : -1.0};
}

// Offset from the joint point r_J of the point of handle joint jx of leaf body b.
inline Vec3 leaf_handle_offset(const Data& d, int b, int J, int jx) {
  const Vec3 ex = jx == b ? Vec3::Zero() : d.d[jx];
  return b == J ? ex : Vec3(ex - d.d[J]);
}

// L's inertia and bias force at the joint point.
inline void leaf_inertia_at_joint(const Data& d, int b, int J, Mat6& K, Vec6& p) {
  if (b == J) {
    K = d.I[b];
    p = d.p_bias[b];
  } else {   // L holds p(J): r_J = r_b + d_J
    const Mat6 X = motion_shift_matrix(-d.d[J]);
    K = X.transpose() * d.I[b] * X;
    K = 0.5 * (K + K.transpose());
    p = shift_force(d.p_bias[b], d.d[J]);
  }
}

// Slot c of node C -> (child, child slot): C's slots are P's without slot_j, then Q's without slot_k.
inline void child_slot(const AssemblyTree& t, int node, int c, int& ch, int& s) {
  const int hP = t.handle_num[t.P[node]];
  if (c < hP - 1) {
    ch = t.P[node];
    s = c < t.slot_j[node] ? c : c + 1;
  } else {
    ch = t.Q[node];
    const int l = c - (hP - 1);
    s = l < t.slot_k[node] ? l : l + 1;
  }
}

// 0: mobility form; 1: P is a light leaf; 2: Q is. The leaf form is used for a leaf body (not the

}  // namespace

namespace detail {

// ground) that is the more mobile side of a joint with constraints (nc = 0: W = 0, nothing cancels).
int leaf_form_side(const Model& m, const Data& d, int node) {
  const auto& t = m.tree;
  if (d.leaf_adr.empty() || d.leaf_adr[node] < 0) return 0;
  const int J = t.joint[node];
  if (m.joint_type[J] == JointType::kFree) return 0;
  const int P = t.P[node], Q = t.Q[node];
  const double trP = d.Phi(P, t.handle_num[P], t.slot_j[node], t.slot_j[node]).trace();
  const double trQ = d.Phi(Q, t.handle_num[Q], t.slot_k[node], t.slot_k[node]).trace();
  const bool lp = t.is_leaf(P) && t.body[P] != 0, lq = t.is_leaf(Q) && t.body[Q] != 0;
  // Only for a leaf at least twice as mobile as the other side: between comparable bodies the
  // mobility form is as accurate and 2–3× cheaper (measured: a threshold of 1 doubled dca_bench's
  // time and cost the binary tree 63 a factor 8 in error; 2 keeps bacteriorhodopsin's gain).
  constexpr double kLeafRatio = 2.0;
  if (lq && trQ > kLeafRatio * trP) return 2;
  if (lp && trP > kLeafRatio * trQ) return 1;
  return 0;
}

}  // namespace detail

namespace {

// Fixed-size matrix types for the kernel (Dynamic: at most 6, the general joint).
template <int R, int C>
using KMat = Eigen::Matrix<double, R, C,
                           (R == 1 && C != 1) ? Eigen::RowMajor : Eigen::ColMajor,
                           R == Eigen::Dynamic ? 6 : R, C == Eigen::Dynamic ? 6 : C>;

// Inverse of a small fixed-size matrix by Gauss-Jordan elimination with partial (row) pivoting: the
// pivoting of Eigen's PartialPivLU, without the general blocked triangular solves its inverse()
// runs at these sizes (which cost more than the factorisation; the light leaf's hot spot).
template <int N>
Eigen::Matrix<double, N, N> pivoted_inverse(Eigen::Matrix<double, N, N> A) {
  Eigen::Matrix<double, N, N> X = Eigen::Matrix<double, N, N>::Identity();
  for (int c = 0; c < N; ++c) {
    int piv = c;
    for (int r = c + 1; r < N; ++r)
      if (std::abs(A(r, c)) > std::abs(A(piv, c))) piv = r;
    if (piv != c) {
      A.row(c).swap(A.row(piv));
      X.row(c).swap(X.row(piv));
    }
    const double inv = 1.0 / A(c, c);
    A.row(c) *= inv;
    X.row(c) *= inv;
    for (int r = 0; r < N; ++r) {
      if (r == c) continue;
      const double f = A(r, c);
      A.row(r) -= f * A.row(c);
      X.row(r) -= f * X.row(c);
    }
  }
  return X;
}

// The leaf-form kernel for nJ = NJ, nc = NC (Eigen::Dynamic for both: any joint). Writes R, Y, F
// and the bias terms f_J0 and a_L0 (no handle forces). Fixed sizes for the revolute/prismatic case
// are what make the form cheap: the dynamic-size blocks and LU cost it ~1.6x.
template <int NJ, int NC>
void leaf_form_kernel(const Mat6& K, const Vec6& p, const Mat6& Bh, const JointMat& Sd,
                      const JointMat& Td, const KMat<NJ, 1>& taup, const Vec6& bO, const Vec6& cp,
                      Mat6& R, Mat6& Y, Mat6& F, Vec6& fJ0, Vec6& aL0, Mat6& Gtau) {
  const int nJ = static_cast<int>(Sd.cols()), nc = static_cast<int>(Td.cols());
  const KMat<6, NJ> S = Sd;
  const KMat<6, NC> T = Td;
  const KMat<6, NC> KT = K * T;
  const KMat<6, NJ> KS = K * S;
  const KMat<NC, NC> B = T.transpose() * Bh * T;
  const KMat<NC, NC> Ktt = T.transpose() * KT;
  const KMat<NJ, NC> Kst = S.transpose() * KT;
  const KMat<NJ, NJ> Kss = S.transpose() * KS;
  const KMat<NC, NC> IKB = KMat<NC, NC>::Identity(nc, nc) + Ktt * B;
  KMat<NC, NC> E;
  if constexpr (NC == Eigen::Dynamic) E = Eigen::PartialPivLU<KMat<NC, NC>>(IKB).inverse();
  else E = pivoted_inverse<NC>(IKB);
  KMat<NC, NC> G = B * E;
  G = 0.5 * (G + G.transpose());
  const KMat<NJ, NC> KstH = Kst * E.transpose();
  KMat<NJ, NJ> N = Kss - Kst * G * Kst.transpose();
  N = 0.5 * (N + N.transpose());
  // N⁻¹ applied to a right-hand side: for one DOF a division (Eigen's LLT would take its general
  // triangular-solve path for a 1×1 factor).
  const Eigen::LLT<KMat<NJ, NJ>> llt = NJ == 1 ? Eigen::LLT<KMat<NJ, NJ>>() : Eigen::LLT<KMat<NJ, NJ>>(N);
  const double inv_n = NJ == 1 ? 1.0 / N(0, 0) : 0.0;
  const auto nsolve = [&](const auto& rhs) {
    using Rhs = std::decay_t<decltype(rhs)>;
    Rhs out(rhs.rows(), rhs.cols());
    if constexpr (NJ == 1) out = inv_n * rhs;
    else out = llt.solve(rhs);
    return out;
  };
  const KMat<6, NC> TG = T * G;
  // V = Sᵀ − K_st G Tᵀ (nJ × 6), N⁻¹V, and the pieces of R, Y, F.
  const KMat<NJ, 6> V = KMat<NJ, 6>(S.transpose()) - Kst * TG.transpose();
  KMat<NJ, 6> NiV(nJ, 6);
  KMat<NJ, NC> NiKstH(nJ, nc);
  if (nJ > 0) {
    NiV = nsolve(V);
    NiKstH = nsolve(KstH);
  }
  R.noalias() = TG * T.transpose();
  if (nJ > 0) R.noalias() += V.transpose() * NiV;
  R = 0.5 * (R + R.transpose());
  const KMat<NC, NC> Ey = E * (Ktt - Kst.transpose() * NiKstH);
  const KMat<6, NC> TEy = T * Ey;
  Y.noalias() = TEy * T.transpose();
  Y = 0.5 * (Y + Y.transpose());
  const KMat<6, NC> TE = T * E;
  F.noalias() = -(TE * T.transpose());
  if (nJ > 0) F.noalias() += TE * (Kst.transpose() * NiV);
  // Bias (no handle forces): g0, α0, λ0, f_J0 and L's acceleration at r_J.
  const KMat<NC, 1> g0 = T.transpose() * (bO + cp - Bh * (S * taup));
  KMat<NJ, 1> alpha0(nJ);
  if (nJ > 0) alpha0 = nsolve(KMat<NJ, 1>(V * p + taup - KstH * g0));
  KMat<NC, 1> lam_rhs = Ktt * g0 - T.transpose() * p;
  if (nJ > 0) lam_rhs.noalias() += Kst.transpose() * alpha0;
  const KMat<NC, 1> lam0 = E * lam_rhs;
  fJ0.noalias() = T * lam0;
  aL0.noalias() = T * KMat<NC, 1>(g0 - B * lam0);
  if (nJ > 0) {
    fJ0.noalias() += S * taup;
    aL0.noalias() += S * alpha0;
  }
  // Gtau = ∂f_J0/∂τ' (first nJ columns; with p = c' = b_O = 0): the same lines for unit torques. The
  // correction pass of Data::refine rebuilds f_J0 = Y b_O + G τ' from it (bias_assemble_node).
  Gtau.setZero();
  if (nJ > 0) {
    const KMat<NC, NJ> Gg = -(T.transpose() * (Bh * S));
    const KMat<NJ, NJ> A = nsolve(KMat<NJ, NJ>(KMat<NJ, NJ>::Identity(nJ, nJ) - KstH * Gg));
    const KMat<NC, NJ> Lam = E * KMat<NC, NJ>(Ktt * Gg + Kst.transpose() * A);
    Gtau.leftCols(nJ) = T * Lam + S;
  }
}

}  // namespace

namespace detail {

void leaf_form_assemble(const Model& m, Data& d, int node, int side, const Eigen::VectorXd& tau) {
  const auto& t = m.tree;
  const LeafSides ls = leaf_sides(m, node, side);
  const int J = t.joint[node];
  const int hL = t.handle_num[ls.L], hO = t.handle_num[ls.O], hC = t.handle_num[node];
  JointMat S, T, Dj;
  joint_subspaces(m, d, J, S, T, Dj);
  const int nJ = static_cast<int>(S.cols());
  Mat6 K;
  Vec6 p;
  leaf_inertia_at_joint(d, ls.b, J, K, p);
  const Mat6 Bh = d.Phi(ls.O, hO, ls.sO, ls.sO);
  const Vec6 cp = ls.sigma * d.c[J];
  const Vec6 bO = d.b(ls.O, ls.sO);
  Mat6 R, Y;
  Mat6& F = d.leaf_F[d.leaf_adr[node]];
  Mat6& G = d.leaf_G[d.leaf_adr[node]];
  Vec6 fJ0, aL0;
  if (nJ == 1) {
    const KMat<1, 1> taup(ls.sigma * tau(m.v_adr[J]));
    leaf_form_kernel<1, 5>(K, p, Bh, S, T, taup, bO, cp, R, Y, F, fJ0, aL0, G);
  } else {
    const DynVec taup = nJ > 0 ? DynVec(ls.sigma * tau.segment(m.v_adr[J], nJ)) : DynVec(0);
    leaf_form_kernel<Eigen::Dynamic, Eigen::Dynamic>(K, p, Bh, S, T, taup, bO, cp, R, Y, F, fJ0,
                                                     aL0, G);
  }
  d.W[node] = Y;   // = T (Tᵀ Φ̂ T)⁻¹ Tᵀ: coupling and metric readers keep f_c = W(s_P − s_Q) + β
  d.beta[node] = ls.sigma * fJ0;
  d.taut[node].setZero();

  d.leaf_side[node] = static_cast<std::uint8_t>(side);

  // Φ_C and b_C: C's slots are P' then Q'.
  for (int c = 0; c < hC; ++c) {
    int ch, s;
    child_slot(t, node, c, ch, s);
    const bool lc = ch == ls.L;
    const Vec3 ec = lc ? leaf_handle_offset(d, ls.b, J, t.handle(ls.L, s)) : Vec3::Zero();
    const Mat6 Xc = lc ? Mat6::Zero() : Mat6(d.Phi(ls.O, hO, s, ls.sO));
    for (int c2 = c; c2 < hC; ++c2) {
      int ch2, s2;
      child_slot(t, node, c2, ch2, s2);
      const bool lc2 = ch2 == ls.L;
      const Vec3 e2 = lc2 ? leaf_handle_offset(d, ls.b, J, t.handle(ls.L, s2)) : Vec3::Zero();
      Mat6 blk;
      if (lc && lc2) {
        blk = shift_cols(shift_rows(ec, R), e2);
      } else if (!lc && !lc2) {
        blk = d.Phi(ls.O, hO, s, s2);
        blk.noalias() -= (Xc * Y) * d.Phi(ls.O, hO, ls.sO, s2);
      } else if (!lc) {   // O slot c, L slot c2
        blk = -shift_cols(Mat6(Xc * F), e2);
      } else {            // L slot c, O slot c2
        const Mat6 X2 = d.Phi(ls.O, hO, s2, ls.sO);
        blk = -shift_cols(Mat6(X2 * F), ec).transpose();
      }
      if (c2 == c) blk = 0.5 * (blk + blk.transpose());
      d.Phi(node, hC, c, c2) = blk;
      if (c2 != c) d.Phi(node, hC, c2, c) = blk.transpose();
    }
    d.b(node, c) = lc ? shift_motion(aL0, ec) : Vec6(d.b(ls.O, s) - Xc * fJ0);
  }
  (void)hL;
}

// Back-substitution of a leaf-form node: f_J = F f_L + Y s_O + f_J0, then q̈ from L's joint-space
// equation K_ss q̈' = Sᵀ(f_J + f_L + p) − Sᵀ K (a_O + c'), a_O from the (heavier) other side.
void leaf_form_top_down(const Model& m, Data& d, int node, int side) {
  const auto& t = m.tree;
  const LeafSides ls = leaf_sides(m, node, side);
  const int J = t.joint[node];
  const int P = t.P[node], Q = t.Q[node], hP = t.handle_num[P], hO = t.handle_num[ls.O];
  Vec6 sO = Vec6::Zero(), fL = Vec6::Zero();
  int ci = 0;
  for (int i = 0; i < hP; ++i) {
    if (i == t.slot_j[node]) continue;
    const Vec6 fi = d.f(node, ci++);
    d.f(P, i) = fi;
    if (P == ls.O) sO.noalias() += d.Phi(ls.O, hO, ls.sO, i) * fi;
    else fL += shift_force(fi, -leaf_handle_offset(d, ls.b, J, t.handle(P, i)));
  }
  for (int l = 0; l < t.handle_num[Q]; ++l) {
    if (l == t.slot_k[node]) continue;
    const Vec6 fl = d.f(node, ci++);
    d.f(Q, l) = fl;
    if (Q == ls.O) sO.noalias() += d.Phi(ls.O, hO, ls.sO, l) * fl;
    else fL += shift_force(fl, -leaf_handle_offset(d, ls.b, J, t.handle(Q, l)));
  }
  const Vec6 fJ = d.leaf_F[d.leaf_adr[node]] * fL + d.W[node] * sO + ls.sigma * d.beta[node];
  const Vec6 fc = ls.sigma * fJ;
  d.f(P, t.slot_j[node]) = -fc;
  d.f(Q, t.slot_k[node]) = fc;
  const int nJ = m.v_num[J];
  if (nJ > 0 && d.kind[node] == NodeKind::kActive) {
    JointMat S, T, Dj;
    joint_subspaces(m, d, J, S, T, Dj);
    Mat6 K;
    Vec6 p;
    leaf_inertia_at_joint(d, ls.b, J, K, p);
    const Vec6 aO = sO + d.b(ls.O, ls.sO) - d.Phi(ls.O, hO, ls.sO, ls.sO) * fJ;
    const JointMat KS = K * S;
    const JointVec rhs = S.transpose() * (fJ + fL + p) - KS.transpose() * (aO + ls.sigma * d.c[J]);
    if (nJ == 1) {   // K_ss is the scalar S·K S
      d.qdd(m.v_adr[J]) = ls.sigma * rhs(0) / S.col(0).dot(KS.col(0));
    } else {
      const JointSq Kss = S.transpose() * KS;
      d.qdd.segment(m.v_adr[J], nJ) = ls.sigma * Eigen::LLT<JointSq>(Kss).solve(rhs);
    }
  }
}

// The bias half of the form, for the correction pass of Data::refine (dca_refine.cpp; p = c' = 0):
// f_J0 = Y b_O + G τ', O's acceleration a_O = b_O − B̂ f_J0, and L's
// a_L = a_O + S q̈' from its joint-space equation K_ss q̈' = Sᵀ f_J0 − (KS)ᵀ a_O (leaf_form_top_down).
void leaf_form_bias(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) {
  const auto& t = m.tree;
  const LeafSides ls = leaf_sides(m, node, d.leaf_side[node]);
  const int J = t.joint[node], hO = t.handle_num[ls.O];
  JointMat S, T, Dj;
  joint_subspaces(m, d, J, S, T, Dj);
  const int nJ = static_cast<int>(S.cols());
  const Vec6 bO = d.b(ls.O, ls.sO);
  Vec6 fJ0 = d.W[node] * bO;
  if (nJ > 0) fJ0.noalias() += d.leaf_G[d.leaf_adr[node]].leftCols(nJ) * (ls.sigma * tau.segment(m.v_adr[J], nJ));
  const Vec6 aO = bO - d.Phi(ls.O, hO, ls.sO, ls.sO) * fJ0;
  Vec6 aL0 = aO;
  if (nJ > 0) {
    Mat6 K;
    Vec6 p;
    leaf_inertia_at_joint(d, ls.b, J, K, p);
    const JointMat KS = K * S;
    const JointVec rhs = S.transpose() * fJ0 - KS.transpose() * aO;
    const JointSq Kss = S.transpose() * KS;
    aL0.noalias() += S * JointVec(Eigen::LLT<JointSq>(Kss).solve(rhs));
  }
  d.beta[node] = ls.sigma * fJ0;
  d.taut[node].setZero();
  const int hC = t.handle_num[node];
  for (int c = 0; c < hC; ++c) {
    int ch, sl;
    child_slot(t, node, c, ch, sl);
    if (ch == ls.L)
      d.b(node, c) = shift_motion(aL0, leaf_handle_offset(d, ls.b, J, t.handle(ls.L, sl)));
    else
      d.b(node, c).noalias() = d.b(ls.O, sl) - d.Phi(ls.O, hO, sl, ls.sO) * fJ0;
  }
}

}  // namespace detail

}  // namespace haptree
