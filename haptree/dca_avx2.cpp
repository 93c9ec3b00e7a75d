// The DCA compiled for x86-64-v3 (AVX2 + FMA): every dca_*.cpp file in one translation unit, given
// -march=x86-64-v3 by haptree/CMakeLists.txt, which renames every global symbol of its object but
// the entry point haptree_dca_kernels_avx2 (dca_detail.hpp: how the baseline copy calls it).
// Whatever is shared with the rest of the library keeps the baseline's layout and allocator:
// Eigen's alignment is the x86-64-v2 one (16 bytes), not the 32 that AVX would otherwise give
// fixed-size matrices and heap blocks, so a matrix allocated here may be freed there and every
// member of Data sits where the baseline's code expects it.
#define EIGEN_MAX_STATIC_ALIGN_BYTES 16
#define EIGEN_MAX_ALIGN_BYTES 16
#define HAPTREE_DCA_LEVEL 1

#if !defined(__AVX2__) || !defined(__FMA__)
#error "dca_avx2.cpp: compile with -march=x86-64-v3"
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
