// adaptive_sweep: run time against error for the adaptive (hybrid) articulated-body dynamics.
//
// For each scene it simulates a fixed simulated time twice from the same initial state: once with
// full DCA (forward_dynamics + integrate) and once per setting with adaptive_step (budget k active
// DOFs, or threshold ε relative to the total acceleration metric of the initial state), same dt,
// same loads. Per setting it records the step time (thread CPU and wall, median and mean), the
// speed-up against full DCA, the neglected metric (the error estimate), the trajectory deviation from
// the full run at the end (RMS over q, max body-origin distance), active DOFs, nodes visited and the
// energy difference against the full run (the V1 velocity policy — inactive joints have q̇ = 0 —
// removes kinetic energy when a moving joint is deactivated; docs/algorithms.md §10.3).
//
//   adaptive_sweep --scenes chain4096,protein_like,bacteriorhodopsin,ala20 --csv sweep.csv
//   adaptive_sweep --smoke      (small and fast, for CTest)
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <functional>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "haptree/adaptive.hpp"
#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"
#ifdef HAPTREE_SWEEP_MOLECULES
#include "haptree/molecule/scene.hpp"
#endif

namespace {

using namespace haptree;
using Clock = std::chrono::steady_clock;

double cpu_us() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e6 + ts.tv_nsec * 1e-3;
}
double wall_us() {
  return std::chrono::duration<double, std::micro>(Clock::now().time_since_epoch()).count();
}
double median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}
double percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0;
  const size_t i = std::min(v.size() - 1, static_cast<size_t>(p * v.size()));
  std::nth_element(v.begin(), v.begin() + i, v.end());
  return v[i];
}
double mean(const std::vector<double>& v) {
  double s = 0;
  for (double x : v) s += x;
  return v.empty() ? 0 : s / v.size();
}

// A scene: the model plus how loads are applied each step (gravity is in the model).
struct Scene {
  std::string name, length_unit, energy_unit, time_unit;
  std::shared_ptr<const Model> model;
  double dt = 1e-3;
  int steps = 100;
  // Overwrites f_ext from the current poses in `d` and returns the potential energy of the loads
  // that have one (force field; 0 for robots, whose gravity potential is potential_energy()).
  std::function<double(const Data&, std::vector<Vec6>&)> loads;
  bool molecular = false;
#ifdef HAPTREE_SWEEP_MOLECULES
  std::shared_ptr<mol::MolecularScene> mol;
#endif
};

struct Setting {
  AdaptiveOptions::Mode mode;
  int budget = 0;
  double eps_rel = 0;   // threshold mode: ε / total metric of the initial state
  std::string label;
};

struct Result {
  std::vector<double> cpu, wall, ff_cpu;   // per step (µs), after warm-up
  std::vector<double> neglected, total, active, nodes;
  int active_max = 0;
  std::int64_t selections = 0;
  std::vector<double> sel_cpu;          // CPU µs of the steps that selected
  std::vector<double> sel_nodes_full;   // nodes assembled in full per selection (incremental metric)
  double check_max = 0;   // largest exact neglected metric of a region when it was replaced
  double v1_jump = 0;   // Σ over selections of KE(q̇ with the new inactive joints zeroed) − KE(q̇)
  Eigen::VectorXd q, qd;
  double energy = 0;
  bool finite = true;
};

// Total energy of a state: kinetic + gravity potential (+ force-field energy for molecules).
double total_energy(const Scene& sc, const State& st) {
  const Model& m = *sc.model;
  Data d(m);
  State s2 = st;
  forward_kinematics(m, d, s2.q);
  body_dynamics_terms(m, d, s2);
  double e = kinetic_energy(m, d) + potential_energy(m, d);
  if (sc.molecular) {
    std::vector<Vec6> f(m.nbodies, Vec6::Zero());
    e += sc.loads(d, f);   // the pull is not a potential: loads() returns the force-field energy
  }
  return e;
}

