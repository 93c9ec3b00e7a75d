// passivity_sweep: stiff virtual coupling against the passivity bound b > K·T/2 (Colgate) on the
// virtual hand, closed in one process (tests/stress/coupling_loop.hpp: VirtualHand + coupler_feedback
// + the sim_server step). For every scene, hand damping b and haptic period T it sweeps the coupling
// stiffness K = k_s on a log grid, refines the first stable → unstable transition by bisection, and
// compares the measured limit K_max with 2b/T and with the exact discrete limit of the hand against a
// ZOH spring to a fixed point. --bs-threshold instead finds the coupling damping b_s at which the
// pulled body of the launcher's configuration blows up, against the explicit-integration bound.
//
//   passivity_sweep --csv passivity.csv --png docs/img/passivity_sweep.png
//   passivity_sweep --bs-threshold
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "tests/stress/coupling_loop.hpp"

namespace {

using haptree::stress::CouplingLoopOptions;
using haptree::stress::CouplingLoopResult;
using haptree::stress::run_coupling_loop;

std::vector<std::string> split(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string x;
  while (std::getline(ss, x, ','))
    if (!x.empty()) out.push_back(x);
  return out;
}
std::vector<double> split_d(const std::string& s) {
  std::vector<double> out;
  for (const auto& x : split(s)) out.push_back(std::stod(x));
  return out;
}

struct Row {
  std::string scene, phase;
  double dt_sim, b, T, K;
  CouplingLoopResult r;
};

void csv_row(std::ofstream& f, const Row& w) {
  if (!f) return;
  const auto& r = w.r;
  f << w.scene << ',' << w.phase << ',' << w.dt_sim << ',' << w.b << ',' << w.T << ',' << w.K << ',' << (r.stable ? 1 : 0) << ','
    << (r.finite ? 1 : 0) << ',' << (r.diverged ? 1 : 0) << ',' << r.growth << ',' << r.max_force_n << ','
    << r.max_grab_disp << ',' << r.env_min_energy << ',' << r.damped_min_energy << ',' << r.env_final_energy << ','
    << r.singular_pivots << ',' << r.final_time << '\n';
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"passivity_sweep: coupling stiffness K against the passivity bound K < 2b/T on the virtual hand"};
  std::string scenes = "wall,chain,protein_like", b_list = "2,8,32", T_list = "1e-4,2.5e-4,5e-4,1e-3", dt_list = "1e-3";
  double k_min = 100, k_max = 1e8, per_decade = 4, hold_s = 0.4, pull_m = 0.01;
  int refine = 8, chain_n = 8;
  std::string csv, png, plot_script;
  bool bs_threshold = false;
  std::string bs_scene = "protein_like";
  int bs_n = 64, bs_budget = 48;
  double bs_k = 20, bs_ps = 10, bs_fs = 0.5, bs_dt = 1e-3, bs_max = 1e4, bs_hold = 2.0;
  app.add_option("--scenes", scenes, "wall (grab point on a revolute axis: f_feed = -f_u), chain, protein_like")
      ->capture_default_str();
  app.add_option("--b-n-s-per-m", b_list, "hand damping values b")->capture_default_str();
  app.add_option("--T-s", T_list, "haptic periods T (dt-sim should be a multiple)")->capture_default_str();
  app.add_option("--k-min", k_min, "smallest K on the grid (N/m; scene = device units here)")->capture_default_str();
  app.add_option("--k-max", k_max, "largest K on the grid")->capture_default_str();
  app.add_option("--per-decade", per_decade, "grid points per decade of K")->capture_default_str();
  app.add_option("--refine", refine, "bisection steps on the transition")->capture_default_str();
  app.add_option("--dt-sim-s", dt_list, "simulation steps (list; each a multiple of every T)")->capture_default_str();
  app.add_option("--hold-s", hold_s, "hold time after the pull (growth is measured over it)")->capture_default_str();
  app.add_option("--pull-m", pull_m, "pull distance of the hand target")->capture_default_str();
  app.add_option("--chain-n", chain_n, "bodies of the chain scene (tip is grabbed)")->capture_default_str();
  app.add_option("--csv", csv, "write every run as CSV");
  app.add_option("--png", png, "plot K_max against 2b/T (needs python3 + matplotlib)");
  app.add_option("--plot-script", plot_script, "default: plot_passivity.py next to this source");
  app.add_flag("--bs-threshold", bs_threshold, "find the largest stable coupling damping b_s on the pulled body instead (explicit-step limit)");
  app.add_option("--bs-scene", bs_scene, "scene of --bs-threshold (launcher default)")->capture_default_str();
  app.add_option("--bs-n", bs_n, "n of that scene (launcher default)")->capture_default_str();
  app.add_option("--bs-budget", bs_budget, "adaptive budget (launcher default; 0 = all DOFs)")->capture_default_str();
  app.add_option("--bs-k", bs_k, "k_s, scene units (launcher default)")->capture_default_str();
  app.add_option("--bs-dt", bs_dt, "sim step (launcher default)")->capture_default_str();
  app.add_option("--bs-max", bs_max, "upper end of the damper search")->capture_default_str();
  app.add_option("--bs-hold-s", bs_hold, "hold after the 1 s pull")->capture_default_str();
  CLI11_PARSE(app, argc, argv);

