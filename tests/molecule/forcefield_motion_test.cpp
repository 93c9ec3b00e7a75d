// "Molecules cost what moved": the force field evaluates only pairs between bodies that
// moved relative to each other (ff::NonbondedOptions::follow_motion), and stays equal to the
// all-pairs reference (ff::evaluate_all_pairs) over adaptive runs with reselections.
//
// Tolerance (relative, derived): the incremental evaluation differs from the reference only by
// (a) summation order: each of the ~10⁶ terms is added once in both, so the difference is
//     ≲ √N·ε·Σ|terms| ≈ 10³·1.1e-16·Σ|terms| ≈ 1e-13·Σ|terms|;
// (b) group-internal terms evaluated at the pose of their group's formation: the relative pose of
//     every joint inside a group stays within Evaluator::kRigidTol = 1e-12 (rotation entries, nm)
//     of it, else the group is re-formed. Over a path of ≤ 10² joints and lever arms ≤ 5 nm an atom
//     is then within ≈ 5e-10 nm of the position its cached force belongs to; with |∂F/∂x|/|F| ≲
//     13/r ≈ 50 nm⁻¹ (r ≥ 0.25 nm for non-excluded pairs) that is ≲ 3e-8 per term in the worst case.
//     In these runs inactive joints are exactly still (q unchanged), so their drift is round-off
//     (~5e-15 nm, i.e. ≲ 3e-13 relative).
// 1e-9 relative (to Σ|energy components| for energies, to max |wrench| for body wrenches) is ≥ 10³
// above (a) and the realised (b), and ≥ 10⁴ below what one missing or doubled pair at 0.3–0.8 nm
// costs (≥ 1e-5 relative), so the test still catches a wrong split, a stale cache or a lost term.
#include <gtest/gtest.h>

#include <cmath>

#include "haptree/adaptive.hpp"
#include "haptree/dca.hpp"
#include "haptree/molecule/scene.hpp"

using namespace haptree;
using namespace haptree::mol;

namespace {

constexpr double kRel = 1e-9;   // derived above

double energy_scale(const ff::EnergyTerms& t) {
  return std::abs(t.coulomb) + std::abs(t.coulomb14) + std::abs(t.lj) + std::abs(t.lj14) + std::abs(t.torsion);
}

// Body wrenches [moment about r_k; force] of per-atom forces.
std::vector<Vec6> wrenches(const MolecularScene& sc, const Data& d, const std::vector<Vec3>& x,
                           const std::vector<Vec3>& F) {
  std::vector<Vec6> w(sc.model->nbodies, Vec6::Zero());
  for (int a = 0; a < sc.natoms(); ++a) {
    const int b = sc.torsion.atom_model_body[a];
    w[b].head<3>() += (x[a] - d.r[b]).cross(F[a]);
    w[b].tail<3>() += F[a];
  }
  return w;
}

struct Check {
  double e_err = 0, e_scale = 0, w_err = 0, w_scale = 0;
};

// Scene energy and f_ext (already computed at `d`) against the all-pairs reference at the same atoms.
Check against_reference(MolecularScene& sc, const Data& d, double E, const std::vector<Vec6>& f_ext) {
  std::vector<Vec3> x, F;
  sc.atom_positions(d, x);
  ff::EnergyTerms t;
  const double E_ref = ff::evaluate_all_pairs(sc.topology, {}, x, &F, &t);
  const std::vector<Vec6> w = wrenches(sc, d, x, F);
  Check c;
  c.e_err = std::abs(E - E_ref);
  c.e_scale = energy_scale(t);
  for (int k = 1; k < sc.model->nbodies; ++k) {
    c.w_err = std::max(c.w_err, (w[k] - f_ext[k]).cwiseAbs().maxCoeff());
    c.w_scale = std::max(c.w_scale, w[k].cwiseAbs().maxCoeff());
  }
  return c;
}

}  // namespace