Result run_full(const Scene& sc, const State& init, int warmup, Refinement refine) {
  const Model& m = *sc.model;
  State st = init;
  Data d(m);
  set_refinement(m, d, refine);
  Result r;
  for (int s = 0; s < sc.steps; ++s) {
    const double w0 = wall_us(), c0 = cpu_us();
    forward_kinematics(m, d, st.q);
    sc.loads(d, st.f_ext);
    const double cf = cpu_us();
    forward_dynamics(m, d, st);
    integrate(m, st.q, st.qd, d.qdd, sc.dt);
    const double c1 = cpu_us(), w1 = wall_us();
    if (s >= warmup) {
      r.cpu.push_back(c1 - cf);   // dynamics + integration (kinematics is part of forward_dynamics)
      r.wall.push_back(w1 - w0);
      r.ff_cpu.push_back(cf - c0);
      r.nodes.push_back(double(d.diag.nodes_bottom_up + d.diag.nodes_top_down));
    }
  }
  r.q = st.q;
  r.qd = st.qd;
  r.finite = st.q.allFinite() && st.qd.allFinite();
  r.energy = total_energy(sc, st);
  r.active_max = m.nv;
  return r;
}

Result run_adaptive(const Scene& sc, const State& init, const AdaptiveOptions& ao, int warmup,
                    bool fresh_poses) {
  const Model& m = *sc.model;
  State st = init;
  Data d(m);
  AdaptiveData ad(m);
  Result r;
  forward_kinematics(m, d, st.q);
  Data dk(m);   // untimed: kinetic energy before/after the V1 zeroing at each selection
  State pre = st;
  auto kinetic = [&](const State& x) {
    forward_kinematics(m, dk, x.q);
    body_dynamics_terms(m, dk, x);
    return kinetic_energy(m, dk);
  };
  for (int s = 0; s < sc.steps; ++s) {
    pre.q = st.q;
    pre.qd = st.qd;
    const double w0 = wall_us(), c0 = cpu_us();
    // Poses of bodies inside rigid regions (needed by the loads); the first step has full poses.
    if (fresh_poses) forward_kinematics(m, d, st.q);   // diagnostic: O(n) poses of the current q
    else if (s > 0) update_all_body_poses(m, d, ad);
    sc.loads(d, st.f_ext);
    const double cf = cpu_us();
    const AdaptiveReport& rep = adaptive_step(m, d, st, ad, ao, sc.dt);
    const double c1 = cpu_us(), w1 = wall_us();
    if (s >= warmup) {
      r.cpu.push_back(c1 - cf);
      r.wall.push_back(w1 - w0);
      r.ff_cpu.push_back(cf - c0);
      r.nodes.push_back(double(rep.nodes_bottom_up + rep.nodes_top_down));
    }
    if (rep.reselected) {
      if (s >= warmup) r.sel_cpu.push_back(c1 - cf);
      r.sel_nodes_full.push_back(double(rep.metric_nodes_full));
      r.check_max = std::max(r.check_max, rep.check_exact);
      const double ke0 = kinetic(pre);
      Eigen::VectorXd keep = Eigen::VectorXd::Zero(m.nv);
      for (int J : ad.active_joints) keep.segment(m.v_adr[J], m.v_num[J]).setOnes();
      pre.qd = pre.qd.cwiseProduct(keep);
      r.v1_jump += kinetic(pre) - ke0;
    }
    r.neglected.push_back(rep.neglected_metric);
    r.total.push_back(rep.total_metric);
    r.active.push_back(rep.active_dofs);
    r.active_max = std::max(r.active_max, rep.active_dofs);
  }
  r.selections = ad.report.selections;
  r.q = st.q;
  r.qd = st.qd;
  r.finite = st.q.allFinite() && st.qd.allFinite();
  r.energy = total_energy(sc, st);
  return r;
}

// Max distance between body origins of two configurations.
double max_body_deviation(const Model& m, const Eigen::VectorXd& qa, const Eigen::VectorXd& qb) {
  Data da(m), db(m);
  forward_kinematics(m, da, qa);
  forward_kinematics(m, db, qb);
  double mx = 0;
  for (int k = 1; k < m.nbodies; ++k) mx = std::max(mx, (da.r[k] - db.r[k]).norm());
  return mx;
}

