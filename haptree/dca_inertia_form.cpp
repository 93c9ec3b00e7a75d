// Welded clusters in inertia form (Model::cluster_case; docs/algorithms.md §4.4, §6.2). A node
// whose handles all attach to one rigid cluster is described by its articulated inertia M and
// bias force p at its reference point o = r_{cluster_ref[node]}:
//   a_o = M⁻¹(Σ_x X_xᵀ f_x + p),  X_x = M(o → handle x);
//   pinned to the ground by a moving joint: a_o = S q̈₀ + c₀ with
//   U q̈₀ = τ₀ + Sᵀ(Σ_x X_xᵀ f_x + p − M c₀), U = SᵀMS (S and c₀ moved to o).
// Joining two such nodes across a fixed joint adds their M and p (moved to o). Joining a
// one-handle side O across a moving joint J adds its articulated-body projection
//   I_a = I_O − I_O S U⁻¹ Sᵀ I_O,  p_a = p_O − I_O S U⁻¹(Sᵀ p_O + σ τ_J) − σ I_a c_J,
//   U = Sᵀ I_O S,  σ = +1 when O = Q, −1 when O = P.
// No difference of large mobilities is formed, so the light pieces of a split hub do not cancel.
// o is a body of the node near most of its mass, not the cluster's root: an inertia moved across
// a long weld has a condition number ~ (length/radius of gyration)⁴, and its inverse lost 1e-5 of
// q̈ at 10⁶ m; mobilities are shifted instead. The node also publishes the mobility form,
// Φ_xy = X_x M⁻¹ X_yᵀ (S U⁻¹ Sᵀ in place of M⁻¹ when pinned) and b_x = X_x a_o(f = 0), for its
// readers. Offsets between bodies of one cluster are compensated sums of the d_k (two-sum).
#include "haptree/dca_detail.hpp"

