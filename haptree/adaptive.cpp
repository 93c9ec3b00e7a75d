#include "haptree/adaptive.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <limits>
#include <mutex>
#include <thread>

#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include "haptree/dca.hpp"

namespace haptree {

namespace {

using MatX = Eigen::MatrixXd;
using VecX = Eigen::VectorXd;

// Gathers every body of a node's subtree (iterative; no recursion on deep trees).
template <class F>
void for_each_body(const AssemblyTree& t, int node, std::vector<int>& stack, F&& f) {
  stack.clear();
  stack.push_back(node);
  while (!stack.empty()) {
    const int n = stack.back();
    stack.pop_back();
    if (t.is_leaf(n)) f(t.body[n]);
    else { stack.push_back(t.P[n]); stack.push_back(t.Q[n]); }
  }
}

}  // namespace

namespace {

// The selection's buffers (swap_metric_scratch lists them), empty of values: Ψ, p, η of every node
// and the incremental metric's cache, marked as holding nothing.
void allocate_metric_scratch(const Model& m, AdaptiveData& ad) {
  const int nn = m.tree.nnodes();
  std::size_t phi = 0, vec = 0;
  for (int node = 0; node < nn; ++node) {
    const std::size_t h = m.tree.handle_num[node];
    phi += 36 * h * h;
    vec += 6 * h;
  }
  ad.Psi_buf.assign(phi, 0.0);
  ad.p_buf.assign(vec, 0.0);
  ad.eta.assign(nn, 0.0);
  ad.Phi_loc.assign(phi, 0.0);
  ad.Psi_loc.assign(phi, 0.0);
  ad.W_loc.assign(nn, Mat6::Zero());
  ad.q_cached = Eigen::VectorXd::Zero(m.nq);
  ad.metric_cached = false;
  ad.selections_since_refresh = 0;
  ad.node_moved.assign(nn, 1);
  ad.world_ok.assign(nn, 0);
  ad.scratch_joint_moved.assign(m.nbodies, 0);
}

}  // namespace

AdaptiveData::AdaptiveData(const Model& m) : AdaptiveData(m, false) {}

AdaptiveData::AdaptiveData(const Model& m, bool selection_only) : impulse(m) {
  const auto& t = m.tree;
  const int nn = t.nnodes(), nb = m.nbodies;
  active.assign(nn, 0);
  frontier_of_body.assign(nb, -1);
  coarse_of.assign(nn, -1);
  X_R.assign(nn, Mat3::Identity());
  X_r.assign(nn, Vec3::Zero());
  fine_frontier.reserve(nn);
  keep_selected.reserve(8);   // the grabbed bodies: a synchronous selection copies the list without allocating
  scratch_nodes.reserve(nn);
  scratch_joints.reserve(nb);
  scratch_mark.assign(nn, 0);
  ref_body.assign(nn, -1);
  for (int node = nn - 1; node >= 0; --node)
    ref_body[node] = t.is_leaf(node) ? t.body[node] : std::min(ref_body[t.P[node]], ref_body[t.Q[node]]);
  comp_mass.assign(nn, 0);
  comp_com.assign(nn, Vec3::Zero());
  comp_Ic.assign(nn, Mat3::Zero());
  comp_ground.assign(nn, 0);
  local_R.assign(nb, Mat3::Identity());
  local_r.assign(nb, Vec3::Zero());
  if (!selection_only) allocate_metric_scratch(m, *this);   // the worker borrows this set (swap_metric_scratch)
  scratch_f.assign(std::max(1, t.max_handles), Vec6::Zero());
  active_nodes.reserve(nn);
  frontier.reserve(nn);
  active_joints.reserve(nb);
  heap.reserve(nn);
  scratch_stack.reserve(nn);
  scratch_joint_active.assign(nb, 0);
  const int hm = std::max(1, t.max_handles);
  scratch_K.assign(hm, Mat6::Zero());
  scratch_U.assign(hm, Mat3::Zero());
  scratch_Vb.assign(hm, Mat3::Zero());
  scratch_Sk.assign(hm, Mat3::Zero());
  scratch_V.assign(hm, Mat6::Zero());
  scratch_Y.assign(static_cast<std::size_t>(hm + 1) * hm, Mat6::Zero());
  if (selection_only) {
    std::vector<Vec6>().swap(impulse.f_ext);
    return;
  }
  // The hybrid pass, the handover and the impulsive lock (adaptive_step's thread only).
  scratch_hn.assign(nn, Vec6::Zero());
  scratch_union.reserve(nn);
  scan_loaded.reserve(nb);
  ref_velocity.assign(nn, Vec6::Zero());
  pred_offset.assign(nb, Vec3::Zero());
  inertia_form.assign(nn, 0);
  if_bodies.reserve(nb);
  if_top.assign(nb, 0);
  loaded_bodies.reserve(nb);
  scratch_h.assign(nb, Vec6::Zero());
  kin_q.reserve(m.nq + m.nv);
}

// §8: Ψ, p, η bottom-up from the full-articulated coefficients held in `d`. With f^C the handle
// forces of C, the children's handle forces are f^P = MP f^C + mP and f^Q = MQ f^C + mQ, where MP
// injects C's P-slots and carries −K at slot j (f_c = K f^C + β), MQ likewise with +K at slot k.
// Ψ_C = MPᵀΨ_P MP + MQᵀΨ_Q MQ + V_Jᵀ D Dᵀ V_J is formed block by block (6×6, no allocation):
// MP is an injection plus one block row, so only the blocks it touches are multiplied.
namespace {

// One node of compute_metric_coefficients (children done).
void metric_node(const Model& m, const Data& d, AdaptiveData& ad, int node) {
  const auto& t = m.tree;
  auto psi = [&](int node, int h, int a, int b) {
    return BlockMap(ad.Psi_buf.data() + d.Phi_adr[node] + 6 * a + 36 * h * b,
                    Eigen::OuterStride<>(6 * h));
  };
  auto pv = [&](int node, int slot) { return VecMap(ad.p_buf.data() + d.vec_adr[node] + 6 * slot); };
  {
    const int hC = t.handle_num[node];
    if (t.is_leaf(node)) {
      ad.eta[node] = 0;
      for (int x = 0; x < hC; ++x) {
        for (int y = 0; y < hC; ++y) psi(node, hC, x, y).setZero();
        pv(node, x).setZero();
      }
      return;
    }
    const int P = t.P[node], Q = t.Q[node], J = t.joint[node];
    const int j = t.slot_j[node], k = t.slot_k[node];
    const int hP = t.handle_num[P], hQ = t.handle_num[Q];
    const Mat6& W = d.W[node];
    const Vec6& beta = d.beta[node];
    // C slot c comes from P slot src(c) (c < hP − 1, skipping j) or from Q slot src(c) (skipping k).
    auto from_p = [&](int c) { return c < hP - 1; };
    auto src = [&](int c) {
      if (from_p(c)) return c < j ? c : c + 1;
      const int l = c - (hP - 1);
      return l < k ? l : l + 1;
    };
    Mat6* K = ad.scratch_K.data();
    Mat6* V = ad.scratch_V.data();   // Rr_c first, then Φ̂ K_c + Rr_c
    for (int c = 0; c < hC; ++c) {
      if (from_p(c)) {
        const Mat6 Pji = d.Phi(P, hP, j, src(c));
        K[c].noalias() = W * Pji;
        V[c] = -Pji;
      } else {
        const Mat6 Qkl = d.Phi(Q, hQ, k, src(c));
        K[c].noalias() = -W * Qkl;
        V[c] = Qkl;
      }
    }
    // Y_X[a][c2] = (Ψ_X M_X)[a][c2] for each child X; T_X(c1, c2) = (M_Xᵀ Y_X)[c1][c2].
    Mat6* Y = ad.scratch_Y.data();
    auto side = [&](int X, int hX, int sJ, bool is_p, double sign) {
      auto owns = [&](int c) { return from_p(c) == is_p; };
      for (int a = 0; a < hX; ++a)
        for (int c2 = 0; c2 < hC; ++c2) {
          Mat6& y = Y[a * hC + c2];
          y.noalias() = sign * (psi(X, hX, a, sJ) * K[c2]);
          if (owns(c2)) y += psi(X, hX, a, src(c2));
        }
      for (int c1 = 0; c1 < hC; ++c1)
        for (int c2 = c1; c2 < hC; ++c2) {
          Mat6 blk = sign * (K[c1].transpose() * Y[sJ * hC + c2]);
          if (owns(c1)) blk += Y[src(c1) * hC + c2];
          if (is_p) psi(node, hC, c1, c2) = blk;
          else psi(node, hC, c1, c2) += blk;
        }
      // p: z[a] = 2 Ψ_X[a][sJ] m + p_X[a] with m = ∓β at sJ.
      const Vec6 m_s = sign * beta;
      const Vec6 zJ = 2 * (psi(X, hX, sJ, sJ) * m_s) + pv(X, sJ);
      for (int c = 0; c < hC; ++c) {
        Vec6 v = sign * (K[c].transpose() * zJ);
        if (owns(c)) v += 2 * (psi(X, hX, src(c), sJ) * m_s) + pv(X, src(c));
        if (is_p) pv(node, c) = v;
        else pv(node, c) += v;
      }
      return m_s.dot(psi(X, hX, sJ, sJ) * m_s) + m_s.dot(pv(X, sJ)) + ad.eta[X];
    };
    double eta = side(P, hP, j, true, -1.0);
    eta += side(Q, hQ, k, false, 1.0);
    const int nJ = m.v_num[J];
    if (nJ > 0) {
      JointMat S, T, D;
      joint_subspaces(m, d, J, S, T, D);
      const Mat6 Phat = d.Phi(P, hP, j, j) + d.Phi(Q, hQ, k, k);
      const Mat6 DD = D * D.transpose();
      const Vec6 q0 = Phat * beta + d.b(Q, k) - d.b(P, j) - d.c[J];
      const Vec6 Dq0 = DD * q0;
      for (int c = 0; c < hC; ++c) V[c].noalias() += Phat * K[c];
      for (int c1 = 0; c1 < hC; ++c1) {
        const Mat6 VtDD = V[c1].transpose() * DD;
        for (int c2 = c1; c2 < hC; ++c2) psi(node, hC, c1, c2).noalias() += VtDD * V[c2];
        pv(node, c1).noalias() += 2 * (V[c1].transpose() * Dq0);
      }
      eta += q0.dot(Dq0);
    }
    for (int c1 = 0; c1 < hC; ++c1) {
      const Mat6 dblk = psi(node, hC, c1, c1);
      psi(node, hC, c1, c1) = 0.5 * (dblk + dblk.transpose());
      for (int c2 = c1 + 1; c2 < hC; ++c2) psi(node, hC, c2, c1) = psi(node, hC, c1, c2).transpose();
    }
    ad.eta[node] = eta;
  }
}

}  // namespace

// Ψ, p, η in world axes (Psi_buf, p_buf, eta) are written by every selection before it reads
// them, so the stepping thread lends its set to the worker for the selection in flight and takes
// it back when the worker is done. This makes sure `ad` holds the set (waits for the worker if
// need be; allocates only for a copy of an AdaptiveData whose set was lent).
void ensure_metric_scratch(const Model& m, AdaptiveData& ad);

void compute_metric_coefficients(const Model& m, const Data& d, AdaptiveData& ad) {
  ensure_metric_scratch(m, ad);
  for (int node = m.tree.nnodes() - 1; node >= 0; --node) metric_node(m, d, ad, node);
}

double metric_value(const Model& m, const AdaptiveData& ad, int node, const double* f) {
  const int h = m.tree.handle_num[node];
  if (m.tree.is_leaf(node)) return 0;
  if (ad.Psi_buf.empty()) return std::numeric_limits<double>::quiet_NaN();   // lent to the worker
  std::size_t adr = 0, vadr = 0;
  // Offsets match Data's layout (computed the same way).
  for (int n = 0; n < node; ++n) {
    adr += 36 * std::size_t(m.tree.handle_num[n]) * m.tree.handle_num[n];
    vadr += 6 * std::size_t(m.tree.handle_num[n]);
  }
  const CMatMap Psi(ad.Psi_buf.data() + adr, 6 * h, 6 * h);
  const Eigen::Map<const VecX> p(ad.p_buf.data() + vadr, 6 * h), fv(f, 6 * h);
  return fv.dot(Psi * fv) + fv.dot(p) + ad.eta[node];
}

namespace {

// blockdiag(R, R) x and its transpose.
inline Vec6 rot6(const Mat3& R, const Vec6& x) {
  Vec6 y;
  y.head<3>().noalias() = R * x.head<3>();
  y.tail<3>().noalias() = R * x.tail<3>();
  return y;
}
inline Vec6 rot6t(const Mat3& R, const Vec6& x) {
  Vec6 y;
  y.head<3>().noalias() = R.transpose() * x.head<3>();
  y.tail<3>().noalias() = R.transpose() * x.tail<3>();
  return y;
}

// Every 3×3 block of an n6×n6 column-major matrix: dst = Rᵀ src R (to_local) or R src Rᵀ.
void rotate_blocks(const Mat3& R, const double* src, double* dst, int n6, bool to_local) {
  using CM3 = Eigen::Map<const Mat3, 0, Eigen::OuterStride<>>;
  using M3 = Eigen::Map<Mat3, 0, Eigen::OuterStride<>>;
  const int n3 = n6 / 3;
  for (int bj = 0; bj < n3; ++bj)
    for (int bi = 0; bi < n3; ++bi) {
      const std::size_t off = 3 * static_cast<std::size_t>(bi) + static_cast<std::size_t>(n6) * 3 * bj;
      const CM3 a(src + off, Eigen::OuterStride<>(n6));
      M3 b(dst + off, Eigen::OuterStride<>(n6));
      const Mat3 x = to_local ? Mat3(R.transpose() * a) : Mat3(R * a);
      if (to_local) b.noalias() = x * R;
      else b.noalias() = x * R.transpose();
    }
}

bool translating(const Model& m, int J) {
  return m.joint_type[J] == JointType::kPrismatic || m.joint_type[J] == JointType::kFree;
}

// World-frame views of a node's cached coefficients (docs/algorithms.md §10.2: a node with no moved
// joint only rotates, with its reference body).
struct MetricCache {
  const Model& m;
  Data& d;
  AdaptiveData& ad;
  enum : char { kPhi = 1, kW = 2, kPsi = 4 };
  const Mat3& R(int X) const { return d.R[ad.ref_body[X]]; }
  CBlockMap phi_loc(int X, int a, int b) const {
    const int h = m.tree.handle_num[X];
    return CBlockMap(ad.Phi_loc.data() + d.Phi_adr[X] + 6 * a + 36 * h * b, Eigen::OuterStride<>(6 * h));
  }
  CBlockMap psi_loc(int X, int a, int b) const {
    const int h = m.tree.handle_num[X];
    return CBlockMap(ad.Psi_loc.data() + d.Phi_adr[X] + 6 * a + 36 * h * b, Eigen::OuterStride<>(6 * h));
  }
  // World Φ_X(a, b) x, Ψ_X(a, b) x, W_C x from the cache.
  Vec6 phi(int X, int a, int b, const Vec6& x) const {
    const Mat3& Rx = R(X);
    return rot6(Rx, phi_loc(X, a, b) * rot6t(Rx, x));
  }
  Vec6 psi(int X, int a, int b, const Vec6& x) const {
    const Mat3& Rx = R(X);
    return rot6(Rx, psi_loc(X, a, b) * rot6t(Rx, x));
  }
  Vec6 W(int C, const Vec6& x) const {
    const Mat3& Rc = R(C);
    return rot6(Rc, ad.W_loc[C] * rot6t(Rc, x));
  }
  // Writes the world values into Data (Φ, W) and Psi_buf (Ψ) for the readers of full coefficients.
  void ensure(int X, char what) {
    const char need = what & ~ad.world_ok[X];
    if (!need) return;
    const int n6 = 6 * m.tree.handle_num[X];
    const std::size_t adr = d.Phi_adr[X];
    if (need & kPhi) rotate_blocks(R(X), ad.Phi_loc.data() + adr, d.Phi_buf.data() + adr, n6, false);
    if ((need & kW) && !m.tree.is_leaf(X))
      rotate_blocks(R(X), ad.W_loc[X].data(), d.W[X].data(), 6, false);
    if ((need & kPsi) && !m.tree.is_leaf(X))
      rotate_blocks(R(X), ad.Psi_loc.data() + adr, ad.Psi_buf.data() + adr, n6, false);
    ad.world_ok[X] |= need;
  }
  // Stores a node just assembled in full (world values in Data/Psi_buf) into the cache.
  void store(int X) {
    const int n6 = 6 * m.tree.handle_num[X];
    const std::size_t adr = d.Phi_adr[X];
    rotate_blocks(R(X), d.Phi_buf.data() + adr, ad.Phi_loc.data() + adr, n6, true);
    if (!m.tree.is_leaf(X)) {
      rotate_blocks(R(X), d.W[X].data(), ad.W_loc[X].data(), 6, true);
      rotate_blocks(R(X), ad.Psi_buf.data() + adr, ad.Psi_loc.data() + adr, n6, true);
    }
    ad.world_ok[X] = kPhi | kW | kPsi;
  }
  // A(X, f) = fᵀΨf + fᵀp + η with the handle forces in Data (Ψ from the cache, rotated f).
  double metric_at(int X) const {
    const int h = m.tree.handle_num[X];
    Vec6* fl = ad.scratch_f.data();
    double v = ad.eta[X];
    for (int a = 0; a < h; ++a) {
      fl[a] = rot6t(R(X), d.f(X, a));
      v += d.f(X, a).dot(CVecMap(ad.p_buf.data() + d.vec_adr[X] + 6 * a));
    }
    for (int a = 0; a < h; ++a) {
      Vec6 s = Vec6::Zero();
      for (int b = 0; b < h; ++b) s.noalias() += psi_loc(X, a, b) * fl[b];
      v += fl[a].dot(s);
    }
    return v;
  }
};

// Bias terms only (b, β, τ̃ and p, η) of a node whose Φ, W, Ψ are cached: §5.2's b-recurrence and
// compute_metric_coefficients' p, η recurrence written as matrix–vector products. With K_c = W Φ_P(j,
// src c) (or −W Φ_Q(k, src c)), K_cᵀ y = ±Φ_X(src c, sJ) W y by the symmetry of Φ and W, so no 6×6
// product is formed.
void bias_node(MetricCache& mc, const State& st, int node) {
  const Model& m = mc.m;
  Data& d = mc.d;
  AdaptiveData& ad = mc.ad;
  const auto& t = m.tree;
  auto pv = [&](int X, int slot) { return VecMap(ad.p_buf.data() + d.vec_adr[X] + 6 * slot); };
  if (t.is_leaf(node)) {
    const int k = t.body[node], h = t.handle_num[node];
    ad.eta[node] = 0;
    const Vec6 a0 = k == 0 ? Vec6::Zero() : Vec6(d.Iinv[k] * d.p_bias[k]);
    for (int x = 0; x < h; ++x) {
      const int jx = t.handle(node, x);
      d.b(node, x) = (jx == k || k == 0) ? a0 : shift_motion(a0, d.d[jx]);
      pv(node, x).setZero();
    }
    return;
  }
  d.cluster_live[node] = 0;
  const int P = t.P[node], Q = t.Q[node], J = t.joint[node];
  const int j = t.slot_j[node], k = t.slot_k[node];
  const int hP = t.handle_num[P], hQ = t.handle_num[Q];
  const bool leafP = t.is_leaf(P), leafQ = t.is_leaf(Q);
  auto phat = [&](const Vec6& x) { return Vec6(mc.phi(P, j, j, x) + mc.phi(Q, k, k, x)); };
  const int nJ = m.v_num[J];
  JointMat S, T, D;
  if (nJ > 0) joint_subspaces(m, d, J, S, T, D);
  Vec6 taut = Vec6::Zero();
  if (nJ > 0 && !st.tau.segment(m.v_adr[J], nJ).isZero(0)) {
    const Vec6 Dtau = D * st.tau.segment(m.v_adr[J], nJ);
    taut = Dtau - mc.W(node, phat(Dtau));
  }
  d.taut[node] = taut;
  const Vec6 beta = mc.W(node, d.c[J] - d.b(Q, k) + d.b(P, j)) + taut;
  d.beta[node] = beta;
  // β in each child's frame once: Φ̂β, Ψ_X(sJ, sJ) m_X (m_P = −β, m_Q = β) and side() reuse it.
  const Mat3 &RP = mc.R(P), &RQ = mc.R(Q);
  const Vec6 xbP = rot6t(RP, beta), xbQ = rot6t(RQ, beta);
  // p, η: z_X = 2 Ψ_X(sJ, sJ) m_X + p_X(sJ).
  Vec6 zP = Vec6::Zero(), zQ = Vec6::Zero();
  double eta = 0;
  if (!leafP) {
    const Vec6 ly = -(mc.psi_loc(P, j, j) * xbP);   // Ψ_P m_P in P's frame
    zP = 2 * rot6(RP, ly) + pv(P, j);
    eta += -xbP.dot(ly) - beta.dot(pv(P, j)) + ad.eta[P];   // m_P·Ψ m_P = (−xbP)·ly
  }
  if (!leafQ) {
    const Vec6 ly = mc.psi_loc(Q, k, k) * xbQ;
    zQ = 2 * rot6(RQ, ly) + pv(Q, k);
    eta += xbQ.dot(ly) + beta.dot(pv(Q, k)) + ad.eta[Q];
  }
  Vec6 e = mc.W(node, zQ - zP);
  if (nJ > 0) {
    const Vec6 phb = rot6(RP, mc.phi_loc(P, j, j) * xbP) + rot6(RQ, mc.phi_loc(Q, k, k) * xbQ);
    const Vec6 q0 = phb + d.b(Q, k) - d.b(P, j) - d.c[J];
    const Vec6 u = D * (D.transpose() * q0);
    e += 2 * (mc.W(node, phat(u)) - u);
    eta += q0.dot(u);
  }
  ad.eta[node] = eta;
  // Surviving handles of child X (sign −1 for P, +1 for Q): b = b_X + sign·Φ_X(·, sJ) β and
  // p = −sign·Φ_X(·, sJ) e + 2 Ψ_X(·, sJ) m_X + p_X (m_X = sign·β), with β, e rotated into X's
  // frame once.
  int ci = 0;
  auto side = [&](int X, int hX, int sJ, double sign, bool leaf, const Vec6& xb) {
    const Mat3& Rx = mc.R(X);
    const Vec6 xe = rot6t(Rx, e);
    for (int i = 0; i < hX; ++i) {
      if (i == sJ) continue;
      const CBlockMap F = mc.phi_loc(X, i, sJ);
      d.b(node, ci) = d.b(X, i) + sign * rot6(Rx, F * xb);
      Vec6 lp = -sign * (F * xe);
      if (!leaf) lp.noalias() += (2 * sign) * (mc.psi_loc(X, i, sJ) * xb);   // m_X = sign·β
      pv(node, ci++) = rot6(Rx, lp) + (leaf ? Vec6::Zero() : Vec6(pv(X, i)));
    }
  };
  side(P, hP, j, -1.0, leafP, xbP);
  side(Q, hQ, k, 1.0, leafQ, xbQ);
}

// The full-articulated coefficients of the selection (§9) and the metric coefficients (§8), for
// every node. A node assembles in full (Φ, W, Ψ and the bias terms) when a joint inside it moved
// since the last selection (bitwise q), a translating joint at one of its handles moved, it is an
// inertia-form cluster node, or `exact`; every other node only recomputes its bias terms from
// its cached Φ, W, Ψ (bias_node). Under V1 only the active region's joints move between
// selections, so O(|active|) nodes assemble in full and O(n) nodes do O(h) matrix–vector work.
void metric_pass(const Model& m, Data& d, const State& st, AdaptiveData& ad, bool exact) {
  const auto& t = m.tree;
  const int nn = t.nnodes();
  exact = exact || !ad.metric_cached;
  auto& jm = ad.scratch_joint_moved;
  for (int k = 1; k < m.nbodies; ++k) {
    const int a = m.q_adr[k], n = joint_nq(m.joint_type[k]);
    jm[k] = exact;
    for (int i = 0; i < n && !jm[k]; ++i) jm[k] = st.q(a + i) != ad.q_cached(a + i);
  }
  for (int node = nn - 1; node >= 0; --node) {
    bool mv = exact;
    for (int x = 0; x < t.handle_num[node] && !mv; ++x) {
      const int jx = t.handle(node, x);
      mv = jm[jx] && translating(m, jx);
    }
    if (!t.is_leaf(node))
      mv = mv || jm[t.joint[node]] || ad.node_moved[t.P[node]] || ad.node_moved[t.Q[node]];
    ad.node_moved[node] = mv;
    d.kind[node] = t.is_leaf(node) ? NodeKind::kLeaf : NodeKind::kActive;
  }
  ad.kin_current = false;
  forward_kinematics(m, d, st.q);
  body_dynamics_terms(m, d, st);
  dca_cluster_offsets(m, d);
  std::fill(ad.world_ok.begin(), ad.world_ok.end(), 0);
  MetricCache mc{m, d, ad};
  std::int64_t full = 0, bias = 0;
  for (int node = nn - 1; node >= 0; --node) {
    if (ad.node_moved[node] || m.cluster_index[node] >= 0) {
      if (!t.is_leaf(node)) {
        for (int X : {t.P[node], t.Q[node]}) mc.ensure(X, MetricCache::kPhi | MetricCache::kPsi);
      }
      dca_bottom_up_node(m, d, node, st.tau);
      metric_node(m, d, ad, node);
      mc.store(node);
      ++full;
    } else {
      bias_node(mc, st, node);
      ++bias;
    }
  }
  d.diag.nodes_bottom_up = full + bias;
  ad.body_terms_current = true;
  ad.q_cached = st.q;
  ad.metric_cached = true;
  ad.report.metric_nodes_full = full;
  ad.report.metric_nodes_bias = bias;
  ad.report.exact_refresh = exact;
}

}  // namespace

// Impulsive lock of the inactive joints (needs the region's frontier caches and a full
// forward_kinematics in `d`). Locking joints suddenly applies constraint impulses only, so the
// active joints keep their generalized momentum pₐ = (H q̇)ₐ and take q̇ₐ' = Hₐₐ⁻¹ pₐ, q̇ᵢ' = 0:
// the kinetic energy can only decrease (simply zeroing q̇ᵢ can *increase* it, e.g. when a child
// counter-rotates against its parent). pₐ comes from composite body momenta in one O(n) sweep;
// Hₐₐ⁻¹ pₐ is the hybrid pass itself with τ = p, no velocities, no forces and no gravity —
// composite frontier nodes, so no difference-formula cancellation (§14.2).
void lock_velocities(const Model& m, Data& d, State& st, AdaptiveData& ad) {
  bool any = false;
  auto& joint_active = ad.scratch_joint_active;
  std::fill(joint_active.begin(), joint_active.end(), 0);
  for (int J : ad.active_joints) joint_active[J] = 1;
  for (int k = 1; k < m.nbodies && !any; ++k)
    any = !joint_active[k] && m.v_num[k] > 0 && !st.qd.segment(m.v_adr[k], m.v_num[k]).isZero(0);
  if (!any) return;
  // I_k, v_k with every joint's q̇ (already in Data when the selection's full pass just ran).
  if (!ad.body_terms_current) body_dynamics_terms(m, d, st);
  ad.body_terms_current = false;
  auto& h = ad.scratch_h;   // subtree momentum at r_k (a force-like vector)
  std::fill(h.begin(), h.end(), Vec6::Zero());
  for (int k = m.nbodies - 1; k >= 1; --k) {
    h[k] += d.I[k] * d.v[k];
    if (m.parent[k] > 0) h[m.parent[k]] += shift_force(h[k], -d.d[k]);
  }
  State& impulse = ad.impulse;   // q̇ = 0, no loads; τ = the active joints' momenta
  impulse.q = st.q;
  impulse.tau.setZero();
  for (int J : ad.active_joints) {
    const int a = m.v_adr[J];
    switch (m.joint_type[J]) {
      case JointType::kRevolute:
      case JointType::kPrismatic: impulse.tau(a) = d.S[J].dot(h[J]); break;
      case JointType::kSpherical: impulse.tau.segment<3>(a) = d.R[J].transpose() * h[J].head<3>(); break;
      case JointType::kFree:
        impulse.tau.segment<3>(a) = d.R[J].transpose() * h[J].head<3>();
        impulse.tau.segment<3>(a + 3) = d.R[J].transpose() * h[J].tail<3>();
        break;
      case JointType::kFixed: break;
    }
  }
  ad.gravity_scale = 0;
  adaptive_forward_dynamics(m, d, impulse, ad);
  ad.gravity_scale = 1;
  for (int k = 1; k < m.nbodies; ++k) {
    const int a = m.v_adr[k], n = m.v_num[k];
    if (joint_active[k]) st.qd.segment(a, n) = d.qdd.segment(a, n);
    else st.qd.segment(a, n).setZero();
  }
  d.qdd.setZero();
}

namespace {

// Region lists and frontier caches (fine = coarse) from ad.active and a full forward_kinematics
// in `d`. O(n).
void build_caches(const Model& m, Data& d, AdaptiveData& ad) {
  const auto& t = m.tree;
  const int nn = t.nnodes();
  ad.active_nodes.clear();
  ad.frontier.clear();
  ad.active_joints.clear();
  for (int node = 0; node < nn; ++node) {
    if (t.is_leaf(node)) { d.kind[node] = NodeKind::kLeaf; continue; }
    d.kind[node] = ad.active[node] ? NodeKind::kActive : NodeKind::kRigid;
    if (ad.active[node]) {
      ad.active_nodes.push_back(node);
      ad.active_joints.push_back(t.joint[node]);
    }
  }
  for (int root : t.roots)
    if (t.is_leaf(root) || !ad.active[root]) ad.frontier.push_back(root);
  for (int node : ad.active_nodes)
    for (int ch : {t.P[node], t.Q[node]})
      if (t.is_leaf(ch) || !ad.active[ch]) ad.frontier.push_back(ch);
  std::sort(ad.active_joints.begin(), ad.active_joints.end());
  d.qdd.setZero();
  // Composite inertia and body placements relative to each frontier node's reference body.
  std::vector<int>& stack = ad.scratch_stack;
  for (int F : ad.frontier)
    for_each_body(t, F, stack, [&](int k) { ad.frontier_of_body[k] = F; });
  // r_k − r_ref from the local offsets d_k (ids ascending: a node's bodies are a connected
  // subtree whose smallest id is ref, so parent[k] is done first), never r_k − r_ref of two world
  // positions, which lost ε·|r| at a far origin.
  for (int k = 0; k < m.nbodies; ++k) {
    if (ad.frontier_of_body[k] < 0) continue;
    const int ref = ad.ref_body[ad.frontier_of_body[k]];
    ad.local_r[k] = k == ref ? Vec3::Zero()
                             : Vec3(ad.local_r[m.parent[k]] + d.R[ref].transpose() * d.d[k]);
  }
  for (int F : ad.frontier) {
    const int ref = ad.ref_body[F];
    const Mat3 Rr = d.R[ref];
    double M = 0;
    Vec3 mc = Vec3::Zero();
    bool ground = false;
    for_each_body(t, F, stack, [&](int k) {
      ad.local_R[k] = k == ref ? Mat3::Identity() : Mat3(Rr.transpose() * d.R[k]);
      if (k == 0) ground = true;
      M += m.mass[k];
      mc += m.mass[k] * (ad.local_r[k] + ad.local_R[k] * m.com[k]);
    });
    ad.comp_ground[F] = ground;
    ad.comp_mass[F] = M;
    const Vec3 com = M > 0 ? Vec3(mc / M) : Vec3::Zero();
    Mat3 Ic = Mat3::Zero();
    for_each_body(t, F, stack, [&](int k) {
      if (k == 0) return;
      const Vec3 dk = ad.local_r[k] + ad.local_R[k] * m.com[k] - com;
      Ic += ad.local_R[k] * m.inertia[k] * ad.local_R[k].transpose() +
            m.mass[k] * (dk.squaredNorm() * Mat3::Identity() - dk * dk.transpose());
    });
    // A one-body composite is the body itself: take its data verbatim (no round-off).
    const bool single = t.is_leaf(F);
    ad.comp_com[F] = single ? m.com[ref] : com;
    ad.comp_Ic[F] = single ? m.inertia[ref] : Ic;
  }
  ad.fine_frontier = ad.frontier;
  for (int F : ad.frontier) {
    ad.coarse_of[F] = F;
    ad.X_R[F].setIdentity();
    ad.X_r[F].setZero();
  }
}

// Inertia-form active nodes of the region in ad (the frontier's comp_ground
// must be set). Entries of inertia_form and if_top are expected clear. O(|active|).
void build_inertia_form(const Model& m, AdaptiveData& ad) {
  const auto& t = m.tree;
  std::vector<int>& stack = ad.scratch_stack;
  // Inertia-form active nodes (children first: their ids are larger). The cases and their
  // readers are dca_inertia_form.cpp's; a side read as an inertia must be a leaf (not the ground) or such a
  // node, a projected one-handle side may also be in mobility form (one_handle_inertia inverts
  // its Φ), and a pin joint to the ground must be active.
  auto inertia_side = [&](int X) {
    return t.is_leaf(X) ? t.body[X] != 0 : ad.active[X] && ad.inertia_form[X];
  };
  auto one_handle_side = [&](int X) {
    return t.is_leaf(X) ? t.body[X] != 0 : ad.active[X] || !ad.comp_ground[X];
  };
  for (auto it = ad.active_nodes.rbegin(); it != ad.active_nodes.rend(); ++it) {
    const int node = *it;
    if (m.cluster_index[node] < 0) continue;
    const int pin = m.cluster_pin[node];
    if (pin >= 0 && !std::binary_search(ad.active_joints.begin(), ad.active_joints.end(), pin))
      continue;
    const int P = t.P[node], Q = t.Q[node];
    bool ok = false;
    switch (m.cluster_case[node]) {
      case Model::ClusterCase::kFixedMerge: ok = inertia_side(P) && inertia_side(Q); break;
      case Model::ClusterCase::kGroundPin: ok = inertia_side(Q); break;
      case Model::ClusterCase::kProjectQ: ok = inertia_side(P) && one_handle_side(Q); break;
      case Model::ClusterCase::kProjectP: ok = inertia_side(Q) && one_handle_side(P); break;
      default: break;
    }
    ad.inertia_form[node] = ok;
  }
  ad.if_bodies.clear();
  for (int node : ad.active_nodes) {
    if (!ad.inertia_form[node] || (t.up[node] >= 0 && ad.inertia_form[t.up[node]])) continue;
    ad.if_top[ad.ref_body[node]] = 1;
    for_each_body(t, node, stack, [&](int k) { ad.if_bodies.push_back(k); });
  }
  std::sort(ad.if_bodies.begin(), ad.if_bodies.end());
}

// Frontier caches from a full forward_kinematics in `d`. O(n).
void build_region(const Model& m, Data& d, State& st, AdaptiveData& ad) {
  ++ad.region_version;
  ad.step_work += m.tree.nnodes() + m.nbodies;
  build_caches(m, d, ad);
  std::fill(ad.inertia_form.begin(), ad.inertia_form.end(), 0);
  std::fill(ad.if_top.begin(), ad.if_top.end(), 0);
  build_inertia_form(m, ad);
  // V1: inactive joints do not move; moving ones are locked impulsively.
  lock_velocities(m, d, st, ad);
  ad.body_terms_current = false;
  ad.kin_current = false;
}

}  // namespace

void set_active_region(const Model& m, Data& d, State& st, AdaptiveData& ad,
                       const std::vector<char>& active_internal_nodes) {
  const auto& t = m.tree;
  for (int node = 0; node < t.nnodes(); ++node) {
    ad.active[node] = !t.is_leaf(node) && active_internal_nodes[node];
    if (ad.active[node] && t.up[node] >= 0 && !active_internal_nodes[t.up[node]])
      throw std::invalid_argument("set_active_region: active region is not a rooted subtree");
  }
  forward_kinematics(m, d, st.q);
  ad.body_terms_current = false;
  ad.kin_current = false;
  build_region(m, d, st, ad);
  ad.region_selected = false;   // an explicit region: no selection to check against
}

namespace {

// The selection proper (§9): full-articulated coefficients, the check of the region in force
// (ad.active_nodes, ad.frontier), the greedy walk; leaves the new region in ad.active, its DOFs in
// `dofs`, and returns its neglected metric. Needs no frontier cache (the background worker runs it).
double select_core(const Model& m, Data& d, const State& st, AdaptiveData& ad,
                   const AdaptiveOptions& opt, int& dofs_out) {
  const auto& t = m.tree;
  // Full-articulated coefficients: every joint free (§9); cached Φ, W, Ψ where nothing moved.
  const bool refresh = !opt.incremental_metric || !ad.metric_cached ||
                       (opt.exact_refresh_every > 0 &&
                        ad.selections_since_refresh + 1 >= opt.exact_refresh_every);
  metric_pass(m, d, st, ad, refresh);
  ad.step_work += m.tree.nnodes() + m.nbodies;
  ad.selections_since_refresh = refresh ? 0 : ad.selections_since_refresh + 1;
  MetricCache mc{m, d, ad};
  auto top_down = [&](int node) {   // world W of the node and Φ of its children, then §7
    mc.ensure(node, MetricCache::kW);
    mc.ensure(t.P[node], MetricCache::kPhi);
    mc.ensure(t.Q[node], MetricCache::kPhi);
    dca_top_down_node(m, d, node);
  };
  // Check (sets the next interval, see adaptive_step): the exact neglected metric of the region
  // being replaced, now — full-articulated top-down over its active nodes, Σ A over its frontier.
  for (int root : t.roots)
    for (int s = 0; s < t.handle_num[root]; ++s) d.f(root, s).setZero();
  ad.report.check_exact = -1;
  if (ad.region_selected) {
    for (int node : ad.active_nodes) top_down(node);
    double exact = 0;
    for (int F : ad.frontier)   // (inactive roots are frontier nodes too)
      if (!t.is_leaf(F)) exact += mc.metric_at(F);
    ad.report.check_exact = std::max(0.0, exact);
  }
  std::fill(ad.active.begin(), ad.active.end(), 0);
  auto& heap = ad.heap;
  heap.clear();
  double frontier_sum = 0;
  for (int root : t.roots) {
    for (int s = 0; s < t.handle_num[root]; ++s) d.f(root, s).setZero();
    if (t.is_leaf(root)) continue;
    const double v = mc.metric_at(root);
    heap.push_back({v, root});
    frontier_sum += v;
  }
  ad.report.total_metric = frontier_sum;
  std::make_heap(heap.begin(), heap.end());
  int dofs = 0;
  while (!heap.empty()) {
    if (opt.mode == AdaptiveOptions::Mode::kThreshold && frontier_sum <= opt.epsilon) break;
    std::pop_heap(heap.begin(), heap.end());
    const auto [value, node] = heap.back();
    heap.pop_back();
    const int nJ = m.v_num[t.joint[node]];
    if (opt.mode == AdaptiveOptions::Mode::kBudget && dofs + nJ > opt.budget) continue;
    ad.active[node] = 1;
    dofs += nJ;
    top_down(node);
    frontier_sum -= value;
    for (int ch : {t.P[node], t.Q[node]}) {
      if (t.is_leaf(ch)) continue;
      const double v = mc.metric_at(ch);
      frontier_sum += v;
      heap.push_back({v, ch});
      std::push_heap(heap.begin(), heap.end());
    }
  }
  for (int b : ad.keep_active_bodies)
    for (int node = t.up[t.leaf_of_body[b]]; node >= 0 && !ad.active[node]; node = t.up[node]) {
      ad.active[node] = 1;
      dofs += m.v_num[t.joint[node]];
    }
  dofs_out = dofs;
  return std::max(0.0, frontier_sum);
}

}  // namespace

double select_active_region(const Model& m, Data& d, State& st, AdaptiveData& ad,
                            const AdaptiveOptions& opt) {
  ensure_metric_scratch(m, ad);
  int dofs = 0;
  const double neglected = select_core(m, d, st, ad, opt, dofs);
  build_region(m, d, st, ad);
  ad.report.neglected_metric = neglected;
  ad.report.active_dofs = dofs;
  ad.report.selections++;
  ad.last_options = opt;
  ad.keep_selected = ad.keep_active_bodies;
  ad.steps_since_selection = 0;
  ad.region_selected = true;
  return ad.report.neglected_metric;
}

namespace {

bool options_changed(const AdaptiveData& ad, const AdaptiveOptions& opt) {
  return opt.mode != ad.last_options.mode || opt.epsilon != ad.last_options.epsilon ||
         opt.budget != ad.last_options.budget;
}

// The bound on the neglected metric of a region selected with value A (total metric T).
double metric_bound(const AdaptiveOptions& opt, double A, double T) {
  return opt.mode == AdaptiveOptions::Mode::kThreshold
             ? std::max(opt.epsilon, A)
             : (1 + opt.estimate_growth) * A + opt.estimate_floor_rel * T;
}

// Error-controlled interval (reselect_every = 0): from the check at this selection — the exact
// neglected metric A₁ of the replaced region after T steps, against its value A₀ when it was
// selected — the growth rate λ = ln(A₁/A₀)/T predicts when the new region's value reaches its
// bound; the next selection comes at half that time (×½ … ×4 of T, ≤ interval_max). A region
// whose bound was already exceeded halves the interval.
int next_interval(const AdaptiveOptions& opt, int T, double A0, double T0, double A1,
                  double A_new, double T_new) {
  const double floor = opt.estimate_floor_rel * std::max(T0, T_new) + 1e-300;
  double next;
  if (A1 > metric_bound(opt, A0, T0)) {
    next = 0.5 * T;
  } else {
    const double lambda = std::log((A1 + floor) / (A0 + floor)) / std::max(1, T);
    const double room = std::log((metric_bound(opt, A_new, T_new) + floor) / (A_new + floor));
    next = lambda <= 0 ? 4.0 * T : std::clamp(0.5 * room / lambda, 0.5 * T, 4.0 * T);
  }
  return static_cast<int>(std::clamp(next, 1.0, double(std::max(1, opt.interval_max))));
}

}  // namespace

bool reselection_due(const AdaptiveData& ad, const AdaptiveOptions& opt) {
  const int every = opt.reselect_every > 0 ? opt.reselect_every : ad.interval;
  return options_changed(ad, opt) || ad.steps_since_selection >= std::max(1, every) ||
         ad.keep_active_bodies != ad.keep_selected;
}

// Poses and velocities of the reference bodies and of every active joint's endpoints, from the
// active joints only (the successor of an active joint is always the reference body of its
// frontier node). O(|active|).
static void reduced_kinematics(const Model& m, Data& d, const State& st,
                               AdaptiveData& ad) noexcept {
  for (int F : ad.frontier) {
    if (ad.comp_ground[F]) {
      d.R[0].setIdentity();
      d.r[0].setZero();
      ad.ref_velocity[F].setZero();
    }
  }
  for (int J : ad.active_joints) {
    const int p = m.parent[J];
    const int fp = ad.frontier_of_body[p];
    const int Fp = ad.coarse_of[fp];
    const int ref = ad.ref_body[Fp];
    // p's pose relative to its frontier node: fine node's placement, then p's in the fine node.
    const Mat3 lR = ad.X_R[fp] * ad.local_R[p];
    const Vec3 lr = ad.X_r[fp] + ad.X_R[fp] * ad.local_r[p];
    const Mat3 Rp = d.R[ref] * lR;
    const Vec3 lp = d.R[ref] * lr;
    joint_placement(m, J, st.q, Rp, d.R[J], d.d[J]);
    ad.pred_offset[J] = lp + d.d[J];
    d.r[J] = d.r[ref] + ad.pred_offset[J];
    d.R[p] = Rp;
    d.r[p] = d.r[ref] + lp;
    const Vec6 vp = shift_motion(ad.ref_velocity[Fp], lp);
    ad.ref_velocity[ad.coarse_of[ad.frontier_of_body[J]]] = joint_motion_terms(m, d, J, st.qd, vp);
  }
}

namespace {

// q (nq_k entries) of joint k.
int q_num(const Model& m, int k) {
  return joint_nq(m.joint_type[k]);
}

// Whether st's active-joint q, q̇ are bitwise those kin_q recorded (record = false), or records them.
bool active_state(const Model& m, const State& st, AdaptiveData& ad, bool record) {
  if (record) ad.kin_q.clear();
  std::size_t i = 0;
  for (int J : ad.active_joints) {
    const int a = m.q_adr[J], n = q_num(m, J), va = m.v_adr[J], nv = m.v_num[J];
    for (int x = 0; x < n; ++x, ++i) {
      if (record) ad.kin_q.push_back(st.q(a + x));
      else if (i >= ad.kin_q.size() || ad.kin_q[i] != st.q(a + x)) return false;
    }
    for (int x = 0; x < nv; ++x, ++i) {
      if (record) ad.kin_q.push_back(st.qd(va + x));
      else if (i >= ad.kin_q.size() || ad.kin_q[i] != st.qd(va + x)) return false;
    }
  }
  return i == ad.kin_q.size();
}

// The hybrid pass; `kinematics` = false reuses the reduced kinematics already in Data (kin_current).
void hybrid_pass(const Model& m, Data& d, const State& st, AdaptiveData& ad,
                 bool kinematics) noexcept {
  const auto& t = m.tree;
  ad.body_terms_current = false;   // composite inertias overwrite Data::I of reference bodies
  // 1. Reduced kinematics and velocities across active joints, in body order.
  if (kinematics) reduced_kinematics(m, d, st, ad);
  // 2. External loads into the frontier nodes, then composite coefficients (§6.2).
  for (int F : ad.frontier) {
    const int ref = ad.ref_body[F];
    const Mat3& R = d.R[ref];
    const Vec3 cw = R * ad.comp_com[F];
    ad.ref_velocity[F] = ad.comp_ground[F] ? Vec6::Zero() : ad.ref_velocity[F];
    if (!ad.comp_ground[F]) {
      const double M = ad.comp_mass[F];
      const Mat3 Ic = R * ad.comp_Ic[F] * R.transpose();
      d.I[ref] = spatial_inertia(M, cw, Ic);
      d.Iinv[ref] = spatial_inertia_inverse(M, cw, Ic);   // also read by coupling snapshots
      d.f_total[ref] = gravity_force(M, cw, ad.gravity_scale * m.gravity);
    }
  }
  auto add_load = [&](int k) {
    const int f = ad.frontier_of_body[k], F = ad.coarse_of[f];
    if (ad.comp_ground[F]) return;
    const int ref = ad.ref_body[F];
    const Vec3 lr = ad.X_r[f] + ad.X_R[f] * ad.local_r[k];
    d.f_total[ref] += shift_force(st.f_ext[k], -(d.R[ref] * lr));
  };
  std::int64_t work = static_cast<std::int64_t>(ad.frontier.size() + ad.active_joints.size());
  if (ad.scan_forces) {
    // 8 bodies at a time: a branch-free test that vectorizes (the bits of each value without its
    // sign: non-zero for every x != 0 and NaN, zero for ±0, as isZero(0)); only a group holding a
    // load is looked into. Body by body this O(n) scan was a tenth of the step on 4096 bodies.
    static_assert(sizeof(Vec6) == 6 * sizeof(double), "f_ext is read as one array");
    const double* f = st.f_ext.empty() ? nullptr : st.f_ext[0].data();
    constexpr int kGroup = 8;
    ad.scan_loaded.clear();
    work += m.nbodies;
    for (int k0 = 1; k0 < m.nbodies; k0 += kGroup) {
      const int k1 = std::min(m.nbodies, k0 + kGroup);
      std::uint64_t bits = 0;
      if (k1 - k0 == kGroup) {
        for (int i = 0; i < 6 * kGroup; ++i) {
          std::uint64_t w;
          std::memcpy(&w, f + 6 * k0 + i, sizeof w);
          bits |= w << 1;
        }
      } else {
        for (int i = 6 * k0; i < 6 * k1; ++i) {
          std::uint64_t w;
          std::memcpy(&w, f + i, sizeof w);
          bits |= w << 1;
        }
      }
      if (!bits) continue;
      for (int k = k0; k < k1; ++k)
        if (!st.f_ext[k].isZero(0)) {
          add_load(k);
          ad.scan_loaded.push_back(k);
        }
    }
  } else {
    for (int k : ad.loaded_bodies) add_load(k);
    work += static_cast<std::int64_t>(ad.loaded_bodies.size());
  }
  std::int64_t up_count = 0;
  for (int F : ad.frontier) {
    const int h = t.handle_num[F];
    ++up_count;
    if (!t.is_leaf(F)) d.cluster_live[F] = 0;   // rigid here: read in mobility form (Φ below)
    if (ad.comp_ground[F]) {
      for (int x = 0; x < h; ++x) {
        for (int y = 0; y < h; ++y) d.Phi(F, h, x, y).setZero();
        d.b(F, x).setZero();
      }
      continue;
    }
    const int ref = ad.ref_body[F];
    const Vec6& V = ad.ref_velocity[F];
    // p_bias too: the light-leaf form of dca_assemble reads a leaf's inertia and bias force.
    d.p_bias[ref] = d.f_total[ref] - cross_force(V, d.I[ref] * V);
    const Vec6 a0 = d.Iinv[ref] * d.p_bias[ref];
    // Handle point offsets from local data: 0 for the joint entering F (its successor is the
    // reference body), the predecessor-side offset for joints leaving F.
    auto offset = [&](int jx) {
      return ad.coarse_of[ad.frontier_of_body[jx]] == F ? Vec3::Zero() : ad.pred_offset[jx];
    };
    // Φ_xy = M_x I⁻¹ M_yᵀ with M_x = [[1, 0], [−S_x, 1]], S_x = [o_x]×, I⁻¹ = [[A, B], [L, D]]:
    // M_x I⁻¹ = [[A, B], [L − S_x A, D − S_x B]] =: [[A, B], [U_x, V_x]], and
    // Φ_xy = [[A, A S_y + B], [U_x, U_x S_y + V_x]] — the 6×6 products without their 0/1 terms.
    const Mat6& Ii = d.Iinv[ref];
    const Mat3 A = Ii.topLeftCorner<3, 3>(), B = Ii.topRightCorner<3, 3>();
    Mat3* U = ad.scratch_U.data();
    Mat3* Vb = ad.scratch_Vb.data();
    Mat3* Sk = ad.scratch_Sk.data();
    for (int x = 0; x < h; ++x) {
      const Vec3 o = offset(t.handle(F, x));
      Sk[x] = skew(o);
      U[x] = Ii.bottomLeftCorner<3, 3>();
      U[x].noalias() -= Sk[x] * A;
      Vb[x] = Ii.bottomRightCorner<3, 3>();
      Vb[x].noalias() -= Sk[x] * B;
      d.b(F, x) = shift_motion(a0, o);
    }
    for (int x = 0; x < h; ++x)
      for (int y = x; y < h; ++y) {
        auto blk = d.Phi(F, h, x, y);
        blk.topLeftCorner<3, 3>() = A;
        blk.topRightCorner<3, 3>() = B;
        blk.topRightCorner<3, 3>().noalias() += A * Sk[y];
        blk.bottomLeftCorner<3, 3>() = U[x];
        blk.bottomRightCorner<3, 3>() = Vb[x];
        blk.bottomRightCorner<3, 3>().noalias() += U[x] * Sk[y];
        if (y != x) d.Phi(F, h, y, x) = blk.transpose();
      }
  }
  // 3. Hybrid bottom-up and top-down over the active region only. The inertia-form regions'
  // offsets are compensated sums of d_k (as dca_cluster_offsets, but over those regions
  // only, O(|active|)): every joint inside them is active, so d_k is current there.
  for (int k : ad.if_bodies) {
    if (ad.if_top[k]) {
      d.cluster_offset[k].setZero();
      d.cluster_offset_lo[k].setZero();
      continue;
    }
    chain_cluster_offset(m, d, k);
  }
  for (auto it = ad.active_nodes.rbegin(); it != ad.active_nodes.rend(); ++it) {
    if (ad.inertia_form[*it]) dca_bottom_up_node(m, d, *it, st.tau);
    else dca_assemble(m, d, *it, st.tau);
    ++up_count;
  }
  for (int root : t.roots)
    for (int s = 0; s < t.handle_num[root]; ++s) d.f(root, s).setZero();
  for (int node : ad.active_nodes) dca_top_down_node(m, d, node);
  ad.step_work += work + up_count + static_cast<std::int64_t>(ad.active_nodes.size());
  ad.report.nodes_bottom_up = up_count;
  ad.report.nodes_top_down = static_cast<std::int64_t>(ad.active_nodes.size());
  ad.report.active_nodes = static_cast<int>(ad.active_nodes.size());
  ad.report.frontier_nodes = static_cast<int>(ad.frontier.size());
  d.diag.nodes_bottom_up = up_count;
  d.diag.nodes_top_down = ad.report.nodes_top_down;
}

}  // namespace

const Eigen::VectorXd& adaptive_forward_dynamics(const Model& m, Data& d, const State& st,
                                                 AdaptiveData& ad) noexcept {
  ad.kin_current = false;   // any state: the kinematics it writes are not the step's
  hybrid_pass(m, d, st, ad, true);
  return d.qdd;
}

// ---------------------------------------------------------------------------------------------
// Background selection. The worker owns a Data, a State and an AdaptiveData of its own (its
// incremental metric caches persist between its selections). A job is the state of the step it
// was asked at and the region in force then; it returns the new region and the frontier caches of
// the *union* of both regions (fine level): no joint inside a union frontier node moves while the
// old region is in force (V1), so those caches are still exact when the main thread installs them.
struct AsyncSelector {
  explicit AsyncSelector(const Model& model)
      : m(model), d(model, Refinement::kOff), st(model), ad(model, true) {
    const int nn = model.tree.nnodes(), nb = model.nbodies;
    in_active_nodes.reserve(nn);
    in_frontier.reserve(nn);
    new_nodes.reserve(nn);
    new_joints.reserve(nb);
    loaded.reserve(nb);
    th = std::thread([this] { loop(); });
  }
  ~AsyncSelector() {
    {
      std::lock_guard<std::mutex> lk(mu);
      quit = true;
    }
    cv.notify_all();
    th.join();
  }
  void loop() {
    // Below the stepping thread's priority: on a machine with fewer free cores than busy threads the
    // step and the coupling loop keep their rate and the selection takes what is left.
    setpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)), 10);
    std::unique_lock<std::mutex> lk(mu);
    for (;;) {
      cv.wait(lk, [&] { return quit || status == kQueued; });
      if (quit) return;
      lk.unlock();
      run();
      lk.lock();
      status = kDone;
      cv.notify_all();
    }
  }
  void run() {
    const auto& t = m.tree;
    ad.active_nodes = in_active_nodes;
    ad.frontier = in_frontier;
    ad.region_selected = in_region_selected;
    int dofs = 0;
    neglected = select_core(m, d, st, ad, opt, dofs);
    active_dofs = dofs;
    rep = ad.report;
    new_nodes.clear();
    new_joints.clear();
    for (int node = 0; node < t.nnodes(); ++node)
      if (ad.active[node]) {
        new_nodes.push_back(node);
        new_joints.push_back(t.joint[node]);
      }
    std::sort(new_joints.begin(), new_joints.end());
    for (int node : in_active_nodes) ad.active[node] = 1;
    build_caches(m, d, ad);   // the union region: fine frontier lists and caches
  }
  enum Status { kIdle, kQueued, kDone };
  const Model& m;
  Data d;
  State st;
  AdaptiveData ad;
  std::thread th;
  std::mutex mu;
  std::condition_variable cv;
  bool quit = false;
  std::atomic<int> status{kIdle};
  // Job.
  AdaptiveOptions opt;
  std::vector<int> in_active_nodes, in_frontier, loaded;
  bool in_region_selected = false;
  std::int64_t version = 0, asked_at = 0;
  bool stale = false;
  // Result (besides the fine caches in ad).
  std::vector<int> new_nodes, new_joints;
  double neglected = 0;
  int active_dofs = 0;
  AdaptiveReport rep;
};

