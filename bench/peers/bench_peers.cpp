// bench_peers: haptree against MuJoCo, Simbody and Bullet btMultiBody on the same models, in one run.
// For every model: µs per forward-dynamics call (median over repetitions, each call timed on its
// own) and the relative error ‖q̈ − q̈_ref‖/‖q̈_ref‖ of each engine against the long-double
// CRBA/RNEA oracle refined in quad precision (tests/support/quad_reference.hpp) at one random state
// (same q, q̇, τ, gravity; no external forces).
// Before scaling up, every engine is checked against the oracle on 2- and 3-link models with
// random frames, axes and full inertias; an engine that disagrees (> 1e-8) is reported and dropped.
#include <CLI/CLI.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <map>
#include <optional>
#include <random>
#include <stdexcept>
#include <sstream>
#include <ctime>

#include "bench/peers/peer_engine.hpp"
#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"
#include "tests/support/oracle.hpp"
#include "tests/support/quad_reference.hpp"
#ifdef HAPTREE_PEERS_ADAPTIVE
#include "haptree/adaptive.hpp"
#endif
#ifdef HAPTREE_PEERS_MOLECULE
#include "haptree/molecule/scene.hpp"
#endif

using namespace haptree;
using Clock = std::chrono::steady_clock;

namespace {

using Factory = std::function<std::unique_ptr<peers::PeerEngine>(const Model&)>;

std::map<std::string, Factory> factories() {
  std::map<std::string, Factory> f;
  f["haptree"] = peers::make_haptree_engine;
  f["haptree_auto"] = peers::make_haptree_auto_engine;
  f["haptree_plain"] = peers::make_haptree_plain_engine;
  f["haptree_exact"] = peers::make_haptree_exact_engine;
#ifdef HAPTREE_PEER_MUJOCO
  f["mujoco"] = [](const Model& m) { return peers::make_mujoco_engine(m, false); };
  f["mujoco_diaginertia"] = [](const Model& m) { return peers::make_mujoco_engine(m, true); };
#endif
#ifdef HAPTREE_PEER_SIMBODY
  f["simbody"] = peers::make_simbody_engine;
#endif
#ifdef HAPTREE_PEER_BULLET
  f["bullet"] = peers::make_bullet_engine;
#endif
  return f;
}

State bench_state(const Model& m, unsigned seed) {
  State st = testing::random_state(m, seed);
  for (auto& f : st.f_ext) f.setZero();
  return st;
}

// One benchmark model with the state every engine gets.
struct Job {
  std::string name;
  std::shared_ptr<const Model> model;
  std::optional<State> state;
  std::string note;   // how the state was made (printed once)
};

bool molecule_name(const std::string& m) { return m == "bacteriorhodopsin" || m == "bR"; }

// Generalized force equivalent to the external spatial forces f_ext (at r_k, world axes), at the
// configuration in `data` (after forward_kinematics): τ_k = a_kᵀ n_k, n_k = moment about r_k of
// everything applied to body k's subtree. Revolute/fixed joints only.
Eigen::VectorXd joint_torques_from_f_ext(const Model& m, const Data& data,
                                         const std::vector<Vec6>& f_ext) {
  std::vector<Vec6> sub(f_ext.begin(), f_ext.end());
  Eigen::VectorXd tau = Eigen::VectorXd::Zero(m.nv);
  for (int k = m.nbodies - 1; k >= 1; --k) {   // parent[k] < k
    if (m.joint_type[k] == JointType::kRevolute)
      tau(m.v_adr[k]) = (data.R[k] * m.joint_axis[k]).dot(sub[k].head<3>());
    else if (m.joint_type[k] != JointType::kFixed)
      throw std::runtime_error("joint_torques_from_f_ext: joint " + std::to_string(k) +
                               " is neither revolute nor fixed");
    const int p = m.parent[k];
    if (p == 0) continue;
    sub[p].head<3>() += sub[k].head<3>() + (data.r[k] - data.r[p]).cross(sub[k].tail<3>());
    sub[p].tail<3>() += sub[k].tail<3>();
  }
  return tau;
}

#ifdef HAPTREE_PEERS_MOLECULE
// Bacteriorhodopsin (1c3w_protein_h, 786 torsion DOF, root body welded to the world), built by the
// molecule library exactly as the launcher builds the "bacteriorhodopsin" scene. Units nm, ps, amu,
// kJ/mol; gravity zero (the molecular scenes' setting, taken from the model by every engine).
// State: torsions q = crystal + U(−q_rad, q_rad), rates q̇ = U(−qd, qd) rad/ps, and τ = the
// ff14SB "model B" force field of the scene at that configuration, mapped to joint torques
// (J_kᵀ f); f_ext = 0, since the peers take joint torques only.
Job molecule_job(const std::string& name, unsigned seed, double q_rad, double qd_rad_ps) {
  mol::MolecularScene sc = mol::load_molecular_scene("bacteriorhodopsin");
  Job job;
  job.name = "bacteriorhodopsin";
  job.model = sc.model;
  const Model& m = *sc.model;
  if (m.gravity.norm() != 0) throw std::runtime_error(name + ": molecular model with gravity");
  State st(m);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int k = 1; k < m.nbodies; ++k)
    if (m.joint_type[k] == JointType::kRevolute) st.q(m.q_adr[k]) = q_rad * u(rng);
  for (int i = 0; i < m.nv; ++i) st.qd(i) = qd_rad_ps * u(rng);
  Data d(m);
  forward_kinematics(m, d, st.q);
  const double E = sc.compute(d, st.f_ext);
  st.tau = joint_torques_from_f_ext(m, d, st.f_ext);
  // Check the mapping with the long-double oracle: the force field as f_ext (τ = 0) and as τ
  // (f_ext = 0) must give the same q̈.
  State with_f = st;
  with_f.tau.setZero();
  const Eigen::VectorXd a_f = testing::oracle_forward_dynamics(m, with_f).qdd;
  for (auto& f : st.f_ext) f.setZero();
  const double map_err = testing::rel_err(testing::oracle_forward_dynamics(m, st).qdd, a_f);
  char buf[400];
  std::snprintf(buf, sizeof buf,
                "%s: %d atoms, %d DOF, gravity 0; q = crystal + U(+-%.3g) rad, qd = U(+-%.3g) "
                "rad/ps, tau = force field (E = %.6g kJ/mol) as joint torques, |tau|_max = %.3g "
                "kJ/mol, f_ext-vs-tau check %.1e",
                job.name.c_str(), sc.natoms(), m.nv, q_rad, qd_rad_ps, E, st.tau.cwiseAbs().maxCoeff(),
                map_err);
  job.note = buf;
  if (!(map_err < 1e-9)) throw std::runtime_error(std::string("f_ext -> tau mapping failed: ") + buf);
  job.state.emplace(std::move(st));
  return job;
}
#endif

