#include "tests/support/quad_reference.hpp"

#include <quadmath.h>

#include <Eigen/Cholesky>

#include "haptree/inverse_dynamics.hpp"

namespace Eigen {
// What Eigen's fixed-size products and reductions need of a scalar type (no norms, no solvers).
template <>
struct NumTraits<__float128> : GenericNumTraits<__float128> {
  using Real = __float128;
  using NonInteger = __float128;
  using Literal = __float128;
  enum { IsComplex = 0, IsInteger = 0, IsSigned = 1, RequireInitialization = 0, ReadCost = 1,
         AddCost = 4, MulCost = 4 };
  static inline Real epsilon() { return FLT128_EPSILON; }
  static inline Real dummy_precision() { return 1e-30Q; }
  static inline Real highest() { return FLT128_MAX; }
  static inline Real lowest() { return -FLT128_MAX; }
  static inline int digits10() { return FLT128_DIG; }
};
}  // namespace Eigen

namespace haptree {
template <>
struct ScalarFunctions<__float128> {
  static __float128 sin(__float128 x) { return sinq(x); }
  static __float128 cos(__float128 x) { return cosq(x); }
  static __float128 sqrt(__float128 x) { return sqrtq(x); }
};
}  // namespace haptree

namespace haptree::testing {

VecXL quad_residual(const Model& m, const State& st, const VecXL& x) {
  InverseDynamicsScratch<__float128> w;
  w.resize(m.nbodies);
  VecXL r = VecXL::Zero(m.nv);
  inverse_dynamics_residual_in(m, st, x, w, r);
  return r;
}

QuadReference quad_reference(const Model& m, const State& st, const OracleResult& orc, int steps) {
  const Eigen::LLT<MatXL> llt(orc.H);
  VecXL x = orc.qdd.cast<LD>();
  InverseDynamicsScratch<__float128> w;
  w.resize(m.nbodies);
  VecXL r = VecXL::Zero(m.nv);
  QuadReference out;
  for (int s = 0; s < steps; ++s) {
    inverse_dynamics_residual_in(m, st, x, w, r);
    const VecXL dx = llt.solve(r);
    x += dx;
    out.last_rel_step = static_cast<double>(dx.norm() / std::max<LD>(x.norm(), 1e-300L));
  }
  out.qdd = x.cast<double>();
  out.oracle_rel_change = rel_err(orc.qdd, out.qdd);
  return out;
}

}  // namespace haptree::testing