// Adaptive runs with reselections (fixed interval so a short run has several, and budget changes
// so the region changes), a pull on one atom:
// energy and every body wrench equal the all-pairs reference, and far fewer pairs are evaluated.
TEST(ForceFieldMotion, AdaptiveRunWithReselectionsMatchesAllPairs) {
  struct Case {
    const char* scene;
    int budget, steps;
  };
  for (const Case& cs : {Case{"bacteriorhodopsin", 48, 36}, Case{"ala20", 12, 60}, Case{"polyaniline", 12, 60}}) {
    MolecularScene sc = load_molecular_scene(cs.scene);
    const Model& m = *sc.model;
    State st(m);
    Data d(m);
    AdaptiveData ad(m);
    AdaptiveOptions ao;
    ao.budget = cs.budget;
    ao.reselect_every = 10;
    // Selections inside the step that is due: a background one lands when its worker is done, so
    // how many land in a short run would depend on the machine's load, and the counts below not.
    ao.background_selection = false;
    forward_kinematics(m, d, st.q);
    const int pulled = sc.natoms() / 2;
    const Vec3 pull(200, -100, 50);   // kJ/mol/nm
    int checks = 0;
    double worst_e = 0, worst_w = 0, pairs_grouped = 0;
    int grouped_steps = 0;
    for (int s = 0; s < cs.steps; ++s) {
      if (s > 0) update_all_body_poses(m, d, ad);
      const double E = sc.compute(d, st.f_ext);
      ASSERT_TRUE(std::isfinite(E)) << cs.scene << " step " << s;
      if (s % 6 == 5 || s == cs.steps - 1) {
        const Check c = against_reference(sc, d, E, st.f_ext);
        EXPECT_LE(c.e_err, kRel * c.e_scale) << cs.scene << " step " << s;
        EXPECT_LE(c.w_err, kRel * c.w_scale) << cs.scene << " step " << s;
        worst_e = std::max(worst_e, c.e_err / c.e_scale);
        worst_w = std::max(worst_w, c.w_err / c.w_scale);
        ++checks;
      }
      if (sc.force_field->rigid_groups() > 0 && sc.force_field->regroups() > 0) {
        pairs_grouped += static_cast<double>(sc.force_field->neighbour_pairs());
        ++grouped_steps;
      }
      sc.add_atom_force(d, pulled, pull, st.f_ext);
      // The budget alternates every 12 steps: each change reselects a different region, so groups
      // inside the old regions start moving and must be re-formed.
      ao.budget = (s / 12) % 2 ? cs.budget - 8 : cs.budget;
      adaptive_step(m, d, st, ad, ao, 0.0005);
    }
    EXPECT_GE(ad.report.selections, cs.steps / 10) << cs.scene;
    EXPECT_GE(sc.force_field->regroups(), 1 + (cs.steps - 1) / 12) << cs.scene;   // one per region change
    EXPECT_GT(grouped_steps, cs.steps / 2) << cs.scene;
    // Pairs evaluated per step with groups: only between frontier regions (bR: the inside of the
    // frontier regions holds a fifth of the listed pairs at 48 active DOF).
    EXPECT_LT(pairs_grouped / grouped_steps, 0.95 * static_cast<double>(sc.force_field->listed_pairs())) << cs.scene;
    std::printf("%s: %d checks, worst energy %.2e, wrench %.2e (relative); pairs/step with groups %.0f of %zu listed; "
                "%d regroups, %lld selections\n",
                cs.scene, checks, worst_e, worst_w, pairs_grouped / std::max(1, grouped_steps),
                sc.force_field->listed_pairs(), sc.force_field->regroups(),
                static_cast<long long>(ad.report.selections));
  }
}