AsyncSelectorHandle::~AsyncSelectorHandle() { delete p; }

namespace {

// The selection's buffers: Ψ, p, η and the incremental metric's cache (Φ, Ψ, W in each node's
// reference frame, the q they hold, the moved-node marks). One set serves both threads: the worker
// borrows it for each background selection, the stepping thread takes it back for a synchronous one.
void swap_metric_scratch(AdaptiveData& a, AdaptiveData& b) {
  std::swap(a.Psi_buf, b.Psi_buf);
  std::swap(a.p_buf, b.p_buf);
  std::swap(a.eta, b.eta);
  std::swap(a.Phi_loc, b.Phi_loc);
  std::swap(a.Psi_loc, b.Psi_loc);
  std::swap(a.W_loc, b.W_loc);
  std::swap(a.q_cached, b.q_cached);
  std::swap(a.metric_cached, b.metric_cached);
  std::swap(a.selections_since_refresh, b.selections_since_refresh);
  std::swap(a.node_moved, b.node_moved);
  std::swap(a.world_ok, b.world_ok);
  std::swap(a.scratch_joint_moved, b.scratch_joint_moved);
}

}  // namespace

void ensure_metric_scratch(const Model& m, AdaptiveData& ad) {
  if (!ad.Psi_buf.empty()) return;
  if (AsyncSelector* w = ad.worker.p) {
    adaptive_selection_wait(ad);   // the worker is done with it (its result stays to be judged)
    if (!w->ad.Psi_buf.empty()) {
      swap_metric_scratch(ad, w->ad);
      return;
    }
  }
  allocate_metric_scratch(m, ad);
}