std::vector<std::string> split(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string x;
  while (std::getline(ss, x, ','))
    if (!x.empty()) out.push_back(x);
  return out;
}

struct Config {
  int robot_steps = 100, mol_steps = 40, warmup = 2, reselect_every = 0;
  bool exact_metric = false;   // every selection recomputes every node's coefficients in full
  double robot_dt_s = 1e-3, mol_dt_ps = 0.0005, pull_n = 5.0, pull_kjmolnm = 1000.0;
  double init_qd_rad_s = 0.0;
  double gravity_z = -9.81;   // robot scenes (m/s²)
  unsigned seed = 1;
  int chain_n = 4096;
  bool fresh_poses = false;
  Refinement full_refine = Refinement::kDouble;   // the full-DCA reference's Data::refine
};

Scene make_robot_scene(const std::string& name, const Config& c) {
  Scene sc;
  sc.name = name;
  sc.length_unit = "m";
  sc.energy_unit = "J";
  sc.time_unit = "s";
  SceneOptions o;
  o.seed = c.seed;
  o.gravity = Vec3(0, 0, c.gravity_z);
  if (name.rfind("chain", 0) == 0) {
    o.n = name.size() > 5 ? std::stoi(name.substr(5)) : c.chain_n;
    sc.model = make_chain(o);
  } else if (name.rfind("binary_tree", 0) == 0) {
    o.n = name.size() > 11 ? std::stoi(name.substr(11)) : 4095;
    sc.model = make_binary_tree(o);
  } else if (name == "protein_like") {
    sc.model = make_protein_like(o);
  } else {
    throw std::runtime_error("adaptive_sweep: unknown scene '" + name + "'");
  }
  sc.dt = c.robot_dt_s;
  sc.steps = c.robot_steps;
  const int tip = sc.model->nbodies - 1;
  const double pull = c.pull_n;
  // A user's pull: constant force along +y on the last body (at its origin).
  sc.loads = [tip, pull](const Data&, std::vector<Vec6>& f) {
    std::fill(f.begin(), f.end(), Vec6::Zero());
    f[tip](4) = pull;
    return 0.0;
  };
  return sc;
}

#ifdef HAPTREE_SWEEP_MOLECULES
Scene make_molecule_scene(const std::string& name, const Config& c) {
  Scene sc;
  sc.name = name;
  sc.length_unit = "nm";
  sc.energy_unit = "kJ/mol";
  sc.time_unit = "ps";
  sc.molecular = true;
  sc.mol = std::make_shared<mol::MolecularScene>(mol::load_molecular_scene(name));
  sc.model = sc.mol->model;
  sc.dt = c.mol_dt_ps;
  sc.steps = c.mol_steps;
  const int atom = sc.mol->natoms() / 2;
  const double pull = c.pull_kjmolnm;
  auto ms = sc.mol;
  // Force field, then a user's pull on the middle atom along +x (add_atom_force after compute).
  sc.loads = [ms, atom, pull](const Data& d, std::vector<Vec6>& f) {
    const double E = ms->compute(d, f);
    ms->add_atom_force(d, atom, Vec3(pull, 0, 0), f);
    return E;
  };
  return sc;
}
#endif

