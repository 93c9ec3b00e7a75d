// adaptive_stress: long adaptive runs that switch ε or the DOF budget k at EVERY step
// (tests/stress/adaptive_switching.hpp), with checks at every step (finite state, no singular pivot,
// budget never exceeded, neglected metric ≤ ε, energy bounded) and the long-double oracle every M
// steps. Progress and timing every ~10 s. With several dt it reports where a run first fails.
//
//   adaptive_stress --steps 100000                       # 857-DOF protein-like tree, dt 1 ms
//   adaptive_stress --scene chain --n 4096 --steps 20000 --oracle-every 0
//   adaptive_stress --dt-list 1e-3,5e-4,2.5e-4 --steps 20000
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "tests/stress/adaptive_switching.hpp"

int main(int argc, char** argv) {
  CLI::App app{"adaptive_stress: adaptive dynamics switching epsilon / budget k every step, checked every step"};
  haptree::stress::SwitchingOptions o;
  o.steps = 100000;
  o.oracle_every = 5000;
  std::string dt_list = "1e-3", csv;
  double progress_s = 10;
  app.add_option("--scene", o.scene, "chain|binary_tree|random_tree|star|protein_like")->capture_default_str();
  app.add_option("--n", o.n, "bodies (protein_like is fixed at 857)")->capture_default_str();
  app.add_option("--steps", o.steps, "steps per run")->capture_default_str();
  app.add_option("--dt-list", dt_list, "time steps (comma list; one run each)")->capture_default_str();
  app.add_option("--schedule", o.schedule, "random (seeded) | cyclic")->capture_default_str();
  app.add_option("--modes", o.modes, "both | budget | threshold")->capture_default_str();
  app.add_option("--seed", o.seed, "schedule seed")->capture_default_str();
  app.add_option("--state-seed", o.state_seed, "random_state seed of the initial angles (q̇ = 0)")->capture_default_str();
  app.add_option("--k-min", o.k_min, "smallest budget k (DOFs)")->capture_default_str();
  app.add_option("--k-max", o.k_max, "largest budget k (DOFs)")->capture_default_str();
  app.add_option("--eps-min", o.eps_min, "smallest ε relative to the total metric")->capture_default_str();
  app.add_option("--eps-max", o.eps_max, "largest ε relative to the total metric")->capture_default_str();
  app.add_option("--oracle-every", o.oracle_every, "steps between oracle comparisons (0: never)")->capture_default_str();
  app.add_option("--energy-gain-limit", o.energy_gain_limit,
                 "blow-up when E - E0 exceeds this times 2·M·|g|·(total link length)")->capture_default_str();
  app.add_option("--progress-s", progress_s, "seconds between progress lines")->capture_default_str();
  bool no_gravity = false;
  app.add_flag("--no-gravity", no_gravity, "switch gravity off");
  app.add_option("--csv", csv, "one row per run");
  CLI11_PARSE(app, argc, argv);
  o.gravity = !no_gravity;

  std::vector<double> dts;
  {
    std::stringstream ss(dt_list);
    std::string x;
    while (std::getline(ss, x, ','))
      if (!x.empty()) dts.push_back(std::stod(x));
  }
  auto model = haptree::stress::switching_model(o);
  spdlog::info("adaptive_stress: {} ({} bodies, {} DOF), {} steps per run, schedule {} ({}), k {}..{}, eps {}..{} "
               "(rel.), oracle every {} steps",
               o.scene, model->nbodies - 1, model->nv, o.steps, o.schedule, o.modes, o.k_min, o.k_max, o.eps_min,
               o.eps_max, o.oracle_every);
  using Clock = std::chrono::steady_clock;
  std::ofstream f;
  if (!csv.empty()) {
    f.open(csv);
    f << "scene,dof,dt,steps_requested,steps_done,first_failure_step,failure,selections,budget_steps,threshold_steps,"
         "budget_violations,threshold_violations,singular_pivots,nonfinite_qdd,min_active,max_active,e0,"
         "energy_scale,max_energy_gain,max_energy_loss,max_ke,oracle_checks,worst_oracle_err,wall_s,ms_per_step\n";
  }
  std::printf("| scene | DOF | dt (s) | steps done | first failure | selections | active DOF min…max | budget "
              "violations | ε violations | singular pivots | max (E−E0)/scale | max KE | oracle checks | worst "
              "oracle rel. err | ms/step |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  for (double dt : dts) {
    o.dt = dt;
    const auto t0 = Clock::now();
    auto next = t0 + std::chrono::duration<double>(progress_s);
    o.progress = [&](std::int64_t s, const haptree::stress::SwitchingResult& r) {
      if ((s & 63) != 0) return;
      const auto now = Clock::now();
      if (now < next) return;
      next = now + std::chrono::duration<double>(progress_s);
      const double el = std::chrono::duration<double>(now - t0).count();
      spdlog::info("dt {}: step {} / {} ({:.1f} s, {:.2f} ms/step), active {}..{}, max (E-E0)/scale {:.3g}, oracle "
                   "worst {:.2e} ({} checks)",
                   dt, s + 1, o.steps, el, 1e3 * el / (s + 1), r.min_active, r.max_active,
                   r.max_energy_gain / r.energy_scale, r.worst_oracle_err, r.oracle_checks);
    };
    const auto r = haptree::stress::run_adaptive_switching(o, model);
    const double wall = std::chrono::duration<double>(Clock::now() - t0).count();
    const std::string fail =
        r.first_failure_step < 0 ? std::string("none") : r.failure + " at step " + std::to_string(r.first_failure_step) +
                                                             " (t = " + fmt::format("{:.4g}", r.sim_time) + " s)";
    std::printf("| %s | %d | %g | %lld | %s | %lld | %d…%d | %lld | %lld | %lld | %.3g | %.3g | %d | %.2e | %.3f |\n",
                o.scene.c_str(), model->nv, dt, static_cast<long long>(r.steps_done), fail.c_str(),
                static_cast<long long>(r.selections), r.min_active, r.max_active,
                static_cast<long long>(r.budget_violations), static_cast<long long>(r.threshold_violations),
                static_cast<long long>(r.singular_pivots), r.max_energy_gain / r.energy_scale, r.max_ke,
                r.oracle_checks, r.worst_oracle_err, 1e3 * wall / std::max<std::int64_t>(1, r.steps_done));
    std::fflush(stdout);
    if (f) {
      f << o.scene << ',' << model->nv << ',' << dt << ',' << o.steps << ',' << r.steps_done << ','
        << r.first_failure_step << ',' << '"' << r.failure << '"' << ',' << r.selections << ',' << r.budget_steps << ','
        << r.threshold_steps << ',' << r.budget_violations << ',' << r.threshold_violations << ','
        << r.singular_pivots << ',' << r.nonfinite_qdd << ',' << r.min_active << ',' << r.max_active << ',' << r.e0
        << ',' << r.energy_scale << ',' << r.max_energy_gain << ',' << r.max_energy_loss << ',' << r.max_ke << ','
        << r.oracle_checks << ',' << r.worst_oracle_err << ',' << wall << ','
        << 1e3 * wall / std::max<std::int64_t>(1, r.steps_done) << '\n';
    }
  }
  return 0;
}