namespace {

template <class T, class A>
std::size_t heap_bytes(const std::vector<T, A>& v) { return v.capacity() * sizeof(T); }
std::size_t heap_bytes(const Eigen::VectorXd& v) { return v.size() * sizeof(double); }

}  // namespace

std::vector<MemoryItem> memory_usage(const AdaptiveData& ad, const std::string& p) {
  std::vector<MemoryItem> out;
  auto add = [&](const char* name, std::size_t bytes) { out.push_back({p + name, bytes}); };
  auto append = [&](std::vector<MemoryItem> items) { out.insert(out.end(), items.begin(), items.end()); };
  add("active", heap_bytes(ad.active));
  add("active_nodes", heap_bytes(ad.active_nodes));
  add("frontier", heap_bytes(ad.frontier));
  add("active_joints", heap_bytes(ad.active_joints));
  add("frontier_of_body", heap_bytes(ad.frontier_of_body));
  add("fine_frontier", heap_bytes(ad.fine_frontier));
  add("coarse_of", heap_bytes(ad.coarse_of));
  add("X_R", heap_bytes(ad.X_R));
  add("X_r", heap_bytes(ad.X_r));
  add("ref_body", heap_bytes(ad.ref_body));
  add("comp_mass", heap_bytes(ad.comp_mass));
  add("comp_com", heap_bytes(ad.comp_com));
  add("comp_Ic", heap_bytes(ad.comp_Ic));
  add("comp_ground", heap_bytes(ad.comp_ground));
  add("local_R", heap_bytes(ad.local_R));
  add("local_r", heap_bytes(ad.local_r));
  add("ref_velocity", heap_bytes(ad.ref_velocity));
  add("pred_offset", heap_bytes(ad.pred_offset));
  add("inertia_form", heap_bytes(ad.inertia_form));
  add("if_bodies", heap_bytes(ad.if_bodies));
  add("if_top", heap_bytes(ad.if_top));
  add("Psi_buf", heap_bytes(ad.Psi_buf));
  add("p_buf", heap_bytes(ad.p_buf));
  add("eta", heap_bytes(ad.eta));
  add("Phi_loc", heap_bytes(ad.Phi_loc));
  add("Psi_loc", heap_bytes(ad.Psi_loc));
  add("W_loc", heap_bytes(ad.W_loc));
  add("q_cached", heap_bytes(ad.q_cached));
  add("node_moved", heap_bytes(ad.node_moved));
  add("world_ok", heap_bytes(ad.world_ok));
  add("scratch_joint_moved", heap_bytes(ad.scratch_joint_moved));
  add("kin_q", heap_bytes(ad.kin_q));
  add("keep_active_bodies", heap_bytes(ad.keep_active_bodies));
  add("keep_selected", heap_bytes(ad.keep_selected));
  add("loaded_bodies", heap_bytes(ad.loaded_bodies));
  add("scratch_K", heap_bytes(ad.scratch_K));
  add("scratch_V", heap_bytes(ad.scratch_V));
  add("scratch_Y", heap_bytes(ad.scratch_Y));
  add("scratch_U", heap_bytes(ad.scratch_U));
  add("scratch_Vb", heap_bytes(ad.scratch_Vb));
  add("scratch_Sk", heap_bytes(ad.scratch_Sk));
  add("scratch_f", heap_bytes(ad.scratch_f));
  add("heap", heap_bytes(ad.heap));
  add("scratch_stack", heap_bytes(ad.scratch_stack));
  add("scratch_joint_active", heap_bytes(ad.scratch_joint_active));
  add("scratch_h", heap_bytes(ad.scratch_h));
  add("scratch_hn", heap_bytes(ad.scratch_hn));
  add("scratch_nodes", heap_bytes(ad.scratch_nodes));
  add("scratch_joints", heap_bytes(ad.scratch_joints));
  add("scratch_union", heap_bytes(ad.scratch_union));
  add("scan_loaded", heap_bytes(ad.scan_loaded));
  add("scratch_mark", heap_bytes(ad.scratch_mark));
  append(memory_usage(ad.impulse, p + "impulse."));
  if (const AsyncSelector* w = ad.worker.p) {
    append(memory_usage(w->d, "worker.Data."));
    append(memory_usage(w->st, "worker.State."));
    append(memory_usage(w->ad, "worker.AdaptiveData."));
    out.push_back({"worker.in_active_nodes", heap_bytes(w->in_active_nodes)});
    out.push_back({"worker.in_frontier", heap_bytes(w->in_frontier)});
    out.push_back({"worker.loaded", heap_bytes(w->loaded)});
    out.push_back({"worker.new_nodes", heap_bytes(w->new_nodes)});
    out.push_back({"worker.new_joints", heap_bytes(w->new_joints)});
  }
  return out;
}

