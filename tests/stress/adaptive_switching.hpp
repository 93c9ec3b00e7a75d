// Long adaptive runs that switch ε or the DOF budget k at every step (stress suite), shared
// by tests/stress/adaptive_switching_test.cpp (smoke, 2000 steps) and tools/adaptive_stress.cpp
// (1e5 steps, progress, limits). Every step: adaptive_step with a new AdaptiveOptions (so every step
// reselects), then the checks: finite q and q̇, no new singular pivot / non-finite q̈ (Data::diag),
// budget never exceeded (budget mode) and neglected metric ≤ ε (threshold mode), total energy
// bounded. Every `oracle_every` steps the hybrid q̈ of the current region is compared with the
// long-double oracle with the inactive DOFs removed (tests/support/oracle.hpp).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "haptree/adaptive.hpp"
#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"
#include "tests/support/oracle.hpp"

namespace haptree::stress {

struct SwitchingOptions {
  std::string scene = "protein_like";   // any make_scene name
  int n = 857;                          // bodies of chain / trees (protein_like is fixed)
  bool gravity = true;
  unsigned state_seed = 11;             // random_state(seed) angles, q̇ = 0 (as the energy-drift runs)
  double dt = 1e-3;
  std::int64_t steps = 2000;
  std::string schedule = "random";      // random (seeded) | cyclic
  std::string modes = "both";           // both (mode also switches) | budget | threshold
  unsigned seed = 1;
  int k_min = 8, k_max = 512;           // budget range (DOFs)
  double eps_min = 1e-8, eps_max = 1e-1;   // ε relative to the total metric of the last selection
  std::int64_t oracle_every = 1000;     // 0: never
  double energy_gain_limit = 1.0;       // stop (blow-up) when E − E0 > limit × energy_scale
  std::function<void(std::int64_t step, const struct SwitchingResult&)> progress;   // optional, each step
};

struct SwitchingResult {
  std::int64_t steps_done = 0;
  std::int64_t first_failure_step = -1;   // -1: none
  std::string failure;                    // what failed first
  std::int64_t selections = 0;            // selections performed (= steps when every step switches)
  std::int64_t budget_steps = 0, threshold_steps = 0;
  std::int64_t budget_violations = 0;     // active DOFs > k
  std::int64_t threshold_violations = 0;  // neglected metric > ε (selection's own report)
  std::int64_t nonfinite_steps = 0;
  std::int64_t singular_pivots = 0, nonfinite_qdd = 0;   // Data::diag increments over the run
  int min_active = std::numeric_limits<int>::max(), max_active = 0;
  double e0 = 0;                          // initial total energy (KE + gravity PE)
  double energy_scale = 0;                // 2·M·|g|·Σ|d_k| (+1): bounds any gravity-PE swing
  double max_energy_gain = 0;             // max (E − E0)
  double max_energy_loss = 0;             // max (E0 − E) (locking dissipates)
  double max_ke = 0;
  double worst_oracle_err = 0;            // max rel. error of hybrid q̈ vs oracle (DOFs removed)
  double worst_oracle_ratio = 0;          // max of that error / its bound B (≤ 1 expected)
  int oracle_checks = 0;
  double sim_time = 0;
};

inline std::shared_ptr<const Model> switching_model(const SwitchingOptions& o) {
  SceneOptions so;
  so.n = o.n;
  auto m = std::make_shared<Model>(*make_scene(o.scene, so));
  if (!o.gravity) m->gravity = Vec3::Zero();
  return m;
}

// Runs the switching schedule; stops at the first failed check (recorded, not thrown).
inline SwitchingResult run_adaptive_switching(const SwitchingOptions& o, std::shared_ptr<const Model> model = nullptr) {
  if (!model) model = switching_model(o);
  const Model& m = *model;
  SwitchingResult r;
  State st = testing::random_state(m, o.state_seed);
  st.qd.setZero();
  st.tau.setZero();
  for (auto& f : st.f_ext) f.setZero();
  Data d(m), de(m);
  AdaptiveData ad(m);
  auto energy = [&](double* ke) {
    forward_kinematics(m, de, st.q);
    body_dynamics_terms(m, de, st);
    *ke = kinetic_energy(m, de);
    return *ke + potential_energy(m, de);
  };
  double ke = 0;
  r.e0 = energy(&ke);
  {
    double M = 0, L = 0;
    for (int k = 1; k < m.nbodies; ++k) {
      M += m.mass[k];
      L += de.d[k].norm();
    }
    r.energy_scale = 2 * M * m.gravity.norm() * L + ke + 1;
  }
  std::mt19937_64 rng(o.seed);
  std::uniform_real_distribution<double> u01(0, 1);
  const int kmax = std::min(o.k_max, m.nv);
  const int kmin = std::max(1, std::min(o.k_min, kmax));
  // Cyclic schedule: k doubling from k_min to k_max and back, ε by decades; modes alternate.
  std::vector<int> ks;
  for (int k = kmin; k < kmax; k *= 2) ks.push_back(k);
  ks.push_back(kmax);
  for (int i = static_cast<int>(ks.size()) - 2; i > 0; --i) ks.push_back(ks[i]);
  std::vector<double> eps;
  for (double e = o.eps_max; e >= o.eps_min * 0.999; e /= 10) eps.push_back(e);
  for (int i = static_cast<int>(eps.size()) - 2; i > 0; --i) eps.push_back(eps[i]);
  const std::int64_t piv0 = d.diag.singular_pivots, nf0 = d.diag.nonfinite;
  double total_metric = 0;
  AdaptiveOptions opt;
  opt.reselect_every = std::numeric_limits<int>::max();   // reselection comes from the option changes
  for (std::int64_t s = 0; s < o.steps; ++s) {
    // 1. New options (always different from the previous step's, so adaptive_step reselects).
    bool budget_mode = o.modes == "budget" || (o.modes == "both" && (o.schedule == "cyclic" ? s % 2 == 0 : u01(rng) < 0.5));
    if (o.modes == "threshold") budget_mode = false;
    const AdaptiveOptions prev = opt;
    if (budget_mode) {
      opt.mode = AdaptiveOptions::Mode::kBudget;
      if (o.schedule == "cyclic") {
        opt.budget = ks[static_cast<std::size_t>(s / (o.modes == "both" ? 2 : 1)) % ks.size()];
      } else {
        opt.budget = static_cast<int>(std::lround(std::exp(std::log(kmin) + u01(rng) * (std::log(kmax) - std::log(kmin)))));
      }
      if (prev.mode == opt.mode && prev.budget == opt.budget) opt.budget = opt.budget > kmin ? opt.budget - 1 : opt.budget + 1;
    } else {
      opt.mode = AdaptiveOptions::Mode::kThreshold;
      double rel;
      if (o.schedule == "cyclic") {
        rel = eps[static_cast<std::size_t>(s / (o.modes == "both" ? 2 : 1)) % eps.size()];
      } else {
        rel = std::exp(std::log(o.eps_min) + u01(rng) * (std::log(o.eps_max) - std::log(o.eps_min)));
      }
      opt.epsilon = rel * std::max(total_metric, 1e-300);
      if (prev.mode == opt.mode && prev.epsilon == opt.epsilon) opt.epsilon *= 1.5;
      if (!(opt.epsilon > 0)) opt.epsilon = 1e-300;
    }
    // 2. Step.
    const AdaptiveReport& rep = adaptive_step(m, d, st, ad, opt, o.dt);
    ++r.steps_done;
    r.sim_time = st.t;
    if (rep.reselected) ++r.selections;
    total_metric = rep.total_metric;
    r.min_active = std::min(r.min_active, rep.active_dofs);
    r.max_active = std::max(r.max_active, rep.active_dofs);
    auto fail = [&](const std::string& what) {
      if (r.first_failure_step < 0) {
        r.first_failure_step = s;
        r.failure = what;
      }
    };
    // 3. Checks.
    if (budget_mode) {
      ++r.budget_steps;
      if (rep.active_dofs > opt.budget) {
        ++r.budget_violations;
        fail("budget exceeded");
      }
    } else {
      ++r.threshold_steps;
      if (rep.neglected_metric > opt.epsilon * (1 + 1e-12) + 1e-300) {
        ++r.threshold_violations;
        fail("neglected metric above epsilon");
      }
    }
    if (!st.q.allFinite() || !st.qd.allFinite()) {
      ++r.nonfinite_steps;
      fail("non-finite state");
    }
    if (d.diag.singular_pivots != piv0 + r.singular_pivots) {
      r.singular_pivots = d.diag.singular_pivots - piv0;
      fail("singular pivot");
    }
    if (d.diag.nonfinite != nf0 + r.nonfinite_qdd) {
      r.nonfinite_qdd = d.diag.nonfinite - nf0;
      fail("non-finite qdd");
    }
    const double e = energy(&ke);
    r.max_ke = std::max(r.max_ke, std::isfinite(ke) ? ke : r.max_ke);
    if (std::isfinite(e)) {
      r.max_energy_gain = std::max(r.max_energy_gain, e - r.e0);
      r.max_energy_loss = std::max(r.max_energy_loss, r.e0 - e);
    }
    if (!std::isfinite(e) || e - r.e0 > o.energy_gain_limit * r.energy_scale) fail("energy blow-up");
    // 4. Oracle on the current region (q̇ of inactive joints is 0 after the impulsive lock).
    if (r.first_failure_step < 0 && o.oracle_every > 0 && (s + 1) % o.oracle_every == 0) {
      const Eigen::VectorXd qa = adaptive_forward_dynamics(m, d, st, ad);
      std::vector<bool> locked(m.nv, true);
      for (int J : ad.active_joints)
        for (int i = 0; i < m.v_num[J]; ++i) locked[m.v_adr[J] + i] = false;
      const auto ref = testing::oracle_forward_dynamics(m, st, locked);
      const double err = testing::rel_err(qa, ref.qdd);
      r.worst_oracle_err = std::max(r.worst_oracle_err, err);
      // Error bound: B of the reduced system (free DOFs, κ(H_aa), its cancellation)
      // scaled to the full model's n and κ(H): the hybrid pass builds the reduced system from all
      // bodies (docs/accuracy_and_stability.md, "Tolerances from error analysis").
      // (ref.H is the full mass matrix; only the solve is reduced.)
      const double B = testing::qdd_error_bound(ref, st, testing::kBoundC, locked) * m.nv /
                       std::max<double>(std::count(locked.begin(), locked.end(), false), 1) * testing::mass_matrix_condition(ref) /
                       testing::mass_matrix_condition(ref, locked);
      r.worst_oracle_ratio = std::max(r.worst_oracle_ratio, err / B);
      ++r.oracle_checks;
    }
    if (o.progress) o.progress(s, r);
    if (r.first_failure_step >= 0) break;
  }
  if (r.min_active == std::numeric_limits<int>::max()) r.min_active = 0;
  return r;
}

}  // namespace haptree::stress
