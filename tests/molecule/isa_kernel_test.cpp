// The force field's cluster kernel at every x86-64 level this CPU runs (haptree/isa.hpp): each
// level against the all-pairs reference and against the generic kernel, per atom.
//
// Tolerance (relative, derived as in forcefield_motion_test's ClusterKernelMatchesAllPairsPerAtom):
// a kernel differs from the reference only by summation order (≈ 1e-13 of the force / energy
// scale) and by its 1/r (within a few ulp: rsqrt + Newton or rsqrt14 + an order-4 step, or sqrt and
// a division), so 1e-9 of the scale holds for every level, and two levels are within 2e-9 of each
// other; one lost, doubled or mis-masked pair costs ≥ 1e-5 of it.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>

#include "haptree/dca.hpp"
#include "haptree/isa.hpp"
#include "haptree/molecule/scene.hpp"

using namespace haptree;
using namespace haptree::mol;

namespace {

constexpr double kRel = 1e-9;   // derived above

double energy_scale(const ff::EnergyTerms& t) {
  return std::abs(t.coulomb) + std::abs(t.coulomb14) + std::abs(t.lj) + std::abs(t.lj14) + std::abs(t.torsion);
}

// Restores the level the process started with (other tests in this binary see the default).
struct LevelGuard {
  isa::Level saved = isa::active();
  ~LevelGuard() { isa::set_active(saved); }
};

}  // namespace

TEST(Isa, NamesParseAndTheBestLevelIsSupported) {
  for (isa::Level l : {isa::Level::generic, isa::Level::avx2, isa::Level::avx512}) {
    ASSERT_TRUE(isa::parse(isa::name(l)).has_value());
    EXPECT_EQ(*isa::parse(isa::name(l)), l);
  }
  EXPECT_FALSE(isa::parse("sse9").has_value());
  EXPECT_TRUE(isa::supported(isa::Level::generic));
  EXPECT_TRUE(isa::supported(isa::best()));
  // Levels are nested: a CPU with x86-64-v4 has x86-64-v3.
  if (isa::supported(isa::Level::avx512)) EXPECT_TRUE(isa::supported(isa::Level::avx2));
  EXPECT_LE(static_cast<int>(isa::active()), static_cast<int>(isa::best()));
  LevelGuard g;
  for (isa::Level l : {isa::Level::generic, isa::Level::avx2, isa::Level::avx512}) {
    const isa::Level before = isa::active();
    EXPECT_EQ(isa::set_active(l), isa::supported(l)) << isa::name(l);
    EXPECT_EQ(isa::active(), isa::supported(l) ? l : before) << isa::name(l);   // unsupported: unchanged
  }
  std::printf("[isa] best %s, supported: generic%s%s\n", isa::name(isa::best()),
              isa::supported(isa::Level::avx2) ? " avx2" : "", isa::supported(isa::Level::avx512) ? " avx512" : "");
}

// Every supported level, both dielectrics and two switches, on scenes with a padded last cluster
// (ala20: 203 atoms) and the 3.7k-atom bacteriorhodopsin.
TEST(Isa, EveryLevelMatchesAllPairsAndTheGenericKernel) {
  LevelGuard g;
  int levels = 0;
  for (const char* name : {"ala20", "bacteriorhodopsin"}) {
    MolecularScene sc = load_molecular_scene(name);
    const Model& m = *sc.model;
    Data d(m);
    Eigen::VectorXd q = neutral_configuration(m);
    const double amp = sc.natoms() > 1000 ? 0.002 : 0.05;   // off the input pose, no clashes
    for (int k = 0; k < q.size(); ++k) q(k) += amp * std::sin(3.0 * k);
    forward_kinematics(m, d, q);
    std::vector<Vec3> x;
    sc.atom_positions(d, x);
    std::vector<int> own(sc.natoms());   // every atom its own body: per-atom forces are complete
    for (int a = 0; a < sc.natoms(); ++a) own[a] = a;
    for (const bool ddd : {true, false})
      for (const double r_on : {0.8, 0.6}) {
        ff::NonbondedOptions o;
        o.distance_dielectric = ddd;
        o.r_on = r_on;
        o.r_off = r_on + (r_on == 0.8 ? 0.2 : 0.6);
        std::vector<Vec3> F_ref, F_gen;
        ff::EnergyTerms t_ref, t_gen;
        const double E_ref = ff::evaluate_all_pairs(sc.topology, o, x, &F_ref, &t_ref);
        double f_scale = 0;
        for (const Vec3& f : F_ref) f_scale = std::max(f_scale, f.cwiseAbs().maxCoeff());
        const double e_scale = energy_scale(t_ref);
        double E_gen = 0;
        levels = 0;
        for (isa::Level l : {isa::Level::generic, isa::Level::avx2, isa::Level::avx512}) {
          if (!isa::set_active(l)) continue;
          ++levels;
          ff::Evaluator ev(sc.topology, own, {}, x, o);
          std::vector<Vec3> F;
          ff::EnergyTerms t;
          const double E = ev.compute_atoms(x, F, &t);
          double f_err = 0, f_gen = 0;
          for (int a = 0; a < sc.natoms(); ++a) {
            f_err = std::max(f_err, (F[a] - F_ref[a]).cwiseAbs().maxCoeff());
            if (l != isa::Level::generic) f_gen = std::max(f_gen, (F[a] - F_gen[a]).cwiseAbs().maxCoeff());
          }
          EXPECT_LE(std::abs(E - E_ref), kRel * e_scale) << name << " " << isa::name(l);
          EXPECT_LE(f_err, kRel * f_scale) << name << " " << isa::name(l);
          if (l == isa::Level::generic) {
            E_gen = E;
            F_gen = F;
            t_gen = t;
          } else {
            EXPECT_LE(std::abs(E - E_gen), 2 * kRel * e_scale) << name << " " << isa::name(l);
            EXPECT_LE(std::abs(t.coulomb + t.lj - t_gen.coulomb - t_gen.lj), 2 * kRel * e_scale) << name;
            EXPECT_LE(f_gen, 2 * kRel * f_scale) << name << " " << isa::name(l);
          }
          EXPECT_GT(ev.kernel_lanes(), 0u);
          std::printf("%s ddd %d r_on %.1f %-7s: E %.9f (ref %.9f), max |F - F_ref| %.2e, |F - F_generic| %.2e of %.2e\n",
                      name, ddd, r_on, isa::name(l), E, E_ref, f_err, f_gen, f_scale);
        }
      }
  }
  EXPECT_GE(levels, 1);
  EXPECT_EQ(levels, 1 + isa::supported(isa::Level::avx2) + isa::supported(isa::Level::avx512));
}
