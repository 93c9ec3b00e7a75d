#include "haptree/dca.hpp"

#include <sched.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <type_traits>

#include "haptree/isa.hpp"

// Run-time choice of the instruction set. This file is compiled twice: for the library's baseline
// (x86-64-v2), and, as the unity file dca_avx2.cpp, for x86-64-v3 (AVX2 + FMA: 4-lane products of
// the 6×6 blocks), whose copy of every function is renamed at build time (cmake/LocalizeObject.cmake)
// so that nothing of it, Eigen's and the standard library's inline code included, can stand in for
// the baseline's. The entry points below start with HAPTREE_DCA_DISPATCH: in the baseline copy it
// hands the call to the x86-64-v3 copy when the CPU has it (isa::active() ≥ avx2); in that copy it is
// empty, so everything called from there (the passes, every node) runs at the same level. The
// AVX-512 level uses the x86-64-v3 code: 6-vectors fill 4-lane registers, not 8-lane ones.
namespace haptree::detail {
/// The entry points of one compiled copy of the DCA.
struct DcaKernels {
  void (*forward_kinematics)(const Model&, Data&, const Eigen::VectorXd&) noexcept;
  void (*body_dynamics_terms)(const Model&, Data&, const State&) noexcept;
  void (*dca_leaf)(const Model&, Data&, int) noexcept;
  void (*dca_assemble)(const Model&, Data&, int, const Eigen::VectorXd&) noexcept;
  void (*dca_top_down_node)(const Model&, Data&, int) noexcept;
  void (*dca_bottom_up)(const Model&, Data&, const State&) noexcept;
  void (*dca_bottom_up_node)(const Model&, Data&, int, const Eigen::VectorXd&) noexcept;
  void (*dca_top_down)(const Model&, Data&) noexcept;
  const Eigen::VectorXd& (*forward_dynamics)(const Model&, Data&, const State&) noexcept;
};
}  // namespace haptree::detail

#if HAPTREE_DCA_AVX2
extern "C" const haptree::detail::DcaKernels* haptree_dca_kernels_avx2() noexcept;
#endif
#if defined(HAPTREE_DCA_LEVEL) || !HAPTREE_DCA_AVX2
#define HAPTREE_DCA_DISPATCH(fn, ...) ((void)0)
#else
#define HAPTREE_DCA_DISPATCH(fn, ...) \
  if (const detail::DcaKernels* k_ = detail::dca_kernels()) return k_->fn(__VA_ARGS__)
#endif

