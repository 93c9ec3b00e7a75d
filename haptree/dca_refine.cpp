// Iterative refinement of q̈ (Data::refine; docs/accuracy_and_stability.md): one step
// q̈ ← q̈ + H⁻¹ r with the residual r = τ − ID(q, q̇, q̈) by RNEA at the handle points (in long
// double from q itself for Refinement::kExtended, inverse_dynamics.hpp). H⁻¹ r is a second pass
// over the first one's matrices: the bias half of every node's assembly (p_bias = 0, c = 0, τ = r;
// Φ, W and the leaf-form and cluster factors depend on the poses only) and a top-down pass. It
// runs on swapped bias buffers, so the node coefficients left after the call are the pass's, bit
// for bit. A correction larger than q̈, or not finite, is dropped and counted
// (Diagnostics::refine_rejected).
#include <cmath>
#include <utility>

#include "haptree/dca_detail.hpp"

namespace haptree {

namespace {

// r = τ − ID(q, q̇, q̈) (RNEA at the handle points r_k, world axes; needs body_dynamics_terms):
// a_k = shift(a_parent, d_k) + S_k q̈_k + c_k, f_k = I_k a_k − p_bias_k + Σ children's f moved
// to r_k, τ_k = S_kᵀ f_k (the joint force of τ is D τ with D = S, orthonormal columns). The
// ground does not accelerate: gravity is in p_bias as a force.
void inverse_dynamics_residual(const Model& m, Data& d, const Eigen::VectorXd& tau,
                               const Eigen::VectorXd& qdd) {
  d.refine_a[0].setZero();
  for (int k = 1; k < m.nbodies; ++k) {
    d.refine_a[k] = shift_motion(d.refine_a[m.parent[k]], d.d[k]) + joint_velocity(m, d, k, qdd) +
                    d.c[k];
    d.refine_f[k] = d.I[k] * d.refine_a[k] - d.p_bias[k];
  }
  for (int k = m.nbodies - 1; k >= 1; --k) {
    const Vec6& f = d.refine_f[k];
    const int a = m.v_adr[k];
    switch (m.joint_type[k]) {
      case JointType::kRevolute:
      case JointType::kPrismatic: d.refine_r(a) = tau(a) - d.S[k].dot(f); break;
      case JointType::kSpherical:
        d.refine_r.segment<3>(a) = tau.segment<3>(a) - d.R[k].transpose() * f.head<3>();
        break;
      case JointType::kFree:
        d.refine_r.segment<3>(a) = tau.segment<3>(a) - d.R[k].transpose() * f.head<3>();
        d.refine_r.segment<3>(a + 3) = tau.segment<3>(a + 3) - d.R[k].transpose() * f.tail<3>();
        break;
      case JointType::kFixed: break;
    }
    const int p = m.parent[k];
    if (p > 0) d.refine_f[p] += shift_force(f, -d.d[k]);
  }
}

// The bias half of one node's assembly, for the correction pass of Data::refine (p_bias = 0, c = 0,
// τ = r): the matrices (Φ, W, the leaf-form and cluster factors) depend on the poses and inertias
// only, which the correction shares with the pass, so only the vectors are recomputed — 6×6
// products with vectors instead of the assembly's 6×6×5 ones. Each form keeps its own formulas, so
// the correction is as accurate as the pass (a mobility-form β at a light leaf loses ~‖Φ_L‖/‖Φ_C‖,
// 10¹² at a 10¹² mass ratio, and made the refinement diverge there). Inertia-form cluster nodes are
// reassembled whole (their bias terms need the factors of M and U; one per weld).
void bias_assemble_node(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) {
  const auto& t = m.tree;
  if (t.is_leaf(node)) {
    const int k = t.body[node], h = t.handle_num[node];
    if (k == 0) {
      for (int x = 0; x < h; ++x) d.b(node, x).setZero();
      return;
    }
    const Vec6 a0 = d.Iinv[k] * d.p_bias[k];
    for (int x = 0; x < h; ++x) {
      const int jx = t.handle(node, x);
      d.b(node, x) = jx == k ? a0 : shift_motion(a0, d.d[jx]);
    }
    return;
  }
  if (m.cluster_index[node] < 0 && !d.leaf_side.empty() && d.leaf_side[node]) {
    detail::leaf_form_bias(m, d, node, tau);
    return;
  }
  const int P = t.P[node], Q = t.Q[node], J = t.joint[node];
  const int j = t.slot_j[node], k = t.slot_k[node];
  const int hP = t.handle_num[P], hQ = t.handle_num[Q];
  const Mat6& W = d.W[node];
  Vec6& taut = d.taut[node];
  const int nJ = m.v_num[J];
  if (nJ > 0) {
    Vec6 Dtau;
    if (m.joint_type[J] == JointType::kRevolute || m.joint_type[J] == JointType::kPrismatic) {
      Dtau = d.S[J] * tau(m.v_adr[J]);
    } else {
      JointMat S, T, D;
      joint_subspaces(m, d, J, S, T, D);
      Dtau = D * tau.segment(m.v_adr[J], nJ);
    }
    const Vec6 PhDtau = d.Phi(P, hP, j, j) * Dtau + d.Phi(Q, hQ, k, k) * Dtau;
    taut = Dtau - W * PhDtau;
  } else {
    taut.setZero();
  }
  const Vec6 beta = W * (d.c[J] - d.b(Q, k) + d.b(P, j)) + taut;
  d.beta[node] = beta;
  if (m.cluster_index[node] >= 0) {
    detail::assemble_inertia_form(m, d, node, tau);
    return;
  }
  int ci = 0;
  for (int i = 0; i < hP; ++i)
    if (i != j) d.b(node, ci++).noalias() = d.b(P, i) - d.Phi(P, hP, i, j) * beta;
  for (int l = 0; l < hQ; ++l)
    if (l != k) d.b(node, ci++).noalias() = d.b(Q, l) + d.Phi(Q, hQ, l, k) * beta;
}

// The pass's bias terms and node vectors against the correction's (O(1) swaps of buffers).
void swap_bias_terms(Data& d) {
  std::swap(d.p_bias, d.refine_p);
  std::swap(d.c, d.refine_c);
  std::swap(d.b_buf, d.refine_b_buf);
  std::swap(d.f_buf, d.refine_f_buf);
  std::swap(d.beta, d.refine_beta);
  std::swap(d.taut, d.refine_taut);
  std::swap(d.cp, d.refine_cp);
  std::swap(d.cpA, d.refine_cpA);
  std::swap(d.cqa, d.refine_cqa);
  std::swap(d.ca, d.refine_ca);
  std::swap(d.cb, d.refine_cb);
}

}  // namespace

namespace detail {

// One step of iterative refinement (Data::refine): q̈ += H⁻¹ r, H⁻¹ applied by the bias half of
// the assembly (no p_bias, no c, τ = r) and a top-down over the factors the pass left.
void refine_step(const Model& m, Data& d, const State& st) {
  d.refine_qdd = d.qdd;
  // kExtended: every operation in long double from q, kinematics included (x87's 64-bit
  // significand). A residual built on the pass's double poses cannot see their rounding; this one
  // can, so q̈ converges to the solution for the inputs as given (mixed-precision refinement).
  if (d.refine == Refinement::kExtended && d.refine_x.sized(m.nbodies))
    inverse_dynamics_residual_in(m, st, d.refine_qdd, d.refine_x, d.refine_r);
  else
    inverse_dynamics_residual(m, d, st.tau, d.refine_qdd);
  swap_bias_terms(d);
  const auto& t = m.tree;
  for (int node = t.nnodes() - 1; node >= 0; --node) bias_assemble_node(m, d, node, d.refine_r);
  const Diagnostics keep = d.diag;
  dca_top_down(m, d);
  d.diag.nodes_bottom_up = keep.nodes_bottom_up;
  d.diag.nodes_top_down = keep.nodes_top_down;
  d.diag.nonfinite = keep.nonfinite;   // δ's are judged below
  swap_bias_terms(d);
  // A correction larger than q̈ itself (or not finite) means the pass had no digits to recover:
  // one step cannot be trusted there (its solve is as wrong as the pass), so q̈ stays the pass's.
  const double dq = d.qdd.lpNorm<Eigen::Infinity>(), q0 = d.refine_qdd.lpNorm<Eigen::Infinity>();
  if (std::isfinite(dq) && dq <= q0) {
    d.qdd += d.refine_qdd;
  } else {
    d.qdd = d.refine_qdd;
    ++d.diag.refine_rejected;
  }
}

}  // namespace detail

void set_refinement(const Model& m, Data& d, Refinement r) {
  d.refine = r;
  if (r != Refinement::kOff && !refinement_sized(m, d)) size_refinement(m, d);
  if (r == Refinement::kExtended) d.refine_x.resize(m.nbodies);
}

}  // namespace haptree
