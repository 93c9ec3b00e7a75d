// The force field's 1×4 cluster kernel (switched non-bonded pairs, atom × 4-atom cluster), one
// implementation per x86-64 ISA level, chosen at run time (haptree/isa.hpp). The boundary between
// the evaluator and the kernels carries plain pointers and scalars only: each ISA-specific kernel is
// its own translation unit compiled with its own -march, includes no Eigen and no other inline
// library code, and keeps everything but its entry point in an anonymous namespace, so no inline
// function compiled for a wider ISA can be merged by the linker into code that runs on any CPU.
#pragma once

namespace haptree::ff::kernel {

// Slot arrays (structure of arrays, slot s = 4c + l: cluster c, lane l), 32-byte aligned, length
// nslots rounded up to a whole cluster. Entries (c << 4 | lane mask) per i slot in CSR form.
struct ClusterRows {
  const double *x, *y, *z;       // positions (nm)
  const double *q, *sigma, *e2;  // charge (e), σ/2 (nm), 2√ε (pair: σ_ij = sum, 4ε_ij = product)
  double *fx, *fy, *fz;          // forces (kJ/mol/nm), accumulated into
  const int *crow, *cent;
  int nslots;
  double r_on, r_off;            // switch (nm)
  double kq;                     // Coulomb constant for the pair (with the distance dielectric: /40)
  bool ddd;                      // distance-dependent dielectric ε(r) = 4r (Å): E_c ∝ 1/r²
};

// Each adds the pairs' forces to fx/fy/fz and the switched Coulomb / LJ energies to ec / el.
void cluster_rows_generic(const ClusterRows& a, double& ec, double& el);   // scalar, any CPU
void cluster_rows_avx2(const ClusterRows& a, double& ec, double& el);      // x86-64-v3: 4 lanes, FMA
void cluster_rows_avx512(const ClusterRows& a, double& ec, double& el);    // x86-64-v4: 8 + 4 lanes

}  // namespace haptree::ff::kernel