Scene make_any_scene(const std::string& name, const Config& c) {
  if (name.rfind("chain", 0) == 0 || name.rfind("binary_tree", 0) == 0 || name == "protein_like")
    return make_robot_scene(name, c);
#ifdef HAPTREE_SWEEP_MOLECULES
  return make_molecule_scene(name, c);
#else
  throw std::runtime_error("adaptive_sweep: molecular scene '" + name +
                           "' needs haptree_molecule (not built)");
#endif
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "adaptive_sweep: run time against error of adaptive articulated-body dynamics.\n"
      "For every scene, a reference run with full DCA and one adaptive run per setting (DOF budget k,\n"
      "or threshold eps relative to the total acceleration metric of the initial state) simulate the\n"
      "same fixed time from the same state with the same dt and loads (robots: gravity + a constant\n"
      "pull on the last body, from rest; molecules: ff14SB force field + a pull on the middle atom).\n"
      "Recorded per setting: step time (thread CPU, median/mean, us; dynamics + integration only,\n"
      "loads timed separately), speed-up vs full DCA, neglected metric (error estimate, mean/max),\n"
      "RMS q deviation and max body-origin deviation from the full run at the end, active DOFs,\n"
      "nodes visited per hybrid pass, total energy minus the full run's, and the sum over selections\n"
      "of the kinetic-energy jumps that plain zeroing of q̇ would make (the policy locks impulsively instead).\n"
      "Scenes: chain<N> (chain4096), protein_like (857 DOF), and molecule names/paths\n"
      "(bacteriorhodopsin, ala20, ...). Writes CSV and a Markdown table on stdout."};
  std::string scenes = "chain4096,protein_like,bacteriorhodopsin,ala20";
  std::string budgets = "8,16,32,48,96,192,384,all";
  std::string eps_rels = "1e-1,1e-2,1e-3,1e-4,1e-6";
  std::string csv_path = "adaptive_sweep.csv";
  Config c;
  bool smoke = false;
  app.add_option("--scenes", scenes, "comma-separated scenes")->capture_default_str();
  app.add_option("--budgets", budgets, "DOF budgets k ('all' = every DOF)")->capture_default_str();
  app.add_option("--eps-rel", eps_rels,
                 "thresholds eps as fractions of the initial total metric (empty: none)")
      ->capture_default_str();
  app.add_option("--robot-steps", c.robot_steps, "steps per run, robot scenes")->capture_default_str();
  app.add_option("--robot-dt-s", c.robot_dt_s, "time step of robot scenes (s)")->capture_default_str();
  app.add_option("--mol-steps", c.mol_steps, "steps per run, molecular scenes")->capture_default_str();
  app.add_option("--mol-dt-ps", c.mol_dt_ps, "time step of molecular scenes (ps)")->capture_default_str();
  app.add_option("--pull-n", c.pull_n, "pull on the last body of robot scenes (N, +y)")
      ->capture_default_str();
  app.add_option("--gravity-z", c.gravity_z, "gravity of robot scenes along z (m/s²; 0 = a pull only)")
      ->capture_default_str();
  app.add_option("--pull-kjmolnm", c.pull_kjmolnm, "pull on the middle atom of molecules (kJ/mol/nm, +x)")
      ->capture_default_str();
  app.add_option("--init-qd-rad-s", c.init_qd_rad_s,
                 "random initial joint velocities, uniform in ±this (rad/s or rad/ps); 0 = at rest")
      ->capture_default_str();
  app.add_option("--seed", c.seed, "seed of random link geometry and initial velocities")
      ->capture_default_str();
  app.add_option("--reselect-every", c.reselect_every,
                 "steps between active-region selections (0 = the library default: error-controlled)")
      ->capture_default_str();
  std::string full_refine = "double";
  app.add_option("--full-refine", full_refine,
                 "refinement of the full-DCA reference (Data::refine): double (the library default), "
                 "off (one pass, 1.2-1.3x faster: the stricter speed-up), extended")
      ->check(CLI::IsMember({"off", "double", "extended"}))
      ->capture_default_str();
  app.add_flag("--exact-metric", c.exact_metric,
               "every selection assembles every node in full (AdaptiveOptions::incremental_metric = "
               "false; the default reuses the cached Φ, W, Ψ of nodes with no moved joint)");
  app.add_option("--warmup", c.warmup, "first steps of each run not timed")->capture_default_str();
  app.add_flag("--fresh-poses", c.fresh_poses,
               "adaptive runs: forward_kinematics of the current q before the loads instead of "
               "update_all_body_poses (diagnostic; the loads then see the integrated q)");
  app.add_option("--csv", csv_path, "CSV output path")->capture_default_str();
  app.add_flag("--smoke", smoke,
               "small fast run (chain256 + protein_like, 20 steps, k = 8,48,all, one eps) that "
               "fails on non-finite states or a budget overrun");
  CLI11_PARSE(app, argc, argv);
  c.full_refine = full_refine == "off" ? Refinement::kOff : full_refine == "extended" ? Refinement::kExtended : Refinement::kDouble;
  if (smoke) {
    scenes = "chain256,protein_like";
    budgets = "8,48,all";
    eps_rels = "1e-3";
    c.robot_steps = 20;
  }

  std::string cmd;
  for (int i = 0; i < argc; ++i) cmd += (i ? " " : "") + std::string(argv[i]);
  std::printf("command: %s\n\n", cmd.c_str());

  std::ofstream csv(csv_path);
  if (!csv) {
    std::fprintf(stderr, "adaptive_sweep: cannot write %s\n", csv_path.c_str());
    return 2;
  }
  csv << "scene,dof,mode,setting,budget,epsilon,eps_rel,steps,dt,sim_time,length_unit,energy_unit,"
         "full_cpu_us_median,full_cpu_us_mean,cpu_us_median,cpu_us_mean,wall_us_median,"
         "speedup_median,speedup_mean,loads_cpu_us_median,whole_speedup_median,"
         "active_dofs_mean,active_dofs_max,nodes_visited_mean,full_nodes_visited,"
         "neglected_mean,neglected_max,total_metric_mean,neglected_rel_mean,rms_q_dev,"
         "max_body_dev,energy_full,energy_adaptive,energy_diff,energy_initial,finite,v1_ke_jump_sum,"
         "selections,check_max,cpu_us_p90,selection_step_cpu_us_mean,metric_nodes_full_mean\n";
  std::printf("| scene | DOF | setting | active DOF (mean/max) | step µs CPU (median / mean) | "
              "full DCA µs (median / mean) | speed-up (median / mean) | selections | nodes visited | "
              "neglected metric (mean / max) | at replacement (max) | rel. to total | RMS q dev | "
              "max body dev | E − E_full | KE jump if q̇ were zeroed | selecting step µs (mean) | "
              "nodes in full per selection |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  std::fflush(stdout);

  bool ok = true;
  for (const std::string& name : split(scenes)) {
    Scene sc;
    try {
      sc = make_any_scene(name, c);
    } catch (const std::exception& e) {
      std::fprintf(stderr, "adaptive_sweep: scene %s skipped: %s\n", name.c_str(), e.what());
      ok = false;
      continue;
    }
    const Model& m = *sc.model;
    State init(m);
    if (c.init_qd_rad_s > 0) {
      std::srand(c.seed);
      for (int i = 0; i < m.nv; ++i)
        init.qd[i] = c.init_qd_rad_s * (2.0 * std::rand() / RAND_MAX - 1.0);
    }
    std::fprintf(stderr, "[%s] %d DOF, %d steps of %g %s: full DCA reference (refinement %s)...\n",
                 name.c_str(), m.nv, sc.steps, sc.dt, sc.time_unit.c_str(), full_refine.c_str());
    const double E0 = total_energy(sc, init);
    const Result full = run_full(sc, init, c.warmup, c.full_refine);
    const double full_med = median(full.cpu), full_mean = mean(full.cpu);
    const double full_loads = median(full.ff_cpu);
    // Total metric of the initial state (with the initial loads) for the relative thresholds.
    double total0 = 0;
    {
      State s0 = init;
      Data d0(m);
      AdaptiveData a0(m);
      forward_kinematics(m, d0, s0.q);
      sc.loads(d0, s0.f_ext);
      AdaptiveOptions o;
      o.mode = AdaptiveOptions::Mode::kBudget;
      o.budget = m.nv;
      select_active_region(m, d0, s0, a0, o);
      total0 = a0.report.total_metric;
    }
    std::vector<Setting> settings;
    for (const std::string& b : split(budgets)) {
      const int k = b == "all" ? m.nv : std::stoi(b);
      if (k > m.nv && b != "all") continue;
      settings.push_back({AdaptiveOptions::Mode::kBudget, k, 0, "k=" + b});
    }
    for (const std::string& e : split(eps_rels))
      settings.push_back({AdaptiveOptions::Mode::kThreshold, 0, std::stod(e), "eps=" + e});

    for (size_t i = 0; i < settings.size(); ++i) {
      const Setting& st = settings[i];
      std::fprintf(stderr, "[%s] setting %zu/%zu %s\n", name.c_str(), i + 1, settings.size(),
                   st.label.c_str());
      AdaptiveOptions ao;
      ao.mode = st.mode;
      ao.budget = st.budget;
      ao.epsilon = st.eps_rel * total0;
      ao.reselect_every = c.reselect_every;
      ao.incremental_metric = !c.exact_metric;
      const Result r = run_adaptive(sc, init, ao, c.warmup, c.fresh_poses);
      const double med = median(r.cpu), mn = mean(r.cpu);
      const double loads = median(r.ff_cpu);
      const double neg_mean = mean(r.neglected);
      const double neg_max = *std::max_element(r.neglected.begin(), r.neglected.end());
      const double tot_mean = mean(r.total);
      const double rms = std::sqrt((r.q - full.q).squaredNorm() / std::max<Eigen::Index>(1, r.q.size()));
      const double body_dev = max_body_deviation(m, r.q, full.q);
      const double dE = r.energy - full.energy;
      const double act_mean = mean(r.active);
      const double nodes = mean(r.nodes);
      const bool finite = r.finite && full.finite && std::isfinite(r.energy);
      if (!finite) ok = false;
      if (st.mode == AdaptiveOptions::Mode::kBudget && r.active_max > st.budget) {
        std::fprintf(stderr, "[%s] %s: budget overrun (%d active)\n", name.c_str(),
                     st.label.c_str(), r.active_max);
        ok = false;
      }
      std::printf("| %s | %d | %s | %.1f / %d | %.1f / %.1f | %.1f / %.1f | %.1f× / %.1f× | %lld | %.0f | "
                  "%.3g / %.3g | %.3g | %.2g | %.3g rad | %.3g %s | %.3g %s%s | %.3g | %.0f | %.0f |\n",
                  name.c_str(), m.nv, st.label.c_str(), act_mean, r.active_max, med, mn, full_med,
                  full_mean, full_med / med, full_mean / mn, static_cast<long long>(r.selections),
                  nodes, neg_mean, neg_max, r.check_max,
                  tot_mean > 0 ? neg_mean / tot_mean : 0.0, rms, body_dev, sc.length_unit.c_str(),
                  dE, sc.energy_unit.c_str(), finite ? "" : " NON-FINITE", r.v1_jump,
                  r.sel_cpu.empty() ? 0.0 : mean(r.sel_cpu), r.sel_nodes_full.empty() ? 0.0 : mean(r.sel_nodes_full));
      std::fflush(stdout);
      csv << name << ',' << m.nv << ',' << (st.mode == AdaptiveOptions::Mode::kBudget ? "budget" : "threshold")
          << ',' << st.label << ',' << st.budget << ',' << ao.epsilon << ',' << st.eps_rel << ','
          << sc.steps << ',' << sc.dt << ',' << sc.steps * sc.dt << ',' << sc.length_unit << ','
          << sc.energy_unit << ',' << full_med << ',' << full_mean << ',' << med << ',' << mn << ','
          << median(r.wall) << ',' << full_med / med << ',' << full_mean / mn << ',' << loads << ','
          << (full_med + full_loads) / (med + loads) << ',' << act_mean << ',' << r.active_max << ','
          << nodes << ',' << mean(full.nodes) << ',' << neg_mean << ',' << neg_max << ',' << tot_mean
          << ',' << (tot_mean > 0 ? neg_mean / tot_mean : 0.0) << ',' << rms << ',' << body_dev << ','
          << full.energy << ',' << r.energy << ',' << dE << ',' << E0 << ',' << (finite ? 1 : 0)
          << ',' << r.v1_jump << ',' << r.selections << ',' << r.check_max << ','
          << percentile(r.cpu, 0.9) << ',' << (r.sel_cpu.empty() ? 0.0 : mean(r.sel_cpu)) << ','
          << (r.sel_nodes_full.empty() ? 0.0 : mean(r.sel_nodes_full)) << '\n';
      csv.flush();
    }
  }
  std::fprintf(stderr, "CSV written to %s\n", csv_path.c_str());
  return ok ? 0 : 1;
}