struct Timing {
  double median_us = 0, min_us = 0;   // wall clock
  double cpu_median_us = 0;           // this thread's CPU time (excludes time descheduled)
  double mean_us = 0, cpu_mean_us = 0;
  int reps = 0;
};

// Thread CPU time in µs: on a shared, overloaded machine the wall time of a long call includes the
// time the thread waited for a core; the thread CPU time does not.
double thread_cpu_us() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e6 + ts.tv_nsec * 1e-3;
}

Timing time_calls(const std::function<void()>& call, double min_seconds, int min_reps,
                  int max_reps) {
  const auto w0 = Clock::now();
  call();   // warm-up
  call();
  // Very slow calls (O(n^3) engines on long chains): 3 timed calls are enough for a median.
  if (std::chrono::duration<double>(Clock::now() - w0).count() > 2.0) min_reps = std::min(min_reps, 3);
  std::vector<double> us, cpu;
  const auto start = Clock::now();
  while (static_cast<int>(us.size()) < max_reps &&
         (static_cast<int>(us.size()) < min_reps ||
          std::chrono::duration<double>(Clock::now() - start).count() < min_seconds)) {
    const double c0 = thread_cpu_us();
    const auto t0 = Clock::now();
    call();
    us.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
    cpu.push_back(thread_cpu_us() - c0);
  }
  Timing t;
  t.reps = static_cast<int>(us.size());
  std::sort(us.begin(), us.end());
  std::sort(cpu.begin(), cpu.end());
  t.median_us = us[us.size() / 2];
  t.min_us = us.front();
  t.cpu_median_us = cpu[cpu.size() / 2];
  for (size_t i = 0; i < us.size(); ++i) {
    t.mean_us += us[i] / us.size();
    t.cpu_mean_us += cpu[i] / cpu.size();
  }
  return t;
}