// Scaling count: the pairs evaluated per step are exactly the listed pairs between bodies that moved
// relative to each other. Moving one joint j (all others still) splits the molecule into j's
// subtree and the rest: the count equals the list pairs across that cut, computed here by brute force
// from the list's own rule (different bodies, not excluded, |x_i − x_j| < r_off + skin at the build).
TEST(ForceFieldMotion, PairsEvaluatedFollowTheMovingSubtree) {
  MolecularScene sc = load_molecular_scene("bacteriorhodopsin");
  const Model& m = *sc.model;
  const Topology& t = sc.topology;
  const int n = sc.natoms();
  std::vector<Vec3> x0(n);
  for (int a = 0; a < n; ++a) x0[a] = sc.structure.atoms[a].pos;   // the list's build positions
  std::vector<std::vector<int>> excl(n);
  for (const auto& [a, b] : t.excluded) { excl[a].push_back(b); excl[b].push_back(a); }
  for (const auto& p : t.pairs14) { excl[p.i].push_back(p.j); excl[p.j].push_back(p.i); }
  const ff::NonbondedOptions o;
  const double rl2 = (o.r_off + o.skin) * (o.r_off + o.skin);
  // Subtree membership of each body below joint j (parent[k] < k: one ascending pass).
  auto subtree = [&](int j) {
    std::vector<char> in(m.nbodies, 0);
    in[j] = 1;
    for (int k = j + 1; k < m.nbodies; ++k) in[k] = in[m.parent[k]];
    return in;
  };
  auto pairs_across = [&](const std::vector<char>& in) {
    size_t count = 0;
    std::vector<int> mark(n, -1);
    for (int i = 0; i < n; ++i) {
      for (int e : excl[i]) mark[e] = i;
      const int bi = sc.torsion.atom_model_body[i];
      for (int j = i + 1; j < n; ++j) {
        const int bj = sc.torsion.atom_model_body[j];
        if (bi == bj || mark[j] == i || in[bi] == in[bj]) continue;
        if ((x0[i] - x0[j]).squaredNorm() < rl2) ++count;
      }
    }
    return count;
  };
  // Joints: the last body's (a side-chain or C-terminal end: small subtree), and one near the
  // middle of the chain (about half of the molecule moves against the other half).
  const int nb = m.nbodies;
  int leaf = nb - 1;
  while (leaf > 1 && m.v_num[leaf] == 0) --leaf;
  int mid = nb / 2;
  while (mid < nb - 1 && m.v_num[mid] == 0) ++mid;
  const std::vector<int> joints = {leaf, mid};
  size_t previous = 0;
  State st(m);
  Data d(m);
  for (size_t c = 0; c < joints.size(); ++c) {
    const int j = joints[c];
    ASSERT_GT(m.v_num[j], 0);
    const size_t expected = pairs_across(subtree(j));
    Eigen::VectorXd q = neutral_configuration(m);
    std::vector<Vec6> f;
    // Two still steps (the groups form: everything is one group, nothing is evaluated), then j moves
    // by 1e-4 rad per step (atoms move < skin/2: no list rebuild, the list stays the x0 one).
    for (int s = 0; s < 8; ++s) {
      if (s >= 3) q(m.v_adr[j]) += 1e-4;
      forward_kinematics(m, d, q);
      const double E = sc.compute(d, f);
      if (s == 2) {
        EXPECT_EQ(sc.force_field->neighbour_pairs(), 0u) << "still molecule, joint " << j;
      }
      if (s >= 5) {   // j has been moving for two steps: groups = j's subtree | the rest
        EXPECT_EQ(sc.force_field->pairs_evaluated(), expected) << "joint " << j << " step " << s;
        const Check ck = against_reference(sc, d, E, f);
        EXPECT_LE(ck.e_err, kRel * ck.e_scale) << "joint " << j;
        EXPECT_LE(ck.w_err, kRel * ck.w_scale) << "joint " << j;
      }
    }
    std::printf("joint %d moving: %zu pairs evaluated per step of %zu listed\n", j, expected,
                sc.force_field->listed_pairs());
    EXPECT_GT(expected, previous);   // the cut grows from the chain's end to its middle
    previous = expected;
    EXPECT_LT(expected, sc.force_field->listed_pairs());
  }
  // Everything moving: every listed pair, every step (no groups).
  Eigen::VectorXd q = neutral_configuration(m);
  std::vector<Vec6> f;
  for (int s = 0; s < 4; ++s) {
    for (int k = 0; k < q.size(); ++k) q(k) += 1e-6 * (1 + (k % 3));   // < skin/2 in all
    forward_kinematics(m, d, q);
    sc.compute(d, f);
  }
  EXPECT_LE(sc.force_field->rigid_groups(), 1);   // at most ground + the welded root body
  EXPECT_EQ(sc.force_field->pairs_evaluated(), sc.force_field->listed_pairs());
  EXPECT_EQ(sc.force_field->neighbour_rebuilds(), 0);   // the counts above used the x0 list
}

