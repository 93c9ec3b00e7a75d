// "Model B" force field (docs/molecules.md): proper torsions + Coulomb with distance-dependent
// dielectric ε(r) = 4r (r in Å) + Lennard-Jones (Lorentz–Berthelot), both multiplied by
// S(x) = 1 − 10x³ + 15x⁴ − 6x⁵, x = (r − r_on)/(r_off − r_on), zero beyond r_off; 1-2/1-3 pairs
// excluded; 1-4 pairs unswitched and scaled (Coulomb 1/1.2, LJ ε 0.5).
// Units: nm, kJ/mol, e; forces kJ/mol/nm (docs/molecules.md).
#pragma once

#include <cstddef>
#include <cstdint>
#include <new>
#include <vector>

#include <Eigen/Core>

#include "haptree/data.hpp"
#include "haptree/molecule/topology.hpp"

namespace haptree::ff {

constexpr double kCoulomb = 138.935456;   // kJ mol⁻¹ nm e⁻² (OpenMM's)

struct NonbondedOptions {
  double r_on = 0.8, r_off = 1.0;   // nm, switch
  double skin = 0.1;                // nm, Verlet skin; the list is rebuilt when an atom moved > skin/2
  bool distance_dielectric = true;  // ε(r) = 4r (Å); false: ε = 1
  // compute(Model, Data, ...): evaluate only pairs between bodies that moved relative to each other
  // (rigid groups found from the body poses, docs/molecules.md "Work follows motion"). false:
  // every pair between different bodies, every step.
  bool follow_motion = true;
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

  // Work follows motion (compute(Model, Data, ...) with follow_motion): every step the relative
  // pose of each body to its parent is compared with the last step's; bodies joined by joints that
  // did not move form rigid groups (with adaptive dynamics: the frontier regions, and clusters that
  // moved together). Pairs, 1-4 pairs and torsions inside one group are evaluated once, when the
  // groups are formed, and kept as a constant energy plus per-atom forces in the group's root-body
  // frame (rotated on use), so energy, atom forces and f_ext stay complete (= all pairs) while only
  // pairs between groups are evaluated. A group whose inside moves by more than kRigidTol (a
  // rotation entry or nm) since it was formed is re-formed at once; joints still for two steps
  // are merged. compute_atoms() evaluates every inter-body pair (no poses, no groups).
  static constexpr double kStillTol = 1e-13;   // per step: "did not move" (round-off is ~5e-15)
  static constexpr double kRigidTol = 1e-12;   // since the group was formed
  // Kept for callers of the earlier interface: the groups are found from the poses, so both are
  // no-ops (forces are always complete; no clearing is needed before a selection's full pass).
  void set_rigid_regions(const std::vector<int>&) {}
  void clear_rigid_regions() {}

  const std::vector<Vec3>& positions() const { return x_; }
  const std::vector<Vec3>& atom_forces() const { return F_; }
  const EnergyTerms& last_terms() const { return terms_; }
  int neighbour_rebuilds() const { return rebuilds_; }
  // Pairs in the list evaluated each step: between groups when grouped, else every listed pair.
  size_t neighbour_pairs() const { return grouped_ ? napairs_ : npairs_; }
  size_t listed_pairs() const { return npairs_; }            // all inter-body pairs in the list
  // Listed pairs through the kernel in the last compute (incl. the group set-up) and in all.
  size_t pairs_evaluated() const { return last_evaluated_; }
  std::int64_t pairs_evaluated_total() const { return total_evaluated_; }
  // Kernel lanes (atom × 4-atom cluster entries × 4) in the last compute: the arithmetic actually
  // done (pairs_evaluated() / kernel_lanes(): listed pairs per lane).
  size_t kernel_lanes() const { return last_lanes_; }
  // Exact pruning of the evaluated entries: a listed pair between groups at ≥ r_off + kPrune when
  // the entries were last split is still at ≥ r_off (switch exactly 0) until an atom has moved
  // kPrune/2, so its lane is dropped until then (re-split; counted by prunes()). It still counts in
  // pairs_evaluated(): its (zero) term is accounted for, only without arithmetic.
  static constexpr double kPrune = 0.02;   // nm
  int prunes() const { return prunes_; }
  int regroups() const { return regroups_; }
  int rigid_groups() const { return ngroups_; }               // groups of >= 2 bodies
  size_t cached_pairs() const { return nipairs_; }            // listed pairs inside groups
  size_t active_torsions() const { return tors_act_.size(); }
  size_t active_pairs14() const { return p14_act_.size(); }
  double rigid_constant() const { return e_const_; }

