// The cluster kernel for x86-64-v3: AVX2 + FMA, the 4-lane kernel (compiled with its own -march: haptree/molecule/CMakeLists.txt).
#define HAPTREE_CLUSTER_ENTRY cluster_rows_avx2
#include "haptree/molecule/cluster_simd.inc"