namespace {

// Copies the state of this step (q, q̇, τ, the loaded bodies' f_ext) and the region in force to the
// worker and starts it. O(nq + nv) copies (memcpy) plus O(|region| + |loaded|). Never waits: if the
// worker still holds its mutex (between publishing its last result and going back to sleep, at its
// lower priority), nothing is posted and the next step tries again. Returns whether it posted.
bool post_selection(const Model& m, const State& st, AdaptiveData& ad, const AdaptiveOptions& opt) {
  AsyncSelector& w = *ad.worker.p;
  std::unique_lock<std::mutex> lk(w.mu, std::try_to_lock);
  if (!lk.owns_lock()) return false;
  if (w.ad.Psi_buf.empty()) swap_metric_scratch(ad, w.ad);   // lent for this selection
  w.st.q = st.q;
  w.st.qd = st.qd;
  w.st.tau = st.tau;
  w.st.t = st.t;
  for (int k : w.loaded) w.st.f_ext[k].setZero();
  w.loaded = ad.scan_forces ? ad.scan_loaded : ad.loaded_bodies;
  for (int k : w.loaded) w.st.f_ext[k] = st.f_ext[k];
  w.opt = opt;
  w.opt.background_selection = false;
  w.in_active_nodes = ad.active_nodes;
  w.in_frontier = ad.frontier;
  w.in_region_selected = ad.region_selected;
  w.ad.keep_active_bodies = ad.keep_active_bodies;
  w.version = ad.region_version;
  w.asked_at = ad.step_count;
  w.stale = false;
  ad.step_work += static_cast<std::int64_t>(ad.active_nodes.size() + ad.frontier.size() + w.loaded.size());
  w.status = AsyncSelector::kQueued;
  lk.unlock();
  w.cv.notify_all();
  (void)m;
  return true;
}

// Installs the worker's region: the union's fine caches are swapped in (O(1)); poses and velocities
// of the fine nodes from the current q, q̇ over the union's joints; the momentum of the moving fine
// nodes for the impulsive lock; the coarse level (frontier in force) over the fine one; the lock by
// one hybrid pass on the new region. O(|old region| + |new region|).
void install_selection(const Model& m, Data& d, State& st, AdaptiveData& ad, AsyncSelector& w) {
  const auto& t = m.tree;
  std::int64_t work = 0;
  std::swap(ad.frontier_of_body, w.ad.frontier_of_body);
  std::swap(ad.local_R, w.ad.local_R);
  std::swap(ad.local_r, w.ad.local_r);
  std::swap(ad.comp_mass, w.ad.comp_mass);
  std::swap(ad.comp_com, w.ad.comp_com);
  std::swap(ad.comp_Ic, w.ad.comp_Ic);
  std::swap(ad.comp_ground, w.ad.comp_ground);
  ad.fine_frontier.assign(w.ad.frontier.begin(), w.ad.frontier.end());
  // 1. Fine nodes as frontier nodes of the union region: their poses and velocities now.
  for (int f : ad.fine_frontier) {
    ad.coarse_of[f] = f;
    ad.X_R[f].setIdentity();
    ad.X_r[f].setZero();
  }
  std::swap(ad.frontier, ad.fine_frontier);
  std::vector<int>& union_joints = ad.scratch_joints;
  union_joints.assign(w.ad.active_joints.begin(), w.ad.active_joints.end());
  std::swap(ad.active_joints, union_joints);
  reduced_kinematics(m, d, st, ad);
  std::swap(ad.active_joints, union_joints);
  std::swap(ad.frontier, ad.fine_frontier);
  work += static_cast<std::int64_t>(ad.fine_frontier.size() + union_joints.size());
  // Joints of the union that the new region locks (only they can move now).
  auto& joint_new = ad.scratch_joint_active;   // (nbodies), all zero between uses
  for (int J : w.new_joints) joint_new[J] = 1;
  bool any = false;
  for (int J : union_joints)
    if (!joint_new[J] && m.v_num[J] > 0 && !st.qd.segment(m.v_adr[J], m.v_num[J]).isZero(0)) any = true;
  // 2. Momenta (lock_velocities' h, from fine composites): the subtree momentum at each joint.
  State& impulse = ad.impulse;
  if (any) {
    auto& hn = ad.scratch_hn;
    for (int f : ad.fine_frontier) {
      if (ad.comp_ground[f]) {
        hn[f].setZero();
        continue;
      }
      const Mat3& R = d.R[ad.ref_body[f]];
      const Mat3 Ic = R * ad.comp_Ic[f] * R.transpose();
      hn[f] = spatial_inertia(ad.comp_mass[f], R * ad.comp_com[f], Ic) * ad.ref_velocity[f];
    }
    for (auto it = union_joints.rbegin(); it != union_joints.rend(); ++it) {
      const int J = *it;
      const Vec6& h = hn[ad.frontier_of_body[J]];
      if (joint_new[J]) {
        const int a = m.v_adr[J];
        impulse.q.segment(m.q_adr[J], q_num(m, J)) = st.q.segment(m.q_adr[J], q_num(m, J));
        switch (m.joint_type[J]) {
          case JointType::kRevolute:
          case JointType::kPrismatic: impulse.tau(a) = d.S[J].dot(h); break;
          case JointType::kSpherical: impulse.tau.segment<3>(a) = d.R[J].transpose() * h.head<3>(); break;
          case JointType::kFree:
            impulse.tau.segment<3>(a) = d.R[J].transpose() * h.head<3>();
            impulse.tau.segment<3>(a + 3) = d.R[J].transpose() * h.tail<3>();
            break;
          case JointType::kFixed: break;
        }
      }
      const int fp = ad.frontier_of_body[m.parent[J]];
      hn[fp] += shift_force(h, -ad.pred_offset[J]);
    }
  }
  // 3. The coarse level: the new region's frontier nodes over the fine ones.
  auto& old_active = ad.scratch_mark;   // (nnodes), all zero between uses
  for (int node : ad.active_nodes) {
    old_active[node] = 1;
    ad.active[node] = 0;
    ad.inertia_form[node] = 0;
    d.kind[node] = NodeKind::kRigid;
  }
  for (int k : ad.if_bodies) ad.if_top[k] = 0;
  ad.active_nodes.assign(w.new_nodes.begin(), w.new_nodes.end());
  ad.active_joints.assign(w.new_joints.begin(), w.new_joints.end());
  for (int node : ad.active_nodes) {
    ad.active[node] = 1;
    d.kind[node] = NodeKind::kActive;
  }
  ad.frontier.clear();
  for (int root : t.roots)
    if (t.is_leaf(root) || !ad.active[root]) ad.frontier.push_back(root);
  for (int node : ad.active_nodes)
    for (int ch : {t.P[node], t.Q[node]})
      if (t.is_leaf(ch) || !ad.active[ch]) ad.frontier.push_back(ch);
  std::vector<int>& stack = ad.scratch_stack;
  std::vector<int>& inner = ad.scratch_union;
  for (int F : ad.frontier) {
    ++work;
    if (t.is_leaf(F) || !old_active[F]) continue;   // a fine node itself (identity placement)
    // F was active: its inner joints (old region only) place its fine nodes, top-down.
    inner.clear();
    stack.assign(1, F);
    const int ref = ad.ref_body[F];
    while (!stack.empty()) {
      const int n = stack.back();
      stack.pop_back();
      ++work;
      if (!t.is_leaf(n) && old_active[n]) {
        inner.push_back(t.joint[n]);
        stack.push_back(t.P[n]);
        stack.push_back(t.Q[n]);
      } else {
        ad.coarse_of[n] = F;
      }
    }
    std::sort(inner.begin(), inner.end());
    for (int J : inner) {
      const int p = m.parent[J], fp = ad.frontier_of_body[p];
      const Mat3 lR = ad.X_R[fp] * ad.local_R[p];
      const Vec3 lr = ad.X_r[fp] + ad.X_R[fp] * ad.local_r[p];
      const int f = ad.frontier_of_body[J];
      Vec3 dj;
      joint_placement(m, J, st.q, lR, ad.X_R[f], dj);
      ad.X_r[f] = lr + dj;
    }
    // Composite of F from its fine nodes (as build_caches from bodies).
    double M = 0;
    Vec3 mc = Vec3::Zero();
    bool ground = false;
    auto each_fine = [&](auto&& fn) {
      stack.assign(1, F);
      while (!stack.empty()) {
        const int n = stack.back();
        stack.pop_back();
        if (!t.is_leaf(n) && old_active[n]) {
          stack.push_back(t.P[n]);
          stack.push_back(t.Q[n]);
        } else {
          fn(n);
        }
      }
    };
    each_fine([&](int f) {
      ground = ground || ad.comp_ground[f];
      M += ad.comp_mass[f];
      mc += ad.comp_mass[f] * (ad.X_r[f] + ad.X_R[f] * ad.comp_com[f]);
    });
    const Vec3 com = M > 0 ? Vec3(mc / M) : Vec3::Zero();
    Mat3 Ic = Mat3::Zero();
    each_fine([&](int f) {
      const Vec3 dk = ad.X_r[f] + ad.X_R[f] * ad.comp_com[f] - com;
      Ic += ad.X_R[f] * ad.comp_Ic[f] * ad.X_R[f].transpose() +
            ad.comp_mass[f] * (dk.squaredNorm() * Mat3::Identity() - dk * dk.transpose());
    });
    ad.comp_ground[F] = ground;
    ad.comp_mass[F] = M;
    ad.comp_com[F] = com;
    ad.comp_Ic[F] = Ic;
    (void)ref;
  }
  for (int node : w.in_active_nodes) old_active[node] = 0;
  build_inertia_form(m, ad);
  for (int J : union_joints) d.qdd.segment(m.v_adr[J], m.v_num[J]).setZero();
  // 4. The impulsive lock on the new region (lock_velocities' solve: H_aa⁻¹ p_a by one pass).
  if (any) {
    std::vector<int> no_loads;
    std::swap(ad.loaded_bodies, no_loads);
    const bool scan = ad.scan_forces;
    ad.scan_forces = false;
    ad.gravity_scale = 0;
    adaptive_forward_dynamics(m, d, impulse, ad);
    ad.gravity_scale = 1;
    ad.scan_forces = scan;
    std::swap(ad.loaded_bodies, no_loads);
    for (int J : union_joints) {
      const int a = m.v_adr[J], n = m.v_num[J];
      if (joint_new[J]) st.qd.segment(a, n) = d.qdd.segment(a, n);
      else st.qd.segment(a, n).setZero();
      d.qdd.segment(a, n).setZero();
      impulse.tau.segment(a, n).setZero();
    }
  }
  for (int J : w.new_joints) joint_new[J] = 0;
  ad.kin_current = false;
  ad.body_terms_current = false;
  ad.step_work += work;
}

}  // namespace

