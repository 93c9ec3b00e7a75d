// O(log n) force-feedback coupling (docs/algorithms.md §11–§12): f_feed computed from the snapshot
// alone against (1) a full DCA pass with the user forces added to the grabbed bodies' f_ext and
// (2) the long-double oracle `I a + v ×* I v − f_u`; nodes read; joint owners; β_ext recovery;
// no allocation per call; statuses; virtual coupling and unit mapping.
#include <gtest/gtest.h>

#include <atomic>
#include <cstdlib>
#include <new>
#include <random>
#include <set>

#include <Eigen/Eigenvalues>

#include "haptree/adaptive.hpp"
#include "haptree/coupling.hpp"
#include "haptree/isa.hpp"
#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"
#include "tests/support/oracle.hpp"

#include "tests/support/count_allocations.hpp"


namespace haptree {
namespace {

using testing::oracle_forward_dynamics;
using testing::random_state;

double rel6(const Vec6& a, const Vec6& ref) { return (a - ref).norm() / std::max(1.0, ref.norm()); }

// Grabs on random bodies (repeats allowed, and forced when n ≥ 3) at random body-local points.
std::vector<Grab> random_grabs(const Model& m, const Data& d, int n, std::mt19937& rng) {
  std::uniform_int_distribution<int> body(1, m.nbodies - 1);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  std::vector<Grab> g;
  for (int i = 0; i < n; ++i) {
    const int k = (i == 2) ? g[0].body : body(rng);
    g.push_back(make_grab(d, k, Vec3(u(rng), u(rng), u(rng))));
  }
  return g;
}

// Random user forces at the grab points; even grabs are 3-DOF ([0; F]), odd ones 6-DOF.
std::vector<Vec6> random_forces(int n, std::mt19937& rng, double scale = 5.0) {
  std::uniform_real_distribution<double> u(-scale, scale);
  std::vector<Vec6> f(n);
  for (int i = 0; i < n; ++i) {
    for (int c = 0; c < 6; ++c) f[i](c) = u(rng);
    if (i % 2 == 0) f[i].head<3>().setZero();
  }
  return f;
}

struct Reference {
  explicit Reference(const Model& m) : st_applied(m) {}
  std::vector<Vec6> full;     // from a full DCA pass with f_u applied
  std::vector<Vec6> oracle;   // I a + v ×* I v − f_u with oracle body accelerations
  State st_applied;
};

// The user forces moved to the body origins and added to State::f_ext.
State apply_user_forces(const Model& m, const Data& kin, const State& st,
                        const std::vector<Grab>& grabs, const std::vector<Vec6>& fu) {
  State s2 = st;
  for (std::size_t g = 0; g < grabs.size(); ++g) {
    const int k = grabs[g].body;
    s2.f_ext[k] += shift_force(fu[g], kin.r[k] - grabs[g].point);
  }
  return s2;
}

Reference reference(const Model& m, const State& st, const std::vector<Grab>& grabs,
                    const std::vector<Vec6>& fu, bool with_oracle) {
  const auto& t = m.tree;
  Data kin(m);
  forward_kinematics(m, kin, st.q);
  Reference ref(m);
  ref.st_applied = apply_user_forces(m, kin, st, grabs, fu);
  Data d2(m);
  forward_dynamics(m, d2, ref.st_applied);
  EXPECT_EQ(d2.diag.singular_pivots, 0);
  testing::OracleResult orc;
  if (with_oracle) orc = oracle_forward_dynamics(m, ref.st_applied);
  for (std::size_t g = 0; g < grabs.size(); ++g) {
    const int k = grabs[g].body;
    Vec6 fu_k = Vec6::Zero();   // all user forces on body k, at r_k
    for (std::size_t g2 = 0; g2 < grabs.size(); ++g2)
      if (grabs[g2].body == k) fu_k += shift_force(fu[g2], d2.r[k] - grabs[g2].point);
    const int leaf = t.leaf_of_body[k];
    Vec6 feed = d2.f_total[k] - fu_k;
    for (int x = 0; x < t.handle_num[leaf]; ++x) {
      const int jx = t.handle(leaf, x);
      const Vec3 off = jx == k ? Vec3::Zero() : Vec3(d2.d[jx]);
      feed += shift_force(d2.f(leaf, x), -off);   // handle force moved from its point to r_k
    }
    const Vec3 to_grab = grabs[g].point - d2.r[k];
    ref.full.push_back(shift_force(feed, to_grab));
    if (with_oracle) {
      const Vec6 a = orc.body_acc[k];
      const Vec6 f = d2.I[k] * a + cross_force(d2.v[k], d2.I[k] * d2.v[k]) - fu_k;
      ref.oracle.push_back(shift_force(f, to_grab));
    }
  }
  return ref;
}

// |E| computed independently from the assembly tree: U ∪ children(U).
int extended_region_size(const Model& m, const std::vector<Grab>& grabs) {
  const auto& t = m.tree;
  std::set<int> U, E;
  for (const auto& g : grabs)
    for (int n = t.leaf_of_body[g.body]; n >= 0; n = t.up[n]) U.insert(n);
  for (int n : U) {
    E.insert(n);
    if (!t.is_leaf(n)) { E.insert(t.P[n]); E.insert(t.Q[n]); }
  }
  return static_cast<int>(E.size());
}

struct Case {
  std::string scene;
  int n;
  bool mixed, free_root, oracle;
  int max_children = 0;   // degree reduction (§4.4): hub pieces assembled in inertia form
};

class CouplingVsFullPass : public ::testing::TestWithParam<Case> {};

// The force bound above, from the oracle's H and the body inertias of `d` (after a pass).
double force_error_bound(const Model& m, const Data& d, const State& st) {
  double kI = 1;
  for (int k = 1; k < m.nbodies; ++k) {
    const Eigen::Matrix<double, 6, 1> ev = Eigen::SelfAdjointEigenSolver<Mat6>(d.I[k]).eigenvalues();
    kI = std::max(kI, ev(5) / std::max(ev(0), 1e-16 * ev(5)));
  }
  const auto orc = oracle_forward_dynamics(m, st);
  const double kH = testing::mass_matrix_condition(orc);
  return testing::qdd_error_bound(orc, st, testing::kBoundC) * (m.nv + 6.0) / std::max(m.nv, 1) *
         std::max(kH, kI) / kH;
}

// Tolerance: f_feed and the full pass are two backward-stable solutions of one
// system, so each is within B of the exact one and they differ by ≤ 2B, with
// B = c·(n + 6)·ε·max(κ(H), κ_I)·cancel (tests/support/oracle.hpp): forces, unlike q̈, include the
// constrained directions, whose systems are as conditioned as the bodies' spatial inertias
// (κ_I = max_k κ(I_k) at r_k; 1e3 for a 0.3 × 0.04 m rod), and 6 more terms per force. B is
// computed per model and state (star_200 mixed reduced: the former fixed 1e-10 failed at
// 1.32e-10 on an AVX-512 Xeon). Errors are recorded as err/B; the line printed keeps the values.
void coupling_vs_full_pass(const Case& c) {
  double worst_full = 0, worst_oracle = 0, worst_applied = 0, worst_requery = 0;
  double worst_ratio = 0, bound_min = 1;
  int cases = 0;
  for (unsigned seed = 1; seed <= 2; ++seed) {
    SceneOptions o;
    o.n = c.n;
    o.seed = seed;
    o.mixed_joints = c.mixed;
    o.build.max_children = c.max_children;
    o.free_root = c.free_root;
    auto model = make_scene(c.scene, o);
    const Model& m = *model;
    const State st = random_state(m, 300 + seed);
    Data d(m);
    forward_dynamics(m, d, st);
    ASSERT_EQ(d.diag.singular_pivots, 0);
    const double B = force_error_bound(m, d, st);
    bound_min = std::min(bound_min, B);
    std::mt19937 rng(seed * 7919 + c.n);
    CouplingSnapshot snap, snap_applied;
    CouplingWorkspace ws;
    for (int nf : {1, 2, 3, 5, 8}) {
      const auto grabs = random_grabs(m, d, nf, rng);
      const auto fu = random_forces(nf, rng);
      const bool orc = c.oracle && (nf == 1 || nf == 8 || c.n <= 64);
      const Reference ref = reference(m, st, grabs, fu, orc);

      // (1) snapshot from a pass WITHOUT the user forces.
      make_coupling_snapshot(m, d, grabs, {}, 11, st.t, snap);
      ws.reserve_for(snap);
      std::vector<Vec6> feed(nf);
      ASSERT_EQ(coupling_forces(snap, fu.data(), ws, feed.data()), CouplingStatus::kOk);
      for (int g = 0; g < nf; ++g) {
        worst_full = std::max(worst_full, rel6(feed[g], ref.full[g]));
        worst_ratio = std::max(worst_ratio, rel6(feed[g], ref.full[g]) / (2 * B));
        if (orc) worst_oracle = std::max(worst_oracle, rel6(feed[g], ref.oracle[g]));
        if (orc) worst_ratio = std::max(worst_ratio, rel6(feed[g], ref.oracle[g]) / B);
      }
      // Nodes read: 2·depth+1 for one grab, |union of extended up-regions| for several.
      if (nf == 1) {
        const int leaf = m.tree.leaf_of_body[grabs[0].body];
        EXPECT_EQ(ws.nodes_read, 2 * m.tree.depth[leaf] + 1);
      }
      EXPECT_EQ(ws.nodes_read, extended_region_size(m, grabs)) << "nf=" << nf;

      // (2) snapshot from the pass WITH the user forces applied (β_ext and f_ext recovery).
      Data d2(m);
      forward_dynamics(m, d2, ref.st_applied);
      make_coupling_snapshot(m, d2, grabs, fu, 12, st.t, snap_applied);
      ws.reserve_for(snap_applied);
      std::vector<Vec6> feed2(nf);
      ASSERT_EQ(coupling_forces(snap_applied, fu.data(), ws, feed2.data()), CouplingStatus::kOk);
      for (int g = 0; g < nf; ++g) {
        worst_applied = std::max(worst_applied, rel6(feed2[g], ref.full[g]));
        worst_ratio = std::max(worst_ratio, rel6(feed2[g], ref.full[g]) / (2 * B));
      }
      // ... and re-queried with other forces it matches a full pass with those forces.
      const auto fu2 = random_forces(nf, rng, 20.0);
      const Reference ref2 = reference(m, st, grabs, fu2, false);
      ASSERT_EQ(coupling_forces(snap_applied, fu2.data(), ws, feed2.data()), CouplingStatus::kOk);
      for (int g = 0; g < nf; ++g) {
        worst_requery = std::max(worst_requery, rel6(feed2[g], ref2.full[g]));
        worst_ratio = std::max(worst_ratio, rel6(feed2[g], ref2.full[g]) / (2 * B));
      }
      ++cases;
    }
  }
  EXPECT_LE(worst_ratio, 1.0) << c.scene << " (error / derived bound; smallest bound "
                              << bound_min << ")";
  ::testing::Test::RecordProperty("max_rel_err_full", std::to_string(worst_full));
  ::testing::Test::RecordProperty("max_rel_err_oracle", std::to_string(worst_oracle));
  ::testing::Test::RecordProperty("max_rel_err_applied", std::to_string(worst_applied));
  ::testing::Test::RecordProperty("max_rel_err_requery", std::to_string(worst_requery));
  std::printf("[ coupling ] %s n=%d, kernels %s: full %.2e  oracle %.2e  applied %.2e  requery %.2e (%d grab sets)"
              "  err/bound %.2e (bound ≥ %.1e)\n",
              c.scene.c_str(), c.n, isa::name(isa::active()), worst_full, worst_oracle, worst_applied, worst_requery, cases,
              worst_ratio, bound_min);
}

// At every instruction-set level the CPU has (the default build holds a baseline and an x86-64-v3
// copy of the DCA and of coupling_forces, chosen at run time): the same derived bound.
TEST_P(CouplingVsFullPass, SnapshotAloneMatchesFullPassAndOracle) {
  const isa::Level was = isa::active();
  for (isa::Level level : {isa::Level::generic, isa::Level::avx2, isa::Level::avx512}) {
    if (!isa::set_active(level)) continue;   // not on this CPU
    SCOPED_TRACE(isa::name(level));
    coupling_vs_full_pass(GetParam());
  }
  isa::set_active(was);
}

INSTANTIATE_TEST_SUITE_P(
    Scenes, CouplingVsFullPass,
    ::testing::Values(Case{"chain", 1, false, false, true}, Case{"chain", 2, false, false, true},
                      Case{"chain", 7, true, true, true}, Case{"chain", 64, false, false, true},
                      Case{"chain", 64, true, true, true}, Case{"chain", 1024, false, false, false},
                      Case{"random_tree", 16, true, true, true},
                      Case{"random_tree", 64, true, true, true},
                      Case{"random_tree", 400, true, true, false},
                      Case{"binary_tree", 63, false, true, true},
                      Case{"binary_tree", 511, false, false, false},
                      Case{"star", 16, false, true, true},
                      Case{"star", 200, true, false, true, 4},
                      Case{"star", 200, false, true, true, 2},
                      Case{"protein_like", 0, false, false, true}),
    [](const auto& info) {
      return info.param.scene + "_" + std::to_string(info.param.n) +
             (info.param.mixed ? "_mixed" : "") + (info.param.free_root ? "_free" : "") +
             (info.param.max_children ? "_reduced" : "");
    });

// The Φ columns of long segments of a 65 536-chain decay to subnormal values (down to
// 5e-324), which cost Intel CPUs ~100 cycles per operand in coupling_forces. Snapshots are built
// without them; the feedback is unchanged (each flushed value moves by < 2⁻¹⁰²²) and still matches
// a full pass with the user force applied, at the tolerance of CouplingVsFullPass.
TEST(Coupling, SnapshotsOfA65536ChainHoldNoSubnormals) {
  SceneOptions o;
  o.n = 1 << 16;
  o.seed = 1;
  auto model = make_chain(o);
  const Model& m = *model;
  std::mt19937 rs(7);   // coupling_bench's state: random angles, rates and torques
  std::uniform_real_distribution<double> u(-1, 1);
  State st(m);
  for (int k = 1; k < m.nbodies; ++k) {
    st.q(m.q_adr[k]) = u(rs);
    st.qd(m.v_adr[k]) = 0.3 * u(rs);
    st.tau(m.v_adr[k]) = 0.1 * u(rs);
  }
  Data d(m);
  forward_dynamics(m, d, st);
  std::mt19937 rng(7);
  std::size_t kept = 0, flushed = 0, in_workspace = 0;
  double worst_full = 0, worst_change = 0;
  CouplingSnapshot raw, snap;
  CouplingWorkspace ws;
  for (int set = 0; set < 4; ++set) {
    const auto grabs = random_grabs(m, d, 1, rng);
    const auto fu = random_forces(1, rng);
    make_coupling_snapshot(m, d, grabs, {}, set, 0, raw, /*flush_tiny=*/false);
    make_coupling_snapshot(m, d, grabs, {}, set, 0, snap);
    kept += count_subnormals(raw.values.data(), raw.values.size());
    flushed += count_subnormals(snap.values.data(), snap.values.size());
    Vec6 feed_raw, feed;
    ws.reserve_for(raw);
    ASSERT_EQ(coupling_forces(raw, fu.data(), ws, &feed_raw), CouplingStatus::kOk);
    ws.reserve_for(snap);
    ASSERT_EQ(coupling_forces(snap, fu.data(), ws, &feed), CouplingStatus::kOk);
    for (const auto* v : {&ws.bu, &ws.f, &ws.dbeta, &ws.W})
      in_workspace += count_subnormals(v->data(), v->size());
    const Reference ref = reference(m, st, grabs, fu, false);
    worst_full = std::max(worst_full, rel6(feed, ref.full[0]));
    worst_change = std::max(worst_change, rel6(feed, feed_raw));
  }
  EXPECT_GT(kept, 0u);            // the coefficients do produce them ...
  EXPECT_EQ(flushed, 0u);         // ... and the snapshots do not carry them
  EXPECT_EQ(in_workspace, 0u);    // nor do the call's stored intermediates
  // Not an error bound: the oracle (and so B) is out of reach at n = 65 536 (O(n³)), and B's
  // normwise κ(H) of a chain that long would exceed 1. 1e-10 is CouplingVsFullPass's former fixed
  // bound, kept as a guard against gross breakage (measured 6.7e-12 generic); what this test
  // asserts is worst_change below.
  EXPECT_LE(worst_full, 1e-10);
  // Flushed values are < 2⁻¹⁰²² and enter sums with O(1) terms: the feedback cannot move by more
  // than round-off (measured: bitwise equal).
  EXPECT_LE(worst_change, 1e-15);
  std::printf("[ coupling ] chain 65536: %zu subnormal values kept without the flush, %zu with; "
              "vs full pass %.2e, change %.2e\n", kept, flushed, worst_full, worst_change);
}

// Hybrid (adaptive) bodies: the active region contains the grabbed leaves' up-regions, siblings are
// composite rigid frontier nodes. The snapshot reads whatever W/β/Φ the nodes hold; f_feed must
// equal the hybrid pass with f_u applied and the oracle with the locked DOFs removed.
TEST(Coupling, HybridBodiesMatchHybridPassAndLockedOracle) {
  double worst_full = 0, worst_oracle = 0, worst_applied = 0;
  double hybrid_bound = 1;
  int rigid_siblings = 0;
  for (const char* scene : {"chain", "random_tree", "protein_like"}) {
    for (unsigned seed = 1; seed <= 2; ++seed) {
      SceneOptions o;
      o.n = 80;
      o.seed = seed;
      o.mixed_joints = std::string(scene) == "random_tree";
      auto model = make_scene(scene, o);
      const Model& m = *model;
      const auto& t = m.tree;
      std::mt19937 rng(seed * 101 + m.nbodies);
      std::uniform_int_distribution<int> body(1, m.nbodies - 1);
      for (int nf : {1, 3, 6}) {
        std::vector<int> bodies;
        for (int g = 0; g < nf; ++g) bodies.push_back(g == 2 ? bodies[0] : body(rng));
        // Active region: the grabbed leaves' ancestors plus the path to one random extra node.
        std::vector<char> active(t.nnodes(), 0);
        for (int k : bodies)
          for (int n = t.up[t.leaf_of_body[k]]; n >= 0; n = t.up[n]) active[n] = 1;
        for (int n = t.up[t.leaf_of_body[body(rng)]]; n >= 0; n = t.up[n]) active[n] = 1;
        State st = random_state(m, 40 + seed);
        Data d(m);
        AdaptiveData ad(m);
        set_active_region(m, d, st, ad, active);   // zeroes q̇ of the locked joints
        if (nf == 1) {
          Data dk(m);
          forward_dynamics(m, dk, st);
          hybrid_bound = std::min(hybrid_bound, force_error_bound(m, dk, st));
        }
        adaptive_forward_dynamics(m, d, st, ad);
        ASSERT_EQ(d.diag.singular_pivots, 0);
        std::uniform_real_distribution<double> u(-0.3, 0.3);
        std::vector<Grab> grabs;
        for (int k : bodies) {
          Grab g;
          g.body = k;
          g.point = d.r[k] + d.R[k] * Vec3(u(rng), u(rng), u(rng));
          grabs.push_back(g);
        }
        const auto fu = random_forces(nf, rng);
        CouplingSnapshot snap;
        make_coupling_snapshot(m, d, grabs, {}, 1, 0, snap);
        CouplingWorkspace ws(snap);
        std::vector<Vec6> feed(nf);
        ASSERT_EQ(coupling_forces(snap, fu.data(), ws, feed.data()), CouplingStatus::kOk);
        EXPECT_EQ(ws.nodes_read, extended_region_size(m, grabs));
        for (int n = 0; n < t.nnodes(); ++n)
          if (!t.is_leaf(n) && !active[n] && t.up[n] >= 0 && active[t.up[n]]) ++rigid_siblings;

        // Hybrid pass with the user forces applied.
        State st2 = apply_user_forces(m, d, st, grabs, fu);
        Data d2(m);
        AdaptiveData ad2(m);
        set_active_region(m, d2, st2, ad2, active);
        adaptive_forward_dynamics(m, d2, st2, ad2);
        // Oracle with the locked DOFs removed; body velocities from full kinematics.
        std::vector<bool> locked(m.nv, true);
        for (int J : ad2.active_joints)
          for (int a = 0; a < m.v_num[J]; ++a) locked[m.v_adr[J] + a] = false;
        const auto orc = oracle_forward_dynamics(m, st2, locked);
        Data kin(m);
        forward_kinematics(m, kin, st2.q);
        body_dynamics_terms(m, kin, st2);
        for (int g = 0; g < nf; ++g) {
          const int k = grabs[g].body, leaf = t.leaf_of_body[k];
          Vec6 fu_k = Vec6::Zero();
          for (int g2 = 0; g2 < nf; ++g2)
            if (grabs[g2].body == k) fu_k += shift_force(fu[g2], d2.r[k] - grabs[g2].point);
          Vec6 ref = d2.f_total[k] - fu_k;
          for (int x = 0; x < t.handle_num[leaf]; ++x) {
            const int jx = t.handle(leaf, x);
            ref += shift_force(d2.f(leaf, x), -(jx == k ? Vec3::Zero() : Vec3(d2.d[jx])));
          }
          const Vec3 to_grab = grabs[g].point - d2.r[k];
          worst_full = std::max(worst_full, rel6(feed[g], shift_force(ref, to_grab)));
          const Vec6 fo = kin.I[k] * orc.body_acc[k] +
                          cross_force(kin.v[k], kin.I[k] * kin.v[k]) - fu_k;
          worst_oracle = std::max(worst_oracle, rel6(feed[g], shift_force(fo, to_grab)));
        }
        // Snapshot from the hybrid pass WITH f_u applied (β_ext recovery on hybrid data).
        CouplingSnapshot snap2;
        make_coupling_snapshot(m, d2, grabs, fu, 2, 0, snap2);
        std::vector<Vec6> feed2(nf);
        ASSERT_EQ(coupling_forces(snap2, fu.data(), ws, feed2.data()), CouplingStatus::kOk);
        for (int g = 0; g < nf; ++g) worst_applied = std::max(worst_applied, rel6(feed2[g], feed[g]));
      }
    }
  }
  EXPECT_GT(rigid_siblings, 0);   // the test did exercise composite rigid siblings
  // Tolerance: the force bound B of the full model (n, κ): the reduced system's
  // data come from all bodies and ‖H_aa⁻¹‖ ≤ ‖H⁻¹‖ (interlacing, see
  // tests/stress/origin_independence_test.cpp); the smallest B over the models is asserted.
  EXPECT_LE(worst_full, 2 * hybrid_bound);
  EXPECT_LE(worst_oracle, hybrid_bound);
  EXPECT_LE(worst_applied, 2 * hybrid_bound);
  std::printf("[ coupling ] hybrid: full %.2e  oracle %.2e  applied %.2e  (rigid siblings %d, "
              "bound %.1e)\n", worst_full, worst_oracle, worst_applied, rigid_siblings,
              hybrid_bound);
}

TEST(Coupling, LogarithmicRegionsOnBalancedChains) {
  // §15.10: nodes read ≤ 2⌈log₂(n+1)⌉+1 for one grab; |U| ≤ n_f(⌈log₂(n/n_f)⌉+2) for n_f grabs.
  SceneOptions o;
  o.n = 4096;
  o.seed = 1;
  auto model = make_chain(o);
  const Model& m = *model;
  Data d(m);
  forward_dynamics(m, d, State(m));
  CouplingSnapshot snap;
  CouplingWorkspace ws;
  std::mt19937 rng(5);
  std::uniform_int_distribution<int> body(1, m.nbodies - 1);
  const double n = o.n;
  for (int nf : {1, 2, 4, 8, 16}) {
    for (int rep = 0; rep < 20; ++rep) {
      std::vector<Grab> grabs;
      for (int g = 0; g < nf; ++g) grabs.push_back(make_grab(d, body(rng), Vec3::Zero()));
      make_coupling_snapshot(m, d, grabs, {}, rep, 0, snap);
      ws.reserve_for(snap);
      std::vector<Vec6> fu(nf, Vec6::Ones()), feed(nf);
      ASSERT_EQ(coupling_forces(snap, fu.data(), ws, feed.data()), CouplingStatus::kOk);
      if (nf == 1) {
        EXPECT_LE(ws.nodes_read, 2 * std::ceil(std::log2(n + 1)) + 1);
      }
      EXPECT_LE(snap.ints[2], nf * (std::ceil(std::log2(n / nf)) + 2)) << nf;
    }
  }
}

TEST(Coupling, JointOwnersOfTheGrabbedBodyLieInItsUpRegion) {
  for (const char* scene : {"chain", "random_tree", "binary_tree", "protein_like", "star"}) {
    SceneOptions o;
    o.n = 200;
    o.seed = 3;
    o.mixed_joints = std::string(scene) == "random_tree";
    auto model = make_scene(scene, o);
    const auto& t = model->tree;
    for (int k = 1; k < model->nbodies; ++k) {
      const auto U = t.up_region(t.leaf_of_body[k]);
      const std::set<int> Us(U.begin(), U.end());
      std::vector<int> incident{k};
      for (int c : model->children[k]) incident.push_back(c);
      for (int J : incident) EXPECT_TRUE(Us.count(t.owner_of_joint[J])) << scene << " body " << k << " joint " << J;
    }
  }
}

TEST(Coupling, WeldedBodyFeedsBackMinusUserForce) {
  // A body welded to the ground cannot accelerate: f_feed = f_ext + f_c = −f_u exactly.
  ModelBuilder b;
  b.add_body("w", 0, JointType::kFixed, Vec3(0.1, 0.2, 0.3), Mat3::Identity(), Vec3::UnitZ(), 2.0,
             Vec3(0.1, 0, 0), Vec3(0.1, 0.2, 0.3).asDiagonal());
  b.add_body("r", 1, JointType::kRevolute, Vec3(0.5, 0, 0), Mat3::Identity(), Vec3::UnitY(), 1.0,
             Vec3(0.2, 0, 0), Vec3(0.01, 0.05, 0.05).asDiagonal());
  auto model = b.build();
  State st(*model);
  st.qd(0) = 0.5;
  Data d(*model);
  forward_dynamics(*model, d, st);
  CouplingSnapshot snap;
  make_coupling_snapshot(*model, d, {make_grab(d, 1, Vec3(0.05, 0.1, 0))}, {}, 1, 0, snap);
  CouplingWorkspace ws(snap);
  Vec6 fu;
  fu << 0.3, -0.2, 0.1, 4, -5, 6;
  Vec6 feed;
  ASSERT_EQ(coupling_forces(snap, &fu, ws, &feed), CouplingStatus::kOk);
  EXPECT_LE((feed + fu).norm(), 1e-12 * fu.norm());
}

TEST(Coupling, FreeFloatingBodyFeedsBackOnlyItsExternalForce) {
  // A free body (6-DOF root joint, no τ) has no constraint force: f_feed = f_ext (here weight).
  SceneOptions o;
  o.n = 1;
  o.free_root = true;
  o.seed = 4;
  auto model = make_chain(o);
  State st = random_state(*model, 9);
  st.tau.setZero();
  Data d(*model);
  forward_dynamics(*model, d, st);
  const Grab g = make_grab(d, 1, Vec3(0.1, -0.2, 0.05));
  CouplingSnapshot snap;
  make_coupling_snapshot(*model, d, {g}, {}, 1, 0, snap);
  CouplingWorkspace ws(snap);
  Vec6 fu;
  fu << 0, 0, 0, 10, 20, -30;
  Vec6 feed;
  ASSERT_EQ(coupling_forces(snap, &fu, ws, &feed), CouplingStatus::kOk);
  const Vec6 expect = shift_force(d.f_total[1], g.point - d.r[1]);
  EXPECT_LE((feed - expect).norm(), 1e-12 * std::max(1.0, expect.norm()));
}

TEST(Coupling, NoAllocationPerCallOrPerSnapshotOnceSized) {
  for (const char* scene : {"chain", "random_tree", "protein_like"}) {
    SceneOptions o;
    o.n = 500;
    o.seed = 2;
    o.mixed_joints = std::string(scene) == "random_tree";
    o.free_root = o.mixed_joints;
    auto model = make_scene(scene, o);
    const State st = random_state(*model, 5);
    Data d(*model);
    forward_dynamics(*model, d, st);
    std::mt19937 rng(3);
    const auto grabs = random_grabs(*model, d, 4, rng);
    const auto fu = random_forces(4, rng);
    CouplingSnapshot snap;
    make_coupling_snapshot(*model, d, grabs, fu, 1, 0, snap);   // sizes the snapshot
    CouplingWorkspace ws(snap);
    std::vector<Vec6> feed(4);
    const long before = haptree::testing::allocation_count();
    for (int i = 0; i < 3; ++i) make_coupling_snapshot(*model, d, grabs, fu, 2 + i, 0, snap);
    for (int i = 0; i < 100; ++i)
      ASSERT_EQ(coupling_forces(snap, fu.data(), ws, feed.data()), CouplingStatus::kOk);
    EXPECT_EQ(haptree::testing::allocation_count() - before, 0) << scene;
  }
}

TEST(Coupling, Statuses) {
  SceneOptions o;
  o.n = 32;
  o.seed = 1;
  auto model = make_chain(o);
  const State st = random_state(*model, 1);
  Data d(*model);
  forward_dynamics(*model, d, st);
  CouplingSnapshot snap;
  make_coupling_snapshot(*model, d, {}, {}, 1, 0, snap);
  CouplingWorkspace ws;
  Vec6 fu = Vec6::Ones(), feed;
  EXPECT_EQ(coupling_forces(snap, &fu, ws, &feed), CouplingStatus::kEmpty);
  make_coupling_snapshot(*model, d, {make_grab(d, 20, Vec3::Zero())}, {}, 2, 0, snap);
  EXPECT_EQ(coupling_forces(snap, &fu, ws, &feed), CouplingStatus::kWorkspaceTooSmall);
  ws.reserve_for(snap);
  EXPECT_EQ(coupling_forces(snap, &fu, ws, &feed), CouplingStatus::kOk);
  Vec6 bad = fu;
  bad(4) = std::nan("");
  EXPECT_EQ(coupling_forces(snap, &bad, ws, &feed), CouplingStatus::kNonFinite);
  EXPECT_TRUE(feed.isZero());
  {
    CouplingSnapshot s2 = snap;
    s2.values.pop_back();
    EXPECT_EQ(coupling_forces(s2, &fu, ws, &feed), CouplingStatus::kBadSnapshot);
  }
  {
    CouplingSnapshot s2 = snap;
    s2.ints[0] = 7;
    EXPECT_EQ(coupling_forces(s2, &fu, ws, &feed), CouplingStatus::kBadSnapshot);
  }
  {
    CouplingSnapshot s2 = snap;   // corrupt a child index
    s2.ints[kHeaderInts + kGrabInts + 2] = 1000;
    EXPECT_EQ(coupling_forces(s2, &fu, ws, &feed), CouplingStatus::kBadSnapshot);
  }
  {
    CouplingSnapshot s2 = snap;
    s2.grabs.push_back(s2.grabs[0]);
    EXPECT_EQ(coupling_forces(s2, &fu, ws, &feed), CouplingStatus::kBadSnapshot);
  }
  EXPECT_THROW(make_coupling_snapshot(*model, d, {Grab{0, Vec3::Zero(), Vec3::Zero()}}, {}, 3, 0, snap),
               std::invalid_argument);
  EXPECT_THROW(make_coupling_snapshot(*model, d, {make_grab(d, 3, Vec3::Zero())}, {fu, fu}, 3, 0, snap),
               std::invalid_argument);
}

TEST(Coupling, SnapshotCarriesHeaderAndGrabData) {
  SceneOptions o;
  o.n = 100;
  o.seed = 6;
  auto model = make_chain(o);
  const State st = random_state(*model, 2);
  Data d(*model);
  forward_dynamics(*model, d, st);
  const Grab g = make_grab(d, 37, Vec3(0.1, 0.2, -0.1));
  CouplingSnapshot snap;
  make_coupling_snapshot(*model, d, {g}, {}, 42, 1.5, snap);
  EXPECT_EQ(snap.model_fingerprint, model->fingerprint);
  EXPECT_EQ(snap.version, 42);
  EXPECT_EQ(snap.sim_time, 1.5);
  ASSERT_EQ(snap.grabs.size(), 1u);
  EXPECT_EQ(snap.ints[0], kSnapshotLayout);
  EXPECT_EQ(snap.ints[2], model->tree.depth[model->tree.leaf_of_body[37]] + 1);   // |U|
  EXPECT_LE((snapshot_grab_offset(snap, 0) - (g.point - d.r[37])).norm(), 1e-15);
  EXPECT_LE((snapshot_grab_rotation(snap, 0) - d.R[37]).norm(), 1e-15);
  EXPECT_LE((snapshot_grab_angular_velocity(snap, 0) - d.v[37].head<3>()).norm(), 1e-15);
  // Point velocity from make_grab = body velocity shifted to the point.
  const Vec3 vp = d.v[37].tail<3>() + d.v[37].head<3>().cross(g.point - d.r[37]);
  EXPECT_LE((g.velocity - vp).norm(), 1e-12 * std::max(1.0, vp.norm()));
  EXPECT_LT(snapshot_payload_bytes(snap), 60u * 1024u);
}

TEST(VirtualCoupling, ThreeDofSpringDamper) {
  VirtualCoupling3 vc{200.0, 3.0};
  const Vec3 xh(1, 2, 3), xs(0.5, 2.5, 3.25), vh(0.1, 0, -0.2), vs(0, 0.3, 0);
  const Vec6 f = vc.user_force(xh, vh, xs, vs);
  EXPECT_TRUE(f.head<3>().isZero());
  EXPECT_LE((f.tail<3>() - (200.0 * (xh - xs) + 3.0 * (vh - vs))).norm(), 1e-12);
  // The damper drags the body along with the hand: a body at rest under a moving hand is pushed
  // the way the hand moves.
  const Vec6 g = vc.user_force(xs, Vec3(1, 0, 0), xs, Vec3::Zero());
  EXPECT_GT(g(3), 0.0);
}

TEST(VirtualCoupling, SixDofRotationalSpring) {
  VirtualCoupling6 vc;
  vc.linear = {100.0, 0.0};
  vc.k_r = 7.0;
  vc.b_r = 0.5;
  const Mat3 Rs = Eigen::AngleAxisd(0.7, Vec3(1, 2, 3).normalized()).toRotationMatrix();
  const Mat3 Rh0 = Eigen::AngleAxisd(-1.1, Vec3(0, 1, 1).normalized()).toRotationMatrix();
  vc.R_grab = Rs.transpose() * Rh0;   // captured at grab time
  const Vec3 x(1, 1, 1), z = Vec3::Zero();
  EXPECT_LE(vc.user_force(x, z, Rh0, z, x, z, Rs, z).norm(), 1e-12);   // aligned: no load
  const Vec3 delta(0.01, -0.02, 0.015);                                 // device turned by δ
  const Mat3 Rh = Eigen::AngleAxisd(delta.norm(), delta.normalized()).toRotationMatrix() * Rh0;
  const Vec3 wh(0.3, 0, 0), ws(0, 0.1, 0);
  const Vec6 f = vc.user_force(x, z, Rh, wh, x, z, Rs, ws);
  EXPECT_LE((f.head<3>() - (7.0 * delta + 0.5 * (wh - ws))).norm(), 1e-12);
  EXPECT_TRUE(f.tail<3>().isZero());
  for (double ang : {1e-9, 0.3, 2.0, 3.14159, M_PI}) {
    const Vec3 axis = Vec3(0.3, -0.5, 0.8).normalized();
    const Vec3 w = rotation_log(Eigen::AngleAxisd(ang, axis).toRotationMatrix());
    EXPECT_NEAR(w.norm(), ang, 1e-9);
    if (ang < 3) {
      EXPECT_LE((w - ang * axis).norm(), 1e-9);
    }
  }
}

TEST(VirtualCoupling, WorkspaceMappingIsTheOnePlaceForUnits) {
  WorkspaceMapping map;
  map.position_scale = 50.0;   // 1 m of device travel = 50 Å
  map.force_scale = 0.02;      // N per scene force unit
  map.torque_scale = 0.001;
  map.time_scale = 2.0;
  map.offset = Vec3(10, -5, 3);
  map.rotation = Eigen::AngleAxisd(0.5, Vec3::UnitZ()).toRotationMatrix();
  const Vec3 xd(0.01, -0.02, 0.03);
  const Vec3 xs = map.device_to_scene_point(xd);
  EXPECT_LE((xs - (map.offset + map.rotation * (50.0 * xd))).norm(), 1e-12);
  EXPECT_LE((map.device_to_scene_velocity(xd) - map.rotation * (25.0 * xd)).norm(), 1e-12);
  const Vec3 f(1, 2, 3);
  const Vec3 fd = map.scene_to_device_force(f);
  EXPECT_LE((map.rotation * fd / 0.02 - f).norm(), 1e-12);   // back to scene axes and units
  EXPECT_LE((map.scene_to_device_torque(f) - 0.001 * map.rotation.transpose() * f).norm(), 1e-12);
}

}  // namespace
}  // namespace haptree
