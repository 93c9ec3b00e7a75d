// The DCA compiled for x86-64-v3 (AVX2 + FMA): every dca_*.cpp file in one translation unit, built
// by haptree_isa_copy (haptree/CMakeLists.txt: -march=x86-64-v3, the baseline's Eigen alignment,
// every global symbol of the object but haptree_dca_kernels_avx2 renamed). dca_detail.hpp: how the
// baseline copy hands its calls over.
#if !defined(__AVX2__) || !defined(__FMA__) || EIGEN_MAX_ALIGN_BYTES != 16 || EIGEN_MAX_STATIC_ALIGN_BYTES != 16
#error "dca_avx2.cpp: built by haptree_isa_copy (-march=x86-64-v3, Eigen alignment 16)"
#endif

#include "haptree/dca_kinematics.cpp"
#include "haptree/dca_assembly.cpp"
#include "haptree/dca_light_leaf.cpp"
#include "haptree/dca_inertia_form.cpp"
#include "haptree/dca_passes.cpp"
#include "haptree/dca_refine.cpp"

extern "C" const haptree::detail::DcaKernels* haptree_dca_kernels_avx2() noexcept {
  using namespace haptree;
  static constexpr detail::DcaKernels k{&forward_kinematics, &body_dynamics_terms, &dca_leaf,
                                        &dca_assemble,       &dca_top_down_node,   &dca_bottom_up,
                                        &dca_bottom_up_node, &dca_top_down,        &forward_dynamics};
  return &k;
}
