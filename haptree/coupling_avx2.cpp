// coupling_forces compiled for x86-64-v3 (AVX2 + FMA), built by haptree_isa_copy
// (haptree/CMakeLists.txt: -march=x86-64-v3, the baseline's Eigen alignment, every global symbol of
// the object but haptree_coupling_forces_avx2 renamed); the baseline's coupling_forces hands its
// calls to it when isa::active() is avx2 or above.
#if !defined(__AVX2__) || !defined(__FMA__) || EIGEN_MAX_ALIGN_BYTES != 16 || EIGEN_MAX_STATIC_ALIGN_BYTES != 16
#error "coupling_avx2.cpp: built by haptree_isa_copy (-march=x86-64-v3, Eigen alignment 16)"
#endif

#include "haptree/coupling.cpp"

extern "C" haptree::CouplingStatus haptree_coupling_forces_avx2(const haptree::CouplingSnapshot& s,
                                                                 const haptree::Vec6* f_u,
                                                                 haptree::CouplingWorkspace& ws,
                                                                 haptree::Vec6* f_feed) noexcept {
  return haptree::coupling_forces(s, f_u, ws, f_feed);
}