 private:
  void build_list(const std::vector<Vec3>& x);
  // list -> pairs between groups (ca*, pruned at x) and inside groups (ci*), by gkey_
  void split_list(const std::vector<Vec3>& x);
  bool list_covers(const std::vector<Vec3>& x) const;
  bool track_motion(const Model& model, const Data& data);
  void regroup(const Model& model, const Data& data);
  void ungroup();
  double evaluate(const std::vector<Vec3>& x, std::vector<Vec3>& F, EnergyTerms* terms, const Data* data);
  void build_clusters();   // atom list (row_, pj_) -> atom × cluster entries (crow_, cent_)
  bool prune_covers(const std::vector<Vec3>& x) const;
  // Switched pairs of the entries crow/cent at positions x; F overwritten with their forces.
  void nonbonded(const int* crow, const int* cent, const std::vector<Vec3>& x, std::vector<Vec3>& F,
                 double& ec, double& el);
  NonbondedOptions o_;
  int n_;
  std::vector<int> body_;
  std::vector<Vec3> local_;
  std::vector<double> q_, sig_, sqeps_;
  std::vector<double> hsig_, e2_;   // 0.5σ and 2√ε per atom (pair kernel: σ_ij = sum, 4ε_ij = product)
  std::vector<int> ex_adr_, ex_list_;   // CSR of excluded partners (1-2, 1-3, 1-4), sorted
  std::vector<mol::Pair14> p14_;
  std::vector<mol::Torsion> tors_;
  double e_const_ = 0, e_group_ = 0;
  std::vector<mol::Pair14> p14_act_;
  std::vector<mol::Torsion> tors_act_;
  // neighbour list: every pair of atoms on different bodies within r_off + skin
  std::vector<int> row_, pj_;   // CSR: partners of atom i are pj_[row_[i] .. row_[i+1])
  size_t npairs_ = 0;
  std::vector<Vec3> x_ref_;
  std::vector<int> cell_head_, cell_next_;
  bool list_valid_ = false;
  int rebuilds_ = 0;
  // rigid groups (follow_motion)
  bool grouped_ = false, tracked_ = false;
  std::vector<int> group_;            // per body: root body of its group (parent[k] < k: smallest id)
  std::vector<int> gkey_;             // per atom: group_[body]
  std::vector<Mat3> rel_R_, ref_R_;   // per body: pose relative to the parent, last step / at grouping
  std::vector<Vec3> rel_t_, ref_t_;
  std::vector<int> still_;            // per body: steps its joint has not moved
  std::vector<char> gmark_;           // scratch (per body)
  // 1×4 cluster kernel: slot s = 4c + l (cluster c, lane l) holds atom slot_atom_[s] (−1: padding);
  // per slot, positions / parameters / forces as structure of arrays. The list as entries
  // (c << 4 | lane mask) per i slot (CSR): atom i against the mask's atoms of cluster c.
  // 64-byte aligned whatever Eigen's alignment at the library's -march (the kernels load whole
  // 4-slot clusters with aligned 256-bit loads).
  template <class T>
  struct Aligned64 {
    using value_type = T;
    Aligned64() = default;
    template <class U>
    Aligned64(const Aligned64<U>&) {}
    T* allocate(size_t n) { return static_cast<T*>(::operator new(n * sizeof(T), std::align_val_t(64))); }
    void deallocate(T* p, size_t) { ::operator delete(p, std::align_val_t(64)); }
    bool operator==(const Aligned64&) const { return true; }
    bool operator!=(const Aligned64&) const { return false; }
  };
  using DVec = std::vector<double, Aligned64<double>>;
  int nslots_ = 0;
  std::vector<int> slot_atom_, atom_slot_, slot_gkey_;
  DVec cx_, cy_, cz_, cq_, cs_, ce_, cfx_, cfy_, cfz_;
  std::vector<int> crow_, cent_;                 // all listed pairs
  std::vector<int> carow_, caent_, cirow_, cient_;   // split: between groups / inside groups
  std::vector<int> cstamp_, cpos_;               // scratch per cluster (build_clusters)
  size_t nents_ = 0, naents_ = 0, nients_ = 0, last_lanes_ = 0;
  std::vector<Vec3> x_prune_;         // positions at the last split
  bool prune_valid_ = false;
  int prunes_ = 0;
  size_t napairs_ = 0, nipairs_ = 0;
  std::vector<Vec3> F_loc_;           // per atom: group-internal force in the group root's frame
  std::vector<int> cached_atoms_;     // atoms with a group-internal force
  int regroups_ = 0, ngroups_ = 0;
  size_t last_evaluated_ = 0;
  std::int64_t total_evaluated_ = 0;
  // workspace
  std::vector<Vec3> x_, F_;
  EnergyTerms terms_;
};

}  // namespace haptree::ff