void start_background_selection(const Model& m, AdaptiveData& ad) {
  if (!ad.worker.p) ad.worker.p = new AsyncSelector(m);
}

void request_reselection(AdaptiveData& ad) {
  if (ad.worker.p) ad.worker.p->stale = true;   // a selection in flight is dropped when done
  ad.steps_since_selection = 1 << 30;
  ad.kin_current = false;
  ad.body_terms_current = false;
}

bool adaptive_selection_wait(AdaptiveData& ad) {
  AsyncSelector* w = ad.worker.p;
  if (!w || w->status.load() == AsyncSelector::kIdle) return false;
  std::unique_lock<std::mutex> lk(w->mu);
  w->cv.wait(lk, [&] { return w->status.load() != AsyncSelector::kQueued; });
  return true;
}

const AdaptiveReport& adaptive_step(const Model& m, Data& d, State& st, AdaptiveData& ad,
                                    const AdaptiveOptions& opt, double dt) {
  ad.report.reselected = false;
  ad.step_work = 0;
  AsyncSelector* w = ad.worker.p;
  bool installed = false;
  // A background selection that is done: installed if it was asked for the region still in force
  // and the same options, else dropped.
  if (w && w->status.load(std::memory_order_acquire) == AsyncSelector::kDone) {
    if (!w->stale && w->version == ad.region_version && !options_changed(ad, opt) &&
        opt.background_selection) {
      const int T = static_cast<int>(w->asked_at - ad.selected_at);
      const double A0 = ad.report.neglected_metric, T0 = ad.report.total_metric;
      install_selection(m, d, st, ad, *w);
      installed = true;
      const std::int64_t selections = ad.report.selections;
      ad.report = w->rep;
      ad.report.selections = selections + 1;
      ad.report.neglected_metric = w->neglected;
      ad.report.active_dofs = w->active_dofs;
      ad.report.reselected = true;
      ad.report.handover_lag = static_cast<int>(ad.step_count - w->asked_at);
      ad.selected_at = w->asked_at;
      std::swap(ad.keep_selected, w->ad.keep_active_bodies);   // no copy: the next post rewrites the worker's
      ad.steps_since_selection = ad.report.handover_lag;
      if (opt.reselect_every <= 0) {
        ad.interval = ad.report.check_exact < 0
                          ? std::max(1, opt.interval_first)
                          : next_interval(opt, std::max(1, T), A0, T0, ad.report.check_exact,
                                          ad.report.neglected_metric, ad.report.total_metric);
      }
      ad.report.interval = ad.interval;
    }
    if (ad.Psi_buf.empty()) swap_metric_scratch(ad, w->ad);   // taken back
    w->status.store(AsyncSelector::kIdle, std::memory_order_release);
  }
  bool post = false;
  if (reselection_due(ad, opt)) {
    const bool changed = options_changed(ad, opt) || !ad.region_selected;
    if (!changed && opt.background_selection && w) {
      // Not in the step that installed a region (its handover already does the work of about one
      // hybrid pass): the state copy for the worker waits for the next step.
      post = !installed && w->status.load(std::memory_order_acquire) == AsyncSelector::kIdle;   // else in flight
    } else {
      if (w) w->stale = true;
      const int T = ad.steps_since_selection;
      const double A0 = ad.report.neglected_metric, T0 = ad.report.total_metric;
      select_active_region(m, d, st, ad, opt);
      ad.report.reselected = true;
      ad.report.handover_lag = 0;
      ad.selected_at = ad.step_count;
      if (opt.reselect_every <= 0) {
        ad.interval = changed || ad.report.check_exact < 0
                          ? std::max(1, opt.interval_first)
                          : next_interval(opt, T, A0, T0, ad.report.check_exact,
                                          ad.report.neglected_metric, ad.report.total_metric);
      }
      ad.report.interval = ad.interval;
      // The worker is started with the first selection (allocations and all), not inside a step.
      if (opt.background_selection && !w) ad.worker.p = new AsyncSelector(m);
    }
  }
  ++ad.steps_since_selection;
  // The last step ended with the reduced kinematics of this q, q̇ (unless the caller changed the
  // state or a selection ran): no need to compute them twice.
  const bool reuse = ad.kin_current && active_state(m, st, ad, false);
  ad.report.kinematics_reused = reuse;
  ad.kin_current = false;
  hybrid_pass(m, d, st, ad, !reuse);
  // The state at the start of this step (its loads just scanned) goes to the worker.
  if (post) post_selection(m, st, ad, opt);
  ad.report.selection_pending = ad.worker.p && ad.worker.p->status.load() != AsyncSelector::kIdle;
  for (int J : ad.active_joints) {
    const int a = m.v_adr[J], n = m.v_num[J];
    st.qd.segment(a, n) += dt * d.qdd.segment(a, n);
    integrate_joint(m, J, st.q, st.qd, dt);
  }
  // Poses and velocities for the new q, q̇, so update_all_body_poses and snapshots are current.
  reduced_kinematics(m, d, st, ad);
  active_state(m, st, ad, true);
  ad.kin_current = true;
  ad.step_work += 2 * static_cast<std::int64_t>(ad.active_joints.size());
  ++ad.step_count;
  st.t += dt;
  return ad.report;
}

void update_all_body_poses(const Model& m, Data& d, const AdaptiveData& ad) noexcept {
  for (int k = 0; k < m.nbodies; ++k) {
    const int f = ad.frontier_of_body[k];
    if (f < 0) continue;
    const int ref = ad.ref_body[ad.coarse_of[f]];
    if (k == ref) continue;
    const Mat3 lR = ad.X_R[f] * ad.local_R[k];
    const Vec3 lr = ad.X_r[f] + ad.X_R[f] * ad.local_r[k];
    d.R[k] = d.R[ref] * lR;
    d.r[k] = d.r[ref] + d.R[ref] * lr;
  }
  // d_k of a reference body is its joint's placement (reduced kinematics, or the selection's
  // forward kinematics for a rigid root); the hybrid pass reads it, so it is kept, not re-derived.
  for (int k = 1; k < m.nbodies; ++k) {
    const int F = frontier_of(ad, k);
    if (F >= 0 && ad.ref_body[F] == k) continue;
    d.d[k] = d.r[k] - d.r[m.parent[k]];
  }
}

}  // namespace haptree