// Small models with random joint frames, axes, COMs and full (rotated) inertias, plus a fixed joint.
std::vector<std::pair<std::string, std::shared_ptr<const Model>>> check_models() {
  std::vector<std::pair<std::string, std::shared_ptr<const Model>>> out;
  SceneOptions o;
  o.n = 2;
  o.seed = 3;
  out.emplace_back("chain2_random", make_chain(o));
  o.seed = 0;
  out.emplace_back("chain2_regular", make_chain(o));
  ModelBuilder b;
  const Mat3 R1 = Eigen::AngleAxisd(0.7, Vec3(1, 2, 3).normalized()).toRotationMatrix();
  const Mat3 R2 = Eigen::AngleAxisd(-1.1, Vec3(-2, 1, 0.5).normalized()).toRotationMatrix();
  Mat3 I1;
  I1 << 0.05, 0.004, -0.002, 0.004, 0.03, 0.001, -0.002, 0.001, 0.04;
  b.add_body("base", 0, JointType::kFixed, Vec3(0.1, -0.2, 0.3), R1, Vec3::UnitZ(), 2.0,
             Vec3(0.05, 0.01, 0), I1);
  b.add_body("l1", 1, JointType::kRevolute, Vec3(0.2, 0.1, 0), R2, Vec3(0.3, -0.5, 0.8).normalized(),
             1.3, Vec3(0.12, -0.03, 0.02), R2 * I1 * R2.transpose());
  b.add_body("l2", 2, JointType::kRevolute, Vec3(0.25, 0, 0.05), R1 * R2,
             Vec3(-0.6, 0.2, 0.4).normalized(), 0.7, Vec3(0.1, 0.02, -0.01), 0.5 * I1);
  out.emplace_back("fixed_plus_2", b.build());
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"haptree vs MuJoCo / Simbody / Bullet: forward-dynamics time and accuracy"};
  std::string csv = "bench_peers.csv";
  std::vector<std::string> models{"chain", "binary_tree", "protein_like"
#ifdef HAPTREE_PEERS_MOLECULE
                                  , "bacteriorhodopsin"
#endif
  };
  std::vector<int> sizes{16, 64, 256, 1024, 4096};
  std::vector<std::string> engines;
  double min_seconds = 0.3;
  int min_reps = 7, max_reps = 20000, oracle_max_nv = 4096;
  unsigned seed = 1;
  bool check_only = false;
  std::vector<int> budgets{48, 128};
  double mol_q_rad = 0.0, mol_qd_rad_per_ps = 1.0;
  app.add_option("--csv", csv, "CSV output path")->capture_default_str();
  app.add_option("--models", models,
                 "chain, binary_tree, protein_like"
#ifdef HAPTREE_PEERS_MOLECULE
                 ", bacteriorhodopsin (bR)"
#endif
                 )
      ->capture_default_str();
  app.add_option("--mol-q-rad", mol_q_rad,
                 "bacteriorhodopsin: torsions = crystal + uniform(-x, x) [rad] (even 0.005 rad makes "
                 "atoms clash: force field 1e4 kJ/mol higher)")
      ->capture_default_str();
  app.add_option("--mol-qd-rad-per-ps", mol_qd_rad_per_ps,
                 "bacteriorhodopsin: torsion rates uniform(-x, x) [rad/ps]")
      ->capture_default_str();
  app.add_option("--sizes", sizes, "body counts for chain and binary_tree")->capture_default_str();
  app.add_option("--engines", engines, "subset of engines (default: all compiled in)");
  app.add_option("--min-seconds", min_seconds, "minimum timing time per engine and model [s]")
      ->capture_default_str();
  app.add_option("--min-reps", min_reps, "minimum timed calls")->capture_default_str();
  app.add_option("--max-reps", max_reps, "maximum timed calls")->capture_default_str();
  app.add_option("--oracle-max-nv", oracle_max_nv, "skip the O(n^3) oracle above this many DOFs")
      ->capture_default_str();
  app.add_option("--seed", seed, "random state seed")->capture_default_str();
  app.add_option("--budgets", budgets, "adaptive DOF budgets k (if the adaptive layer is built)")
      ->capture_default_str();
  app.add_flag("--check-only", check_only, "only run the small-model frame-convention check");
  CLI11_PARSE(app, argc, argv);
  std::setvbuf(stdout, nullptr, _IOLBF, 0);   // progress lines appear as they are printed

  auto all = factories();
  // mujoco_diaginertia is a diagnostic variant: by default it is checked and run only on models
  // with off-diagonal body inertias (bacteriorhodopsin), where MuJoCo's own diagonalisation of
  // fullinertia costs accuracy.
  const bool diag_explicit =
      std::find(engines.begin(), engines.end(), "mujoco_diaginertia") != engines.end();
  // Every engine by default: haptree (the library default, one refinement step), haptree_plain
  // (the single pass) and haptree_exact (kExtended) side by side.
  if (engines.empty())
    for (auto& [name, f] : all) engines.push_back(name);
  for (const char* p : {"mujoco", "simbody", "bullet"})
    if (!all.count(p)) std::printf("peer %s: not compiled in (library not found at build time), skipped\n", p);

  // 1. Frame-convention check on small models.
  std::vector<std::string> verified;
  std::printf("== convention check (relative q̈ error vs long-double oracle, must be <= 1e-8)\n");
  auto checks = check_models();
  for (const auto& name : engines) {
    if (!all.count(name)) {
      std::printf("%-8s unknown or not compiled in, skipped\n", name.c_str());
      continue;
    }
    double overall = 0;
    std::string why;
    for (auto& [mname, model] : checks) {
      double worst = 0;
      try {
        auto eng = all[name](*model);
        for (unsigned s = 1; s <= 3; ++s) {
          const State st = bench_state(*model, s);
          eng->compute(st);
          const auto ref = testing::oracle_forward_dynamics(*model, st);
          const double e = testing::rel_err(eng->qdd(), ref.qdd);
          if (!(e <= worst)) worst = e;   // NaN-propagating max
        }
      } catch (const std::exception& ex) {
        why = ex.what();
        worst = INFINITY;
      }
      std::printf("%-8s %-16s worst rel err %.3e\n", name.c_str(), mname.c_str(), worst);
      if (!(worst <= overall)) overall = worst;
    }
    if (overall <= 1e-8) verified.push_back(name);
    else std::printf("%-8s FAILED the convention check%s%s: dropped\n", name.c_str(),
                     why.empty() ? "" : ": ", why.c_str());
  }
  if (check_only) return verified.size() == engines.size() ? 0 : 1;

  // 2. The scaled run.
  std::ofstream out(csv);
  // rel_err: against the full oracle. rel_err_locked: against the oracle with the DOFs the engine
  // leaves out locked (adaptive rows: the inactive joints; equal to rel_err for full engines).
  // us_*: wall clock; cpu_us_*: thread CPU time per call (of the calling thread only: for
  // haptree_auto's parallel passes the wall clock is the figure).
  out << "engine,model,bodies,nv,us_median,us_min,reps,rel_err,max_abs_err,rel_err_locked,"
         "cpu_us_median,us_mean,cpu_us_mean,timed_call\n";
  std::vector<std::pair<std::string, int>> jobs;
  for (const auto& m : models) {
    if (m == "protein_like") jobs.emplace_back(m, 857);
    else if (molecule_name(m)) jobs.emplace_back("bacteriorhodopsin", 0);
    else
      for (int n : sizes) jobs.emplace_back(m, n);
  }
  const auto run_start = Clock::now();
  auto elapsed = [&] { return std::chrono::duration<double>(Clock::now() - run_start).count(); };
  int job_no = 0;
  for (const auto& [mname, n] : jobs) {
    ++job_no;
    Job job;
    try {
      if (molecule_name(mname)) {
#ifdef HAPTREE_PEERS_MOLECULE
        job = molecule_job(mname, seed, mol_q_rad, mol_qd_rad_per_ps);
#else
        throw std::runtime_error("the molecule library (haptree_molecule) was not built");
#endif
      } else {
        SceneOptions o;
        o.n = n;
        job.name = mname;
        job.model = make_scene(mname, o);
        job.state.emplace(bench_state(*job.model, seed));
      }
    } catch (const std::exception& ex) {
      std::printf("[%d/%zu] %s: cannot build the model, skipped: %s\n", job_no, jobs.size(),
                  mname.c_str(), ex.what());
      continue;
    }
    const auto model = job.model;
    const State& st = *job.state;
    bool off_diagonal = false;
    for (int k = 1; k < model->nbodies; ++k) {
      const Mat3& I = model->inertia[k];
      if (I(0, 1) != 0 || I(0, 2) != 0 || I(1, 2) != 0) off_diagonal = true;
    }
    std::printf("[%d/%zu] %s, %d bodies, %d DOF (t = %.0f s)%s%s\n", job_no, jobs.size(),
                mname.c_str(), model->nbodies - 1, model->nv, elapsed(), job.note.empty() ? "" : "\n    ",
                job.note.c_str());
    Eigen::VectorXd ref;
    bool have_ref = model->nv <= oracle_max_nv;
    if (have_ref) {
      const auto t0 = Clock::now();
      // The long-double oracle refined by the quad-precision residual (its own Cholesky error,
      // ~κ₂(H)·2⁻⁶⁴, reaches 1e-12 on the 1024 chain: tests/support/quad_reference.hpp).
      const auto orc = testing::oracle_forward_dynamics(*model, st);
      const auto quad = testing::quad_reference(*model, st, orc);
      ref = quad.qdd;
      std::printf("    oracle %.1f s; reference = oracle refined in quad precision (the long-double "
                  "oracle's own error %.2e, last step %.1e)\n",
                  std::chrono::duration<double>(Clock::now() - t0).count(), quad.oracle_rel_change,
                  quad.last_rel_step);
    }
    std::printf("   %-17s %6s %6s  %-22s %12s %12s %10s %10s %6s %10s %10s\n", "model", "bodies",
                "nv", "engine", "us_median", "cpu_us_med", "rel_err", "rel_locked", "reps", "us_mean",
                "cpu_mean");
    std::fflush(stdout);
    auto emit = [&](const std::string& eng, const Timing& t, const Eigen::VectorXd& qdd,
                    const std::string& what, double e_locked) {
      const double e = have_ref ? testing::rel_err(qdd, ref) : NAN;
      if (std::isnan(e_locked)) e_locked = e;
      const double a = have_ref ? (qdd - ref).cwiseAbs().maxCoeff() : NAN;
      std::printf("   %-17s %6d %6d  %-22s %12.2f %12.2f %10.2e %10.2e %6d %10.2f %10.2f\n",
                  mname.c_str(), model->nbodies - 1, model->nv, eng.c_str(), t.median_us,
                  t.cpu_median_us, e, e_locked, t.reps, t.mean_us, t.cpu_mean_us);
      std::fflush(stdout);
      out << eng << "," << mname << "," << model->nbodies - 1 << "," << model->nv << ","
          << t.median_us << "," << t.min_us << "," << t.reps << "," << e << "," << a << "," << e_locked
          << "," << t.cpu_median_us << "," << t.mean_us << "," << t.cpu_mean_us << ",\""
          << what << "\"\n";
      out.flush();
    };
    for (const auto& name : verified) {
      if (name == "mujoco_diaginertia" && !diag_explicit && !off_diagonal) continue;
      std::unique_ptr<peers::PeerEngine> eng;
      try {
        eng = all[name](*model);
      } catch (const std::exception& ex) {
        std::printf("   %-17s %-8s n/a: %s\n", mname.c_str(), name.c_str(), ex.what());
        std::string why = ex.what();
        std::replace(why.begin(), why.end(), '"', '\'');
        out << name << "," << mname << "," << model->nbodies - 1 << "," << model->nv
            << ",nan,nan,0,nan,nan,nan,nan,nan,nan,\"n/a: " << why << "\"\n";
        out.flush();
        continue;
      }
      const Timing t = time_calls([&] { eng->compute(st); }, min_seconds, min_reps, max_reps);
      emit(name, t, eng->qdd(), eng->timed_call(), NAN);
    }
#ifdef HAPTREE_PEERS_ADAPTIVE
    for (int k : budgets) {
      if (k >= model->nv) continue;
      Data data(*model);
      State ast = st;
      AdaptiveData ad(*model);
      AdaptiveOptions opt;
      opt.mode = AdaptiveOptions::Mode::kBudget;
      opt.budget = k;
      select_active_region(*model, data, ast, ad, opt);
      // Error of the hybrid q̈ against the full oracle at the same (reduced-velocity) state.
      const Timing t = time_calls([&] { adaptive_forward_dynamics(*model, data, ast, ad); },
                                  min_seconds, min_reps, max_reps);
      // Reference at the adaptive state (inactive q̇ zeroed by the velocity policy), full and with
      // the inactive DOFs locked (the hybrid dynamics must match the latter exactly).
      Eigen::VectorXd aref = ref;
      double e_locked = NAN;
      if (have_ref) {
        aref = testing::oracle_forward_dynamics(*model, ast).qdd;
        std::vector<bool> locked(model->nv, true);
        for (int j : ad.active_joints)
          for (int i = 0; i < model->v_num[j]; ++i) locked[model->v_adr[j] + i] = false;
        e_locked = testing::rel_err(data.qdd,
                                    testing::oracle_forward_dynamics(*model, ast, locked).qdd);
      }
      std::swap(ref, aref);
      emit("haptree_adaptive_k" + std::to_string(k), t, data.qdd,
           "adaptive_forward_dynamics on a budget-k active region (selection not timed)", e_locked);
      std::swap(ref, aref);
    }
#endif
  }
  std::printf("wrote %s (%.0f s)\n", csv.c_str(), elapsed());
  return 0;
}
