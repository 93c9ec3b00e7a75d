// The cluster kernel without SIMD intrinsics: the lanes of an entry one after another, with sqrt
// and a division (cluster_kernel.hpp). Runs on any CPU; the compiler's own vectorisation at the
// library's baseline -march is all it gets.
#include <cmath>

#include "haptree/molecule/cluster_kernel.hpp"

namespace haptree::ff::kernel {

namespace {
template <bool DDD>
void rows(const ClusterRows& a, double& ec_out, double& el_out) {
  const double r_on = a.r_on;
  const double kq = a.kq;
  const int nslots = a.nslots;
  const int *crow = a.crow, *cent = a.cent;
  const double *X = a.x, *Y = a.y, *Z = a.z;
  const double *Q = a.q, *SG = a.sigma, *E2 = a.e2;
  double *FX = a.fx, *FY = a.fy, *FZ = a.fz;

  const double inv_w = 1.0 / (a.r_off - a.r_on);
  const double far = (a.r_off + 1.0) * (a.r_off + 1.0);
  double ec = 0, el = 0;
  for (int s = 0; s < nslots; ++s) {
    const int b = crow[s], e = crow[s + 1];
    if (b == e) continue;
    const double qi = kq * Q[s];
    double fix = 0, fiy = 0, fiz = 0;
    for (int k = b; k < e; ++k) {
      const int w = cent[k];
      const int j0 = (w >> 4) << 2;
      for (int l = 0; l < 4; ++l) {
        const int j = j0 + l;
        const double dx = X[s] - X[j], dy = Y[s] - Y[j], dz = Z[s] - Z[j];
        const double r2 = (w >> l & 1) ? dx * dx + dy * dy + dz * dz : far;
        const double inv_r2 = 1.0 / r2;
        const double r = std::sqrt(r2);
        const double inv_r = r * inv_r2;
        double Ec, dEc_r;
        if (DDD) {
          Ec = qi * Q[j] * inv_r2;
          dEc_r = -2.0 * Ec * inv_r2;
        } else {
          Ec = qi * Q[j] * inv_r;
          dEc_r = -Ec * inv_r2;
        }
        const double sg = SG[s] + SG[j], e4 = E2[s] * E2[j];
        const double sr2 = sg * sg * inv_r2;
        const double s6 = sr2 * sr2 * sr2, s12 = s6 * s6;
        const double El = e4 * (s12 - s6);
        const double dE_r = dEc_r + e4 * (-12.0 * s12 + 6.0 * s6) * inv_r2;
        double xs = (r - r_on) * inv_w;
        xs = xs < 0.0 ? 0.0 : xs;
        xs = xs > 1.0 ? 1.0 : xs;
        const double x2 = xs * xs, x3 = x2 * xs;
        const double S = 1 - 10 * x3 + 15 * x3 * xs - 6 * x3 * x2;
        const double dS = (-30 * x2 + 60 * x3 - 30 * x3 * xs) * inv_w;
        const double dE = S * dE_r + dS * (Ec + El) * inv_r;
        fix -= dE * dx;
        fiy -= dE * dy;
        fiz -= dE * dz;
        FX[j] += dE * dx;
        FY[j] += dE * dy;
        FZ[j] += dE * dz;
        ec += S * Ec;
        el += S * El;
      }
    }
    FX[s] += fix;
    FY[s] += fiy;
    FZ[s] += fiz;
  }
  ec_out += ec;
  el_out += el;
}
}  // namespace

void cluster_rows_generic(const ClusterRows& a, double& ec, double& el) {
  if (a.ddd) rows<true>(a, ec, el);
  else rows<false>(a, ec, el);
}

}  // namespace haptree::ff::kernel
