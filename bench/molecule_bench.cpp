// Molecular-scene benchmark (plain runner): force-field ms per step and whole-step ms (force field +
// DCA forward dynamics + semi-implicit Euler) for the molecular scenes, with all joints active
// (haptree::forward_dynamics) and with an adaptive active region of --budget DOF
// (haptree::adaptive_step, default options: error-controlled reselection), the adaptive run once
// with the force field evaluating every inter-body pair and once following motion (only pairs
// between bodies that moved relative to each other; ff::NonbondedOptions::follow_motion).
// Prints a Markdown table (thread-CPU mean and median) and the command line.
//   molecule_bench --scenes bacteriorhodopsin,ala20,polyaniline --steps 200 --dt-ps 0.0005
#include <algorithm>
#include <chrono>
#include <ctime>
#include <xmmintrin.h>
#include <pmmintrin.h>
#include <cmath>
#include <cstdio>
#include <sstream>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "haptree/adaptive.hpp"
#include "haptree/dca.hpp"
#include "haptree/molecule/scene.hpp"

namespace {

using namespace haptree;
using Clock = std::chrono::steady_clock;

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}
// Thread CPU time (ms): the machine is shared, so wall time includes time spent descheduled.
double cpu_ms() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}

struct Row {
  std::string scene, mode;
  int atoms = 0, dofs = 0, active = 0;
  double ff_ms = 0, step_ms = 0, ff_median = 0, step_median = 0, ff_cpu = 0, step_cpu = 0;
  double ff_cpu_mean = 0, step_cpu_mean = 0, pairs_per_step = 0, lanes_per_step = 0;
  int rebuilds = 0, regroups = 0, selections = 0, splits = 0;
  size_t pairs = 0;
  double e0 = 0, e1 = 0;
  bool finite = true;
};