namespace haptree {

namespace {

// r_a − r_b for two bodies of one cluster, from the compensated offsets (exact to O(ε|r_a − r_b|)).
inline Vec3 body_offset(const Data& d, int a, int b) {
  if (a == b) return Vec3::Zero();
  return (d.cluster_offset[a] - d.cluster_offset[b]) +
         (d.cluster_offset_lo[a] - d.cluster_offset_lo[b]);
}

// Offset of handle `slot` of `node` from the origin of body `ref` (same cluster).
inline Vec3 handle_offset_from(const Model& m, const Data& d, int node, int slot, int ref) {
  const int J = m.tree.handle(node, slot), a = m.tree.attached_body(node, slot);
  const Vec3 e = body_offset(d, a, ref);
  return a == J ? e : Vec3(e + d.d[J]);
}
// Offset of handle `slot` of `node` from the node's reference point.
inline Vec3 handle_offset(const Model& m, const Data& d, int node, int slot) {
  return handle_offset_from(m, d, node, slot, m.cluster_ref[node]);
}

// Motion subspace S given at r_a, expressed at r_a + e: bottom rows − [e]× top rows.
inline void shift_motion_cols(JointMat& S, const Vec3& e) {
  if (e.isZero(0)) return;
  const Mat3 E = skew(e);
  for (int c = 0; c < S.cols(); ++c) S.col(c).tail<3>() -= E * S.col(c).head<3>();
}

// Inertia I given at point o + delta, moved to o: Xᵀ I X with X = M(o → o + delta).
inline Mat6 inertia_at_origin(const Mat6& I, const Vec3& delta) {
  if (delta.isZero(0)) return I;   // pieces of a split hub share its origin
  const Mat6 X = motion_shift_matrix(delta);
  return X.transpose() * I * X;
}

// Inertia form (M, p) of a leaf or an inertia-form node, moved from its own reference point to the
// origin of body `ref` (a no-op when they coincide, as on the heavier side of a merge).
inline void inertia_form(const Model& m, const Data& d, int node, int ref, Mat6& M, Vec6& p) {
  const Vec3 e = body_offset(d, m.cluster_ref[node], ref);
  if (m.tree.is_leaf(node)) {
    const int k = m.tree.body[node];
    M = inertia_at_origin(d.I[k], e);
    p = shift_force(d.p_bias[k], -e);
  } else {
    const int c = m.cluster_index[node];
    M = inertia_at_origin(d.cM[c], e);
    p = shift_force(d.cp[c], -e);
  }
}

// Articulated inertia IA and bias pA at the handle point r_J of a one-handle node O.
void one_handle_inertia(const Model& m, const Data& d, int O, int J, Mat6& IA, Vec6& pA) {
  const auto& t = m.tree;
  if (t.is_leaf(O)) {
    const int b = t.body[O];
    if (b == J) {
      IA = d.I[J];
      pA = d.p_bias[J];
    } else {   // O is J's predecessor: r_J = r_b + d_J
      IA = inertia_at_origin(d.I[b], -d.d[J]);
      pA = shift_force(d.p_bias[b], d.d[J]);
    }
  } else if (d.cluster_live[O]) {
    const int c = m.cluster_index[O];
    const Vec3 delta = handle_offset(m, d, O, 0);
    IA = inertia_at_origin(d.cM[c], -delta);
    pA = shift_force(d.cp[c], delta);
  } else {   // mobility form: a = Φ f + b  =>  f = Φ⁻¹ a − Φ⁻¹ b
    const Eigen::LLT<Mat6> llt(Mat6(d.Phi(O, 1, 0, 0)));
    IA = llt.solve(Mat6::Identity());
    IA = 0.5 * (IA + IA.transpose());
    pA = IA * d.b(O, 0);
  }
}

}  // namespace

namespace detail {

void assemble_inertia_form(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) {
  const auto& t = m.tree;
  const int P = t.P[node], Q = t.Q[node], J = t.joint[node];
  const int c = m.cluster_index[node];
  const int ref = m.cluster_ref[node];
  Mat6 M;
  Vec6 p;
  if (m.cluster_case[node] == Model::ClusterCase::kGroundPin) {
    inertia_form(m, d, Q, ref, M, p);
  } else if (m.cluster_case[node] == Model::ClusterCase::kFixedMerge) {
    Mat6 MP, MQ;
    Vec6 pP, pQ;
    inertia_form(m, d, P, ref, MP, pP);
    inertia_form(m, d, Q, ref, MQ, pQ);
    M = MP + MQ;
    p = pP + pQ;
  } else {
    const bool o_is_q = m.cluster_case[node] == Model::ClusterCase::kProjectQ;
    const int O = o_is_q ? Q : P, In = o_is_q ? P : Q;
    const double sigma = o_is_q ? 1.0 : -1.0;   // a_O = a_K + σ(S q̈ + c)
    Mat6& IA = d.cIA[c];
    Vec6& pA = d.cpA[c];
    one_handle_inertia(m, d, O, J, IA, pA);
    JointMat S, T, D;
    joint_subspaces(m, d, J, S, T, D);
    const int nJ = static_cast<int>(S.cols());
    Mat6 Ia = IA;
    Vec6 pa = pA;
    if (nJ > 0) {
      const JointMat IS = IA * S;
      const JointSq U = S.transpose() * IS;
      const Eigen::LLT<JointSq> llt(U);
      const JointVec rhs = S.transpose() * pA + sigma * tau.segment(m.v_adr[J], nJ);
      const JointVec u = llt.solve(rhs);
      d.cqa[c].head(nJ) = u;
      Ia -= IS * llt.solve(Eigen::Matrix<double, Eigen::Dynamic, 6, 0, 6, 6>(IS.transpose()));
      pa -= IS * u;
    }
    pa -= sigma * (Ia * d.c[J]);
    Mat6 MI;
    Vec6 pI;
    inertia_form(m, d, In, ref, MI, pI);
    const Vec3 delta = handle_offset(m, d, In, o_is_q ? t.slot_j[node] : t.slot_k[node]);
    M = MI + inertia_at_origin(Ia, delta);
    p = pI + shift_force(pa, -delta);
  }
  M = 0.5 * (M + M.transpose());
  d.cM[c] = M;
  d.cp[c] = p;
  Mat6 Minv;
  Vec6 a0;
  const int pin = m.cluster_pin[node];
  if (pin < 0) {
    const Eigen::LLT<Mat6> llt(M);
    Minv = llt.solve(Mat6::Identity());
    a0 = llt.solve(p);
  } else {
    // The pin joint enters the cluster root r_pin; S and c0 moved to o: a_o = S q̈0 + c0 with
    // q̈0 = U⁻¹(τ0 + Sᵀ(F_o + p − M c0)), U = SᵀMS.
    JointMat S, T, D;
    joint_subspaces(m, d, pin, S, T, D);
    const Vec3 e_pin = body_offset(d, ref, pin);
    shift_motion_cols(S, e_pin);
    const int n0 = static_cast<int>(S.cols());
    const Vec6 c0 = shift_motion(d.c[pin], e_pin);
    Minv.setZero();
    a0 = c0;
    if (n0 > 0) {
      const JointMat MS = M * S;
      const JointSq U = S.transpose() * MS;
      const Eigen::LLT<JointSq> llt(U);
      Minv = S * llt.solve(Eigen::Matrix<double, Eigen::Dynamic, 6, 0, 6, 6>(S.transpose()));
      const JointVec r = tau.segment(m.v_adr[pin], n0) + S.transpose() * (p - M * c0);
      a0.noalias() += S * llt.solve(r);
    }
  }
  Minv = 0.5 * (Minv + Minv.transpose());
  d.cMinv[c] = Minv;
  d.cb[c] = a0;
  // Mobility form for consumers that read Φ and b (parents in mobility form, coupling, metric).
  const int h = t.handle_num[node];
  for (int x = 0; x < h; ++x) {
    const Vec3 dx = handle_offset(m, d, node, x);
    const Mat6 XM = dx.isZero(0) ? Minv : shift_rows(dx, Minv);
    for (int y = x; y < h; ++y) {
      const Vec3 dy = handle_offset(m, d, node, y);
      const Mat6 blk = dy.isZero(0) ? XM : shift_cols(XM, dy);
      d.Phi(node, h, x, y) = blk;
      if (y != x) d.Phi(node, h, y, x) = blk.transpose();
    }
    d.b(node, x) = shift_motion(a0, dx);
  }
  d.cluster_live[node] = 1;
}

// Back-substitution in inertia form: the cluster's acceleration comes from the parent when the
// parent is in inertia form (never recomputed from large constraint forces on a light piece).
void top_down_inertia_form(const Model& m, Data& d, int node) {
  const auto& t = m.tree;
  const int P = t.P[node], Q = t.Q[node], J = t.joint[node];
  const int j = t.slot_j[node], k = t.slot_k[node];
  const int hP = t.handle_num[P], hQ = t.handle_num[Q];
  const int c = m.cluster_index[node];
  const int up = t.up[node];
  Vec6 a;
  if (up >= 0 && d.cluster_live[up]) {
    a = d.ca[c];
  } else {
    Vec6 F = Vec6::Zero();
    for (int x = 0; x < t.handle_num[node]; ++x)
      F += shift_force(d.f(node, x), -handle_offset(m, d, node, x));
    a = d.cMinv[c] * F + d.cb[c];
    d.ca[c] = a;
  }
  int ci = 0;
  for (int i = 0; i < hP; ++i)
    if (i != j) d.f(P, i) = d.f(node, ci++);
  for (int l = 0; l < hQ; ++l)
    if (l != k) d.f(Q, l) = d.f(node, ci++);
  const int ref = m.cluster_ref[node];
  auto pass_down = [&](int child, const Vec6& ac) {
    if (!t.is_leaf(child) && d.cluster_live[child])
      d.ca[m.cluster_index[child]] = shift_motion(ac, body_offset(d, m.cluster_ref[child], ref));
  };
  Vec6 fc;
  if (m.cluster_case[node] == Model::ClusterCase::kGroundPin) {
    // J enters the cluster root r_J: q̈ = Sᵀ(a_J − c_J); the ground's force from Q's equation.
    Mat6 MQ;
    Vec6 pQ;
    inertia_form(m, d, Q, ref, MQ, pQ);
    Vec6 g = MQ * a - pQ;
    for (int x = 0; x < hQ; ++x)
      if (x != k) g -= shift_force(d.f(Q, x), -handle_offset_from(m, d, Q, x, ref));
    fc = shift_force(g, handle_offset_from(m, d, Q, k, ref));
    const int nJ = m.v_num[J];
    if (nJ > 0 && d.kind[node] == NodeKind::kActive) {
      JointMat S, T, D;
      joint_subspaces(m, d, J, S, T, D);
      d.qdd.segment(m.v_adr[J], nJ) =
          S.transpose() * (shift_motion(a, body_offset(d, J, ref)) - d.c[J]);
    }
    pass_down(Q, a);
  } else if (m.cluster_case[node] == Model::ClusterCase::kFixedMerge) {
    // Force through J from the lighter side's equation M_L a = Σ X_xᵀ f_x + p_L.
    Mat6 MP, MQ;
    Vec6 pP, pQ;
    inertia_form(m, d, P, ref, MP, pP);
    inertia_form(m, d, Q, ref, MQ, pQ);
    const bool use_q = MQ.trace() <= MP.trace();
    const int L = use_q ? Q : P, sJ = use_q ? k : j;
    Vec6 g = (use_q ? MQ : MP) * a - (use_q ? pQ : pP);
    for (int x = 0; x < t.handle_num[L]; ++x)
      if (x != sJ) g -= shift_force(d.f(L, x), -handle_offset_from(m, d, L, x, ref));
    const Vec6 fL = shift_force(g, handle_offset_from(m, d, L, sJ, ref));
    fc = use_q ? fL : Vec6(-fL);
    pass_down(P, a);
    pass_down(Q, a);
  } else {
    const bool o_is_q = m.cluster_case[node] == Model::ClusterCase::kProjectQ;
    const int O = o_is_q ? Q : P, In = o_is_q ? P : Q;
    const double sigma = o_is_q ? 1.0 : -1.0;
    const Mat6& IA = d.cIA[c];
    const Vec3 delta = handle_offset(m, d, In, o_is_q ? j : k);
    const Vec6 aK = shift_motion(a, delta);
    JointMat S, T, D;
    joint_subspaces(m, d, J, S, T, D);
    const int nJ = static_cast<int>(S.cols());
    Vec6 aO = aK + sigma * d.c[J];
    if (nJ > 0) {
      const JointMat IS = IA * S;
      const JointSq U = S.transpose() * IS;
      const JointVec qdd =
          sigma * (d.cqa[c].head(nJ) - Eigen::LLT<JointSq>(U).solve(JointVec(IS.transpose() * aO)));
      aO.noalias() += sigma * (S * qdd);
      if (d.kind[node] == NodeKind::kActive) d.qdd.segment(m.v_adr[J], nJ) = qdd;
    }
    fc = sigma * (IA * aO - d.cpA[c]);
    pass_down(In, a);
    if (!t.is_leaf(O) && d.cluster_live[O])
      d.ca[m.cluster_index[O]] = shift_motion(aO, -handle_offset(m, d, O, 0));
  }
  d.f(P, j) = -fc;
  d.f(Q, k) = fc;
}

}  // namespace detail

void chain_cluster_offset(const Model& m, Data& d, int k) noexcept {
  // Knuth's two-sum: hi + lo = hi_p + lo_p + d_k with no rounding error kept in hi alone.
  const int p = m.parent[k];
  const Vec3& a = d.cluster_offset[p];
  const Vec3& b = d.d[k];
  const Vec3 s = a + b;
  const Vec3 bb = s - a;
  d.cluster_offset_lo[k] = d.cluster_offset_lo[p] + ((a - (s - bb)) + (b - bb));
  d.cluster_offset[k] = s;
}

// Every body's offset from its cluster's root, once per pass before any node (dca_bottom_up, the
// parallel passes, adaptive.cpp's partial passes).
void dca_cluster_offsets(const Model& m, Data& d) noexcept {
  if (m.ncluster_nodes > 0)
    for (int k = 1; k < m.nbodies; ++k) {
      if (m.cluster_root[k] == k) {
        d.cluster_offset[k].setZero();
        d.cluster_offset_lo[k].setZero();
        continue;
      }
      chain_cluster_offset(m, d, k);
    }
}

}  // namespace haptree
