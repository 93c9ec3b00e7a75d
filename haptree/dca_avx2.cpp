// The DCA compiled for x86-64-v3 (AVX2 + FMA; haptree/CMakeLists.txt gives it -march=x86-64-v3 and
// renames every global symbol of its object but the entry point haptree_dca_kernels_avx2). Whatever
// is shared with the rest of the library keeps the baseline's layout and allocator: Eigen's
// alignment is the x86-64-v2 one (16 bytes), not the 32 that AVX would otherwise give fixed-size
// matrices and heap blocks, so a matrix made here may be freed there and every member of Data sits
// where the baseline's code expects it.
#define EIGEN_MAX_STATIC_ALIGN_BYTES 16
#define EIGEN_MAX_ALIGN_BYTES 16
#define HAPTREE_DCA_LEVEL 1

#if !defined(__AVX2__) || !defined(__FMA__)
#error "dca_avx2.cpp: compile with -march=x86-64-v3"
#endif

#include "haptree/dca.cpp"