  std::ofstream f;
  if (!csv.empty()) {
    f.open(csv);
    if (!f) {
      spdlog::error("cannot write {}", csv);
      return 1;
    }
    f << "scene,phase,dt_sim,b,T,K,stable,finite,diverged,growth,max_force_n,max_grab_disp,env_min_energy,"
         "damped_min_energy,env_final_energy,singular_pivots,final_time\n";
  }
  const auto t0 = std::chrono::steady_clock::now();
  auto elapsed = [&] { return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(); };

  if (bs_threshold) {
    // The launcher's configuration: scripted device (no hand dynamics), ps 10, fs 0.5, k_s 20, dt 1 ms,
    // gravity on, pull 0.03 m over 1 s, then hold; budget 48 and all DOFs.
    // VirtualCoupling3 computes f_u = k_s (x_h − x_s) + b_s (ẋ_h − ẋ_s): a damper on the relative
    // velocity. The explicit step limits it: b_s·dt/m_eff + k_s·dt²/(2 m_eff) < 2, i.e.
    // b_s < 2 m_eff/dt − k_s dt/2 with m_eff the smallest effective mass at the grab point. Found
    // here by bisection on b_s, for the launcher's budget and with every DOF active.
    std::printf("## Coupling damping b_s on the simulated side (launcher configuration: scripted device, "
                "ps %g, fs %g, k_s %g, dt %g s, gravity on)\n\n", bs_ps, bs_fs, bs_k, bs_dt);
    std::printf("| scene | budget | m_eff,min at the grab (full DCA) | at b_s = 10 m_eff | predicted b* = 2m/dt − k·dt/2 "
                "| measured b* (last stable … first unstable) | b*·dt/m_eff |\n|---|---|---|---|---|---|---|\n");
    for (int budget : {bs_budget, 0}) {
      CouplingLoopOptions o;
      o.scene = bs_scene;
      o.n = bs_n;
      o.gravity = true;
      o.budget_dofs = budget;
      o.k_s = bs_k;
      o.position_scale = bs_ps;
      o.force_scale = bs_fs;
      o.scripted_device = true;
      o.T = 1e-4;
      o.dt_sim = bs_dt;
      o.pull_distance_m = 0.03;
      o.pull_s = 1.0;
      o.hold_s = bs_hold;
      o.diverge_force_n = 1e4;
      o.growth_check = false;   // gravity on: the failure is a blow-up
      auto model = haptree::stress::coupling_loop_model(o);
      const std::string bud = budget > 0 ? std::to_string(budget) : std::string("all");
      o.b_s = 0;
      const CouplingLoopResult base = run_coupling_loop(o, model);
      const double meff = base.m_eff_min;
      o.b_s = 10 * meff;
      const CouplingLoopResult ten = run_coupling_loop(o, model);
      csv_row(f, Row{bs_scene, "bs_10meff_" + bud, bs_dt, 0, o.T, o.b_s, ten});
      double lo = 0, hi = bs_max;
      o.b_s = hi;
      const bool top_stable = run_coupling_loop(o, model).stable;
      if (!top_stable) {
        for (int it = 0; it < 12; ++it) {
          const double mid = lo > 0 ? std::sqrt(lo * hi) : hi / 8;
          o.b_s = mid;
          const CouplingLoopResult r = run_coupling_loop(o, model);
          csv_row(f, Row{bs_scene, "bs_damper_" + bud, bs_dt, 0, o.T, mid, r});
          (r.stable ? lo : hi) = mid;
        }
      }
      std::printf("%s\n", fmt::format("| {} | {} | {:.4g} | {} | {:.4g} | {} | {} |", bs_scene, bud, meff,
                                      ten.stable ? "stable" : fmt::format("unstable at {:.3g} s", ten.final_time),
                                      2 * meff / bs_dt - bs_k * bs_dt / 2,
                                      top_stable ? fmt::format("stable up to {:g}", bs_max)
                                                 : fmt::format("{:.4g} … {:.4g}", lo, hi),
                                      top_stable ? "-" : fmt::format("{:.3f}", std::sqrt(lo * hi) * bs_dt / meff))
                               .c_str());
      std::fflush(stdout);
    }
    std::printf("\n(%.1f s)\n", elapsed());
    return 0;
  }

  const auto scene_list = split(scenes);
  const auto bs = split_d(b_list);
  const auto Ts = split_d(T_list);
  std::vector<double> grid;
  for (double lk = std::log10(k_min); lk <= std::log10(k_max) + 1e-9; lk += 1.0 / per_decade)
    grid.push_back(std::pow(10.0, lk));