namespace haptree {

#if !defined(HAPTREE_DCA_LEVEL)
namespace detail {
/// The x86-64-v3 copy when the kernels run at avx2 or above and the build has it; null: this copy.
const DcaKernels* dca_kernels() noexcept {
#if HAPTREE_DCA_AVX2
  if (isa::active() >= isa::Level::avx2) return haptree_dca_kernels_avx2();
#endif
  return nullptr;
}
}  // namespace detail

isa::Level dca_level() noexcept {
#if HAPTREE_DCA_AVX2
  return detail::dca_kernels() ? isa::Level::avx2 : isa::Level::generic;
#elif defined(__AVX512F__) && defined(__AVX512VL__)
  return isa::Level::avx512;   // the whole library compiled for it (-march)
#elif defined(__AVX2__) && defined(__FMA__)
  return isa::Level::avx2;
#else
  return isa::Level::generic;
#endif
}
#endif

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
  HAPTREE_DCA_DISPATCH(forward_kinematics, m, d, q);
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

namespace {

// The per-body part of body_dynamics_terms (needs R[k] and v[k]); independent across bodies, so
// the parallel driver runs it in the leaf that reads it.
inline void body_inertia_terms(const Model& m, Data& d, const State& st, int k) {
  const Mat3& Rk = d.R[k];
  const Vec3 cw = Rk * m.com[k];
  const Mat3 Ic = Rk * m.inertia[k] * Rk.transpose();
  d.I[k] = spatial_inertia(m.mass[k], cw, Ic);
  d.Iinv[k] = spatial_inertia_inverse(m.mass[k], cw, Ic);
  d.f_total[k] = gravity_force(m.mass[k], cw, m.gravity) + st.f_ext[k];
  d.p_bias[k] = d.f_total[k] - cross_force(d.v[k], d.I[k] * d.v[k]);
}

}  // namespace

void body_dynamics_terms(const Model& m, Data& d, const State& st) noexcept {
  HAPTREE_DCA_DISPATCH(body_dynamics_terms, m, d, st);
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
  HAPTREE_DCA_DISPATCH(dca_leaf, m, d, node);
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

}  // namespace

namespace {

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

void assemble_joint(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) noexcept {
  JointX X;
  assemble_joint(m, d, node, tau, X);
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

namespace {

// ---- Light-leaf form -----------------------------------------------------------
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
using JointVec = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, 6, 1>;
using JointSq = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 6, 6>;
using DynMat = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 6, 6>;
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

}  // namespace

void dca_assemble(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) noexcept {
  HAPTREE_DCA_DISPATCH(dca_assemble, m, d, node, tau);
  const auto& t = m.tree;
  d.cluster_live[node] = 0;
  if (!d.leaf_side.empty()) d.leaf_side[node] = 0;
  if (const int side = leaf_form_side(m, d, node)) {
    leaf_form_assemble(m, d, node, side, tau);
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

namespace {

// ---- Inertia form of cluster nodes (Model::cluster_case) -------------------------------------
// A node whose handles all attach to one rigid cluster is described by its articulated inertia M
// and bias force p at its reference point o = r_{cluster_ref[node]}: a_o = M⁻¹(Σ_x X_xᵀ f_x + p),
// X_x the motion shift from o to handle x. Joining two such nodes across a fixed joint adds M and
// p; joining a one-handle side across a moving joint adds its ABA projection. No difference of
// large mobilities is formed, so light pieces of a split hub do not cancel (docs/algorithms.md §4.4,
// §16.4). o is a body of the node near most of its mass, not the cluster's root: an inertia moved
// across a long weld has a condition number ~ (length/radius of gyration)⁴, and its inverse lost
// 1e-5 of q̈ at 10⁶ m. Mobilities are shifted instead (no cancellation).


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

}  // namespace

void dca_top_down_node(const Model& m, Data& d, int node) noexcept {
  HAPTREE_DCA_DISPATCH(dca_top_down_node, m, d, node);
  const auto& t = m.tree;
  if (d.cluster_live[node]) {
    top_down_inertia_form(m, d, node);
    return;
  }
  if (!d.leaf_side.empty() && d.leaf_side[node]) {
    leaf_form_top_down(m, d, node, d.leaf_side[node]);
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

namespace {

void cluster_offsets(const Model& m, Data& d) {
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

inline void bottom_up_node(const Model& m, Data& d, const State& st, int node) {
  dca_bottom_up_node(m, d, node, st.tau);
}

}  // namespace

void dca_bottom_up(const Model& m, Data& d, const State& st) noexcept {
  HAPTREE_DCA_DISPATCH(dca_bottom_up, m, d, st);
  const auto& t = m.tree;
  cluster_offsets(m, d);
  std::int64_t count = 0;
  for (int node = t.nnodes() - 1; node >= 0; --node) {
    bottom_up_node(m, d, st, node);
    ++count;
  }
  d.diag.nodes_bottom_up = count;
}

void dca_top_down(const Model& m, Data& d) noexcept {
  HAPTREE_DCA_DISPATCH(dca_top_down, m, d);
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

namespace {

// One task of the parallel passes: the subtree [lo, hi), ids descending; each leaf first computes
// its body's inertia terms (one sweep over memory instead of two).
void bottom_up_task(const Model& m, Data& d, const State& st, int lo, int hi) {
  const auto& t = m.tree;
  for (int node = hi - 1; node >= lo; --node) {
    if (t.is_leaf(node) && t.body[node] > 0) body_inertia_terms(m, d, st, t.body[node]);
    bottom_up_node(m, d, st, node);
  }
}
void top_down_task(const Model& m, Data& d, int lo, int hi) {
  const auto& t = m.tree;
  for (int node = lo; node < hi; ++node)
    if (!t.is_leaf(node)) dca_top_down_node(m, d, node);
}

// forward_dynamics on d.dca_threads threads over d.dca_cut (ParallelCut). Every node runs the same
// kernel on the same inputs as in the serial passes, so the result is bit-for-bit the same.
void parallel_passes(const Model& m, Data& d, const State& st) {
  const auto& t = m.tree;
  const ParallelCut& cut = d.dca_cut;
  const int ntask = static_cast<int>(cut.lo.size());
  d.v[0].setZero();
  for (int k = 1; k < m.nbodies; ++k) joint_motion_terms(m, d, k, st.qd, d.v[m.parent[k]]);
  cluster_offsets(m, d);
#pragma omp parallel for schedule(dynamic, 1) num_threads(d.dca_threads)
  for (int i = 0; i < ntask; ++i) bottom_up_task(m, d, st, cut.lo[i], cut.hi[i]);
  for (size_t i = cut.top.size(); i-- > 0;) bottom_up_node(m, d, st, cut.top[i]);
  d.diag.nodes_bottom_up = t.nnodes();

  for (int root : t.roots)
    for (int s = 0; s < t.handle_num[root]; ++s) d.f(root, s).setZero();
  for (int node : cut.top) dca_top_down_node(m, d, node);
#pragma omp parallel for schedule(dynamic, 1) num_threads(d.dca_threads)
  for (int i = 0; i < ntask; ++i) top_down_task(m, d, cut.lo[i], cut.hi[i]);
  std::int64_t internal = 0;
  for (int node = 0; node < t.nnodes(); ++node) internal += t.is_leaf(node) ? 0 : 1;
  d.diag.nodes_top_down = internal;
  for (int i = 0; i < m.nv; ++i)
    if (!std::isfinite(d.qdd(i))) { ++d.diag.nonfinite; break; }
}

int cpus_available() {
  cpu_set_t set;
  if (sched_getaffinity(0, sizeof(set), &set) != 0) return 1;
  return CPU_COUNT(&set);
}

}  // namespace

int set_dca_threads(const Model& m, Data& d, int threads) {
#ifdef _OPENMP
  if (threads == 0) {
    // A free core: the 1-minute load average (this thread included) leaves at least one CPU idle.
    // On a loaded machine the second thread waits for a core at every barrier: 2 threads at load
    // 20 on 2 CPUs took 5x the serial wall time.
    const int cpus = cpus_available();
    double load = 1e9;
    const bool free_core = getloadavg(&load, 1) == 1 && load <= cpus - 1;
    threads = m.tree.nnodes() >= kDcaParallelMinNodes && cpus >= 2 && free_core ? cpus : 1;
  }
#else
  threads = 1;   // built without OpenMP
#endif
  d.dca_threads = std::max(1, threads);
  // 4 tasks per thread so a dynamic schedule evens out unequal subtrees; none below 64 nodes.
  d.dca_cut = parallel_cut(m.tree, d.dca_threads == 1 ? 1 : 4 * d.dca_threads, 64);
  return d.dca_threads;
}

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
// A light-leaf node (p = c' = 0): f_J0 = Y b_O + G τ', O's acceleration a_O = b_O − B̂ f_J0, and L's
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
    leaf_form_bias(m, d, node, tau);
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
    assemble_inertia_form(m, d, node, tau);
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

}  // namespace

const Eigen::VectorXd& forward_dynamics(const Model& m, Data& d, const State& st) noexcept {
  HAPTREE_DCA_DISPATCH(forward_dynamics, m, d, st);
  forward_kinematics(m, d, st.q);
  if (d.dca_threads > 1) {
    parallel_passes(m, d, st);
  } else {
    body_dynamics_terms(m, d, st);
    dca_bottom_up(m, d, st);
    dca_top_down(m, d);
  }
  if (d.refine != Refinement::kOff) {   // serial even after parallel passes
    if (!refinement_sized(m, d)) size_refinement(m, d);   // Data::refine assigned, not set_refinement
    refine_step(m, d, st);
  }
  return d.qdd;
}

void set_refinement(const Model& m, Data& d, Refinement r) {
  d.refine = r;
  if (r != Refinement::kOff && !refinement_sized(m, d)) size_refinement(m, d);
  if (r == Refinement::kExtended) d.refine_x.resize(m.nbodies);
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

// Hooks for adaptive.cpp: the same steps as dca_bottom_up, split (kept apart from it
// so that the pass itself is unchanged).
void dca_cluster_offsets(const Model& m, Data& d) noexcept { cluster_offsets(m, d); }

void dca_bottom_up_node(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) noexcept {
  HAPTREE_DCA_DISPATCH(dca_bottom_up_node, m, d, node, tau);
  if (m.tree.is_leaf(node)) {
    dca_leaf(m, d, node);
  } else if (m.cluster_index[node] >= 0) {
    assemble_joint(m, d, node, tau);   // W, β for coupling and metric readers
    assemble_inertia_form(m, d, node, tau);
  } else {
    dca_assemble(m, d, node, tau);
  }
}

}  // namespace haptree

#if defined(HAPTREE_DCA_LEVEL)
extern "C" const haptree::detail::DcaKernels* haptree_dca_kernels_avx2() noexcept {
  using namespace haptree;
  static constexpr detail::DcaKernels k{&forward_kinematics, &body_dynamics_terms, &dca_leaf,
                                        &dca_assemble,       &dca_top_down_node,   &dca_bottom_up,
                                        &dca_bottom_up_node, &dca_top_down,        &forward_dynamics};
  return &k;
}
#endif