double median(std::vector<double> v) {
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

Row run(mol::MolecularScene& sc, bool adaptive, bool follow, int budget, int steps, double dt) {
  const Model& m = *sc.model;
  State st(m);
  Data d(m);
  AdaptiveData ad(m);
  AdaptiveOptions ao;
  ao.mode = AdaptiveOptions::Mode::kBudget;
  ao.budget = budget;
  Row row;
  row.scene = sc.name;
  row.mode = !adaptive ? "full DCA" : follow ? "adaptive, follows motion" : "adaptive, all pairs";
  row.atoms = sc.natoms();
  row.dofs = m.nv;
  const int rebuild0 = sc.force_field->neighbour_rebuilds();
  const int regroup0 = sc.force_field->regroups();
  const int split0 = sc.force_field->prunes();
  std::vector<double> tf, ts, cf, cs;
  double pairs = 0, lanes = 0;
  forward_kinematics(m, d, st.q);
  for (int s = 0; s < steps; ++s) {
    const auto t0 = Clock::now();
    const double c0 = cpu_ms();
    if (adaptive && s > 0) update_all_body_poses(m, d, ad);
    else if (!adaptive) forward_kinematics(m, d, st.q);
    // f_ext is complete (every body's own force) with or without follow_motion, so the
    // selection's full pass needs no preparation.
    const double E = sc.compute(d, st.f_ext);
    const double f_ms = ms_since(t0), f_cpu = cpu_ms() - c0;
    if (adaptive) {
      const AdaptiveReport& r = adaptive_step(m, d, st, ad, ao, dt);
      row.active = r.active_dofs;
      row.selections = static_cast<int>(r.selections);
    } else {
      forward_dynamics(m, d, st);
      integrate(m, st.q, st.qd, d.qdd, dt);
      row.active = m.nv;
    }
    const double s_ms = ms_since(t0), s_cpu = cpu_ms() - c0;
    if (s == 0) row.e0 = E;
    row.e1 = E;
    if (s >= 5) {   // skip warm-up
      tf.push_back(f_ms);
      ts.push_back(s_ms);
      cf.push_back(f_cpu);
      cs.push_back(s_cpu);
      pairs += static_cast<double>(sc.force_field->pairs_evaluated());
      lanes += static_cast<double>(sc.force_field->kernel_lanes());
    }
  }
  row.finite = st.q.allFinite() && std::isfinite(row.e1);
  for (double x : tf) row.ff_ms += x / tf.size();
  for (double x : ts) row.step_ms += x / ts.size();
  for (double x : cf) row.ff_cpu_mean += x / cf.size();
  for (double x : cs) row.step_cpu_mean += x / cs.size();
  row.pairs_per_step = pairs / cf.size();
  row.lanes_per_step = lanes / cf.size();
  row.regroups = sc.force_field->regroups() - regroup0;
  row.splits = sc.force_field->prunes() - split0;
  row.ff_median = median(tf);
  row.ff_cpu = median(cf);
  row.step_cpu = median(cs);
  row.step_median = median(ts);
  row.rebuilds = sc.force_field->neighbour_rebuilds() - rebuild0;
  row.pairs = sc.force_field->neighbour_pairs();
  return row;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"haptree molecular scene benchmark (force field + DCA step)"};
  std::string scenes = "bacteriorhodopsin,ala20,polyaniline";
  int steps = 200, budget = 48;
  double dt_ps = 0.0005;
  bool ftz = false;
  std::string modes = "full,all,follow";
  app.add_option("--scenes", scenes, "comma-separated scene names or PDB paths")->capture_default_str();
  app.add_option("--steps", steps, "steps per run (first 5 not timed)")->capture_default_str();
  app.add_option("--dt-ps", dt_ps, "time step in ps (0.0005 = 0.5 fs)")->capture_default_str();
  app.add_option("--budget", budget, "active DOF budget of the adaptive run")->capture_default_str();
  app.add_option("--modes", modes, "runs: full (full DCA), all (adaptive, all pairs), follow (adaptive, follows motion)")
      ->capture_default_str();
  app.add_flag("--ftz", ftz, "set flush-to-zero and denormals-are-zero (MXCSR) first: a subnormal check");
  CLI11_PARSE(app, argc, argv);
  if (ftz) {
    _MM_SET_FLUSH_ZERO_MODE(_MM_FLUSH_ZERO_ON);
    _MM_SET_DENORMALS_ZERO_MODE(_MM_DENORMALS_ZERO_ON);
  }
  std::string cmd;
  for (int i = 0; i < argc; ++i) cmd += (i ? " " : "") + std::string(argv[i]);
  std::printf("command: %s\n\n", cmd.c_str());
  std::printf("| scene | atoms | DOF | mode | active DOF | thread CPU ms force field (mean / median) | "
              "thread CPU ms whole step (mean / median) | wall ms whole step (mean / median) | "
              "pairs evaluated / step (mean) | kernel lanes / step (mean) | list rebuilds | regroups | list splits (prunes) | selections | E first → last (kJ/mol) |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  std::stringstream ss(scenes);
  std::string name;
  while (std::getline(ss, name, ',')) {
    for (int mode = 0; mode < 3; ++mode) {
      if (modes.find(mode == 0 ? "full" : mode == 1 ? "all" : "follow") == std::string::npos) continue;
      mol::SceneOptions so;
      so.nonbonded.follow_motion = mode == 2;
      mol::MolecularScene sc = mol::load_molecular_scene(name, so);   // fresh state per run
      const Row r = run(sc, mode > 0, mode == 2, budget, steps, dt_ps);
      std::printf("| %s | %d | %d | %s | %d | %.3f / %.3f | %.3f / %.3f | %.3f / %.3f | %.0f | %.0f | %d | %d | %d | %d | %.1f → %.1f%s |\n",
                  r.scene.c_str(), r.atoms, r.dofs, r.mode.c_str(), r.active, r.ff_cpu_mean, r.ff_cpu,
                  r.step_cpu_mean, r.step_cpu, r.step_ms, r.step_median, r.pairs_per_step, r.lanes_per_step, r.rebuilds,
                  r.regroups, r.splits, r.selections, r.e0, r.e1, r.finite ? "" : " (NON-FINITE)");
      std::fflush(stdout);
    }
  }
  return 0;
}