  std::printf("## Coupling stiffness K against the passivity bound 2b/T (virtual hand m = 0.2 kg, arm spring "
              "200 N/m, %d hand substeps per T; pull %g m then hold %g s)\n\n",
              CouplingLoopOptions{}.hand_substeps, pull_m, hold_s);
  std::printf("| scene | dt_sim (s) | b (N·s/m) | T (s) | 2b/T (N/m) | exact ZOH-wall limit | measured K_max (last stable … "
              "first unstable) | K_max / (2b/T) | K_max / (2b/dt_sim) | sim-side 4·m_eff/dt² | at K = 2b/T/2: growth, min "
              "E_env (J) | at K = 2·2b/T: stable?, max abs F (N) |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  struct Summary {
    std::string scene;
    double b, T, bound, exact, lo, hi;
  };
  std::vector<Summary> sums;
  for (const auto& scene : scene_list) {
   for (double dt_sim : split_d(dt_list)) {
    CouplingLoopOptions base;
    base.scene = scene;
    base.n = scene == "chain" ? chain_n : 64;
    base.dt_sim = dt_sim;
    base.hold_s = hold_s;
    base.pull_distance_m = pull_m;
    auto model = haptree::stress::coupling_loop_model(base);
    for (double T : Ts) {
      for (double b : bs) {
        CouplingLoopOptions o = base;
        o.T = T;
        o.hand_damping_n_s_per_m = b;
        o.diverge_force_n = 1e3 * std::max(1.0, 1e2 * b / T * pull_m);
        auto run = [&](double K, const char* phase) {
          o.k_s = K;
          Row w{scene, phase, dt_sim, b, T, K, run_coupling_loop(o, model)};
          csv_row(f, w);
          return w.r;
        };
        const double bound = 2 * b / T;
        const double exact =
            haptree::stress::zoh_wall_limit(o.hand_mass_kg, o.hand_stiffness_n_per_m, b, T, o.hand_substeps);
        double lo = 0, hi = 0;
        double meff = 0;
        for (double K : grid) {
          const CouplingLoopResult r = run(K, "grid");
          meff = r.m_eff_min;
          if (r.stable) {
            lo = K;
          } else {
            hi = K;
            break;
          }
        }
        if (hi > 0 && lo > 0) {
          for (int it = 0; it < refine; ++it) {
            const double mid = std::sqrt(lo * hi);
            (run(mid, "refine").stable ? lo : hi) = mid;
          }
        }
        const CouplingLoopResult half = run(bound / 2, "half_bound");
        const CouplingLoopResult twice = run(2 * bound, "twice_bound");
        const double sim_limit = 4 * meff / (dt_sim * dt_sim);
        char kmax[96];
        if (hi == 0) std::snprintf(kmax, sizeof kmax, "> %.3g (none unstable)", lo);
        else if (lo == 0) std::snprintf(kmax, sizeof kmax, "< %.3g", hi);
        else std::snprintf(kmax, sizeof kmax, "%.4g … %.4g", lo, hi);
        const bool both = lo > 0 && hi > 0;
        std::printf("| %s | %g | %g | %g | %.4g | %.4g | %s | %s | %s | %s | %.3g, %.3g | %s, %.3g |\n", scene.c_str(),
                    dt_sim, b, T, bound, exact, kmax, both ? fmt::format("{:.3f}", std::sqrt(lo * hi) / bound).c_str() : "-",
                    both ? fmt::format("{:.2f}", std::sqrt(lo * hi) / (2 * b / dt_sim)).c_str() : "-",
                    std::isfinite(sim_limit) ? fmt::format("{:.3g}", sim_limit).c_str() : "∞ (anchored)", half.growth,
                    half.env_min_energy, twice.stable ? "**stable**" : "unstable", twice.max_force_n);
        std::fflush(stdout);
        sums.push_back({scene, b, T, bound, exact, lo, hi});
      }
    }
   }
    spdlog::info("{} done ({:.1f} s)", scene, elapsed());
  }
  std::printf("\nK_max is the largest K on the grid/bisection whose run stayed finite, bounded and not growing "
              "(kinetic energy of hand + simulated body at most 1.5× over the last 0.1 s of the hold what it was in its first 0.1 s). min E_env is the "
              "passivity observer (haptree::PassivityObserver) at the device port: energy the hand put into "
              "coupling + simulation; negative = energy produced. (%.1f s)\n",
              elapsed());
  if (!png.empty()) {
    if (csv.empty()) {
      spdlog::warn("--png needs --csv: not plotting");
    } else {
      std::string script = plot_script.empty() ? std::string(HAPTREE_TOOLS_DIR) + "/plot_passivity.py" : plot_script;
      const std::string args = " " + script + " " + csv + " --out " + png;
      f.flush();
      int rc = std::system(("python3" + args + " 2>/dev/null").c_str());
      if (rc != 0) rc = std::system(("/usr/bin/python3" + args).c_str());   // a pyenv python3 may lack matplotlib
      const std::string cmd = "python3" + args;
      if (rc != 0) spdlog::warn("plot failed ({}): is python3-matplotlib installed?", cmd);
      else spdlog::info("wrote {}", png);
    }
  }
  return 0;
}
