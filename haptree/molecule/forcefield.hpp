// "Model B" force field (shared/data/README.md): proper torsions + Coulomb with distance-dependent
// dielectric ε(r) = 4r (r in Å) + Lennard-Jones (Lorentz–Berthelot), both multiplied by
// S(x) = 1 − 10x³ + 15x⁴ − 6x⁵, x = (r − r_on)/(r_off − r_on), zero beyond r_off; 1-2/1-3 pairs
// excluded; 1-4 pairs unswitched and scaled (Coulomb 1/1.2, LJ ε 0.5).
// Units: nm, kJ/mol, e; forces kJ/mol/nm (docs/molecules.md).
#pragma once

#include <vector>

#include "haptree/data.hpp"
#include "haptree/molecule/topology.hpp"

namespace haptree::ff {

constexpr double kCoulomb = 138.935456;   // kJ mol⁻¹ nm e⁻² (OpenMM's)

struct NonbondedOptions {
  double r_on = 0.8, r_off = 1.0;   // nm, switch
  double skin = 0.1;                // nm, Verlet skin; the list is rebuilt when an atom moved > skin/2
  bool distance_dielectric = true;  // ε(r) = 4r (Å); false: ε = 1
};

struct EnergyTerms {
  double coulomb = 0, coulomb14 = 0, lj = 0, lj14 = 0, torsion = 0;
  double rigid_constant = 0;   // scene path only: terms inside rigid bodies (constant, set up once)
  double total() const { return coulomb + coulomb14 + lj + lj14 + torsion + rigid_constant; }
};

// Reference evaluation over all atom pairs (O(N²), no list, nothing skipped). F is resized to N and
// overwritten with the total force per atom. For validation and for structures without a tree.
double evaluate_all_pairs(const mol::Topology& t, const NonbondedOptions& o,
                          const std::vector<Vec3>& x, std::vector<Vec3>* F, EnergyTerms* terms);

// Scene evaluator: skips every term inside one rigid body (their constant energy is computed once at
// setup and added), uses a cell list + skin Verlet list, gathers atom forces into one spatial force
// per body. Sized at construction; compute() does not allocate unless the pair list outgrows twice
// its size at setup.
class Evaluator {
 public:
  // atom_body: per atom the Model body id it belongs to (all distinct = no rigid groups).
  // atom_local: per atom its position in its body frame (for compute(Model, Data, ...)).
  Evaluator(const mol::Topology& t, std::vector<int> atom_body, std::vector<Vec3> atom_local,
            const std::vector<Vec3>& x0, const NonbondedOptions& o = {});

  // Energy and per-atom forces of the moving part of the scene at positions x (plus the constant).
  // Non-finite positions (a blown-up state) give an empty pair list and a non-finite energy.
  double compute_atoms(const std::vector<Vec3>& x, std::vector<Vec3>& F, EnergyTerms* terms = nullptr);
  // Atom positions from data.R / data.r (after forward_kinematics), energy, and f_ext[k] = the
  // total force on body k as [moment about r_k; force], world axes. f_ext is overwritten (size
  // model.nbodies; bodies without atoms get zero). Returns the potential energy (kJ/mol).
  double compute(const Model& model, const Data& data, std::vector<Vec6>& f_ext);

  // Adaptive dynamics: bodies with the same region id (>= 0) move as one rigid body (e.g.
  // AdaptiveData::frontier_of_body after a selection). Until the next call, terms inside one region
  // are skipped; their energy (at the positions of the last compute) is added as a constant. Body
  // wrenches then lack the region-internal forces, whose sum over the region is zero (they cancel
  // in the composite rigid body). O(pairs); does not allocate. Empty vector = no regions.
  void set_rigid_regions(const std::vector<int>& body_region);
  void clear_rigid_regions();

  const std::vector<Vec3>& positions() const { return x_; }
  const std::vector<Vec3>& atom_forces() const { return F_; }
  const EnergyTerms& last_terms() const { return terms_; }
  int neighbour_rebuilds() const { return rebuilds_; }
  size_t neighbour_pairs() const { return npairs_; }
  size_t active_torsions() const { return tors_act_.size(); }
  size_t active_pairs14() const { return p14_act_.size(); }
  double rigid_constant() const { return e_const_; }

 private:
  void build_list(const std::vector<Vec3>& x);
  bool list_covers(const std::vector<Vec3>& x) const;
  template <bool DDD>
  void nonbonded_rows(const std::vector<Vec3>& x, std::vector<Vec3>& F, double& ec, double& el) const;
  bool regions_active_ = false;
  NonbondedOptions o_;
  int n_;
  std::vector<int> body_;
  std::vector<Vec3> local_;
  std::vector<double> q_, sig_, sqeps_;
  std::vector<double> hsig_, e2_;   // 0.5σ and 2√ε per atom (pair kernel: σ_ij = sum, 4ε_ij = product)
  std::vector<int> ex_adr_, ex_list_;   // CSR of excluded partners (1-2, 1-3, 1-4), sorted
  std::vector<mol::Pair14> p14_;
  std::vector<mol::Torsion> tors_;
  double e_const_ = 0, e_region_ = 0;
  std::vector<int> key_, new_key_;   // per atom: pairs with equal keys are skipped (body or region)
  std::vector<mol::Pair14> p14_act_;
  std::vector<mol::Torsion> tors_act_;
  // neighbour list
  std::vector<int> row_, pj_;   // CSR: partners of atom i are pj_[row_[i] .. row_[i+1])
  size_t npairs_ = 0;
  std::vector<Vec3> x_ref_;
  std::vector<int> cell_head_, cell_next_;
  bool list_valid_ = false;
  int rebuilds_ = 0;
  // workspace
  std::vector<Vec3> x_, F_;
  EnergyTerms terms_;
};

}  // namespace haptree::ff
