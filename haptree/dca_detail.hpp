// What the dca_*.cpp files share; internal to the core library (not installed, not in the API).
// The small helpers are inline with internal linkage (an anonymous namespace): no file exports
// them, and a translation unit that includes every dca_*.cpp compiles them once. The functions one
// file defines for another are declared in haptree::detail.
#pragma once

#include <cmath>

#include "haptree/dca.hpp"
#include "haptree/isa.hpp"

// Run-time choice of the instruction set. The dca_*.cpp files are compiled twice: for the library's
// baseline (x86-64-v2), and together, as the one file dca_avx2.cpp, for x86-64-v3 (AVX2 + FMA:
// 4-lane products of the 6×6 blocks), whose copy of every function is renamed at build time
// (cmake/LocalizeObject.cmake) so that nothing of it, Eigen's and the standard library's inline code
// included, can stand in for the baseline's. The public entry points open with HAPTREE_DCA_DISPATCH:
// in the baseline copy it hands the call to the x86-64-v3 copy when the kernels run at avx2 or
// above (isa::active()); in that copy it is empty, so everything called from there (the passes,
// every node) stays at its level. The AVX-512 level uses the x86-64-v3 code: a 6-vector fills 4-lane
// registers, not 8-lane ones.
namespace haptree::detail {
// The entry points of one compiled copy of the DCA.
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
// The x86-64-v3 copy when the kernels run at avx2 or above and the build has it; null: this copy.
const DcaKernels* dca_kernels() noexcept;
}  // namespace haptree::detail

extern "C" const haptree::detail::DcaKernels* haptree_dca_kernels_avx2() noexcept;

#if defined(HAPTREE_ISA_COPY) || !HAPTREE_DCA_AVX2
#define HAPTREE_DCA_DISPATCH(fn, ...) ((void)0)
#else
#define HAPTREE_DCA_DISPATCH(fn, ...) \
  if (const ::haptree::detail::DcaKernels* k_ = ::haptree::detail::dca_kernels()) return k_->fn(__VA_ARGS__)
#endif

namespace haptree {

namespace {

using JointVec = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, 6, 1>;
using JointSq = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, 6, 6>;

// Two unit vectors orthogonal to u.
inline void orthonormal_pair(const Vec3& u, Vec3& e1, Vec3& e2) {
  const Vec3 a = std::abs(u.x()) < 0.9 ? Vec3::UnitX() : Vec3::UnitY();
  e1 = u.cross(a).normalized();
  e2 = u.cross(e1);
}

// Joint motion (world axes) for joint k given S and q̇: S q̇.
inline Vec6 joint_velocity(const Model& m, const Data& d, int k, const Eigen::VectorXd& qd) {
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

namespace detail {

// dca_assembly.cpp: W, τ̃ and β of an ordinary node (the joint part of §5.2), not its Φ and b; the
// coupling and the metric read them at an inertia-form node too.
void assemble_joint_terms(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) noexcept;

// dca_light_leaf.cpp: which child of `node` is a light leaf (0: none, 1: P, 2: Q), the node's
// assembly and back-substitution in the light-leaf form, and its bias half for the refinement.
int leaf_form_side(const Model& m, const Data& d, int node);
void leaf_form_assemble(const Model& m, Data& d, int node, int side, const Eigen::VectorXd& tau);
void leaf_form_top_down(const Model& m, Data& d, int node, int side);
void leaf_form_bias(const Model& m, Data& d, int node, const Eigen::VectorXd& tau);

// dca_inertia_form.cpp: a welded cluster's node, assembled and back-substituted in inertia form.
void assemble_inertia_form(const Model& m, Data& d, int node, const Eigen::VectorXd& tau);
void top_down_inertia_form(const Model& m, Data& d, int node);

// dca_refine.cpp: one step of iterative refinement after the passes (Data::refine).
void refine_step(const Model& m, Data& d, const State& st);

}  // namespace detail

}  // namespace haptree
