// The cluster kernel for x86-64-v4: AVX-512 F/VL/DQ/BW/CD, the 8-lane kernel and rsqrt14 (compiled with its own -march: haptree/molecule/CMakeLists.txt).
#define HAPTREE_CLUSTER_ENTRY cluster_rows_avx512
#include "haptree/molecule/cluster_simd.inc"