// A joint inside a group that starts moving re-forms the groups at once (no stale cache), and
// compute_atoms (no poses) still evaluates every pair.
TEST(ForceFieldMotion, GroupInsideMovingIsReformedAtOnce) {
  MolecularScene sc = load_molecular_scene("ala20");
  const Model& m = *sc.model;
  Data d(m);
  Eigen::VectorXd q = neutral_configuration(m);
  std::vector<Vec6> f;
  for (int s = 0; s < 4; ++s) {   // still: one group
    forward_kinematics(m, d, q);
    sc.compute(d, f);
  }
  EXPECT_EQ(sc.force_field->neighbour_pairs(), 0u);
  const int r0 = sc.force_field->regroups();
  q(m.v_adr[10]) += 0.05;   // a large step of one joint inside the group
  forward_kinematics(m, d, q);
  const double E = sc.compute(d, f);
  EXPECT_EQ(sc.force_field->regroups(), r0 + 1);
  const Check c = against_reference(sc, d, E, f);
  EXPECT_LE(c.e_err, kRel * c.e_scale);
  EXPECT_LE(c.w_err, kRel * c.w_scale);
  std::vector<Vec3> x, F;
  sc.atom_positions(d, x);
  const double Ea = sc.force_field->compute_atoms(x, F);
  EXPECT_NEAR(Ea, E, kRel * c.e_scale);
  EXPECT_EQ(sc.force_field->pairs_evaluated(), sc.force_field->listed_pairs());
}

// The 1×4 cluster kernel (masked lanes, padding of the last cluster, rsqrt + Newton 1/r, pruning)
// against the all-pairs reference, per atom (every atom its own body, so nothing is cached), for
// both dielectrics and a switch other than the default (r_on, r_off move where the masked lanes'
// "far" r² and the clamp land). Only summation order differs (tolerance (a) above: ≈ 1e-13 of
// the force scale; 1/r is within 2 ulp), so 1e-9 of max |F| still catches one lost, doubled or
// mis-masked pair (≥ 1e-5 of it). At least one scene has an atom count that is not a multiple of 4
// (the last cluster padded; the greedy clusters may pad others too).
TEST(ForceFieldMotion, ClusterKernelMatchesAllPairsPerAtom) {
  int padded = 0;
  for (const char* name : {"ala20", "polyaniline", "bacteriorhodopsin"}) {
    MolecularScene sc = load_molecular_scene(name);
    const Model& m = *sc.model;
    Data d(m);
    Eigen::VectorXd q = neutral_configuration(m);
    // Off the input pose, without clashes (bR's 444-joint chain amplifies the angles).
    const double amp = sc.natoms() > 1000 ? 0.002 : 0.05;
    for (int k = 0; k < q.size(); ++k) q(k) += amp * std::sin(3.0 * k);
    forward_kinematics(m, d, q);
    std::vector<Vec3> x;
    sc.atom_positions(d, x);
    padded += sc.natoms() % 4 != 0;
    for (const bool ddd : {true, false})
      for (const double r_on : {0.8, 0.6}) {
        ff::NonbondedOptions o;
        o.distance_dielectric = ddd;
        o.r_on = r_on;
        o.r_off = r_on + (r_on == 0.8 ? 0.2 : 0.6);
        // Every atom its own body: no term is skipped as rigid, so per-atom forces are complete.
        std::vector<int> own(sc.natoms());
        for (int a = 0; a < sc.natoms(); ++a) own[a] = a;
        ff::Evaluator ev(sc.topology, own, {}, x, o);
        std::vector<Vec3> F, F_ref;
        ff::EnergyTerms t, t_ref;
        const double E = ev.compute_atoms(x, F, &t);
        const double E_ref = ff::evaluate_all_pairs(sc.topology, o, x, &F_ref, &t_ref);
        double f_err = 0, f_scale = 0;
        for (int a = 0; a < sc.natoms(); ++a) {
          f_err = std::max(f_err, (F[a] - F_ref[a]).cwiseAbs().maxCoeff());
          f_scale = std::max(f_scale, F_ref[a].cwiseAbs().maxCoeff());
        }
        EXPECT_LE(std::abs(E - E_ref), kRel * energy_scale(t_ref)) << name << " ddd " << ddd << " r_on " << r_on;
        EXPECT_LE(std::abs(t.coulomb + t.lj - t_ref.coulomb - t_ref.lj), kRel * energy_scale(t_ref)) << name;
        EXPECT_LE(f_err, kRel * f_scale) << name << " ddd " << ddd << " r_on " << r_on;
        EXPECT_EQ(ev.pairs_evaluated(), ev.listed_pairs());
        EXPECT_GT(ev.kernel_lanes(), 0u);   // pruned at r_off + kPrune: may be below listed_pairs()
        std::printf("%s ddd %d r_on %.1f: E %.6f vs %.6f, max |dF| %.2e of %.2e; cluster fill %.3f\n", name, ddd,
                    r_on, E, E_ref, f_err, f_scale,
                    static_cast<double>(ev.pairs_evaluated()) / static_cast<double>(ev.kernel_lanes()));
      }
  }
  EXPECT_GE(padded, 1);
}
