// stress_report: the longer numerical-stability report behind docs/accuracy_and_stability.md.
// Sections (all by default):
//   isa      the build's ISA level, compiler flags, FMA contraction and the CPU it runs on;
//   drift    energy drift of conservative 857-DOF protein-like runs (scenes fall and tumble) with
//            semi-implicit Euler and/or RK4 (--integrator) over a short horizon and over --steps
//            steps at several dt, halving dt below the list until a run survives --steps steps;
//   far      q̈ of models placed 10^3 … 10^15 m from the origin against the same model at the origin
//            (and what the long-double oracle does there);
//   welds    a 127-joint tree mounted 10^3/10^6 m off a massive root link, then random models (every joint type, fixed roots, chains of welds, welded massive links,
//            welds up to 1 km from their parent's frame) translated by 10^3/10^6 m and rotated;
//   light    light bodies (smallest principal inertia / r) between normal ones: error vs bound;
//   ratio    mass ratio 10^-k … 10^k between neighbouring links: error vs the long-double oracle;
//   coaxial  aligned (coaxial) joint axes with a vanishing axial inertia: error vs the oracle;
//   size     error vs the oracle as chains grow (n = 16 … --oracle-max-n);
//   long     chains of 2^10 … 2^--max-log2 bodies: finite q̈, agreement with a shifted origin, time.
// Every "limit" reported is the first sweep value at which the stated criterion fails.
#include <CLI/CLI.hpp>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>

#include "haptree/isa.hpp"
#include "tests/stress/random_models.hpp"
#include "tests/stress/stress_scenes.hpp"

using namespace haptree;
using namespace haptree::stress;
using testing::oracle_forward_dynamics;
using testing::rel_err;
using Clock = std::chrono::steady_clock;

namespace {

double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

void print_drift_row(const char* method, double dt, const DriftResult& r, double wall) {
  char tb[48] = "never";
  if (r.cut) std::snprintf(tb, sizeof tb, "cut (wall limit)");
  if (r.t_blowup >= 0)
    std::snprintf(tb, sizeof tb, "%.4g%s", r.t_blowup, r.finite ? " (energy)" : " (NaN)");
  char rel[32] = "—";
  if (r.survived || r.cut) std::snprintf(rel, sizeof rel, "%.3e", r.rel_drift);
  std::printf("| %s | %g | %d | %g | %.3e | %.3e | %.3e | %.3e | %s | %s | %.1f |\n", method, dt,
              r.steps_done, r.steps_done * dt, r.max_abs_drift, r.final_drift, r.max_kinetic,
              r.max_qd, rel, tb, wall);
  std::fflush(stdout);
}

struct DriftSettings {
  int steps = 100000;
  std::vector<double> dts{1e-3, 5e-4, 2.5e-4, 1e-4};
  std::vector<std::string> scenes{"fall", "tumble"};
  std::vector<std::string> integrators{"euler", "rk4"};
  double horizon_s = 0.25;
  double blowup_factor = 10;   // blow-up: |E − E0| > factor × kinetic-energy bound
  int max_halvings = 6;        // below the smallest listed dt, while nothing survives
  int progress_every = 10000;
  bool limit_search = true;
  double max_wall_s = 0;       // per run; 0: no limit (a cut run neither survives nor fails)
};

DriftResult drift_run(const DriftScene& sc, Integrator method, double dt, int steps,
                      const DriftSettings& cfg) {
  DriftOptions opt;
  opt.method = method;
  opt.blowup_J = cfg.blowup_factor * sc.ke_bound;
  opt.progress_every = cfg.progress_every;
  if (cfg.max_wall_s > 0) opt.max_wall_s = cfg.max_wall_s;
  const auto t0 = Clock::now();
  opt.progress = [&](const DriftProgress& p) {
    spdlog::info("drift {} {} dt={:g}: step {}/{} t={:.4g} s E-E0={:.3e} J KE={:.3e} J max|qd|={:.3e} ({:.0f} s)",
                 sc.name, integrator_name(method), dt, p.step, p.steps, p.t, p.drift, p.kinetic,
                 p.max_qd, seconds_since(t0));
  };
  return energy_drift(*sc.model, sc.st0, dt, steps, opt);
}

// The build's instruction set and floating-point settings, so that a report names the ISA level
// its numbers come from (scripts/test_isa.sh --report runs the numeric sections in each build).
// Out of line, so the product has no other use and the compiler may contract it (-ffp-contract).
__attribute__((noinline)) double square_minus(double a, double p) { return a * a - p; }

void section_isa() {
  std::printf("\n## Build and CPU (the ISA level of the numbers below)\n\n| item | value |\n|---|---|\n");
#if defined(__clang__)
  const char* compiler = "clang";
#else
  const char* compiler = "GCC";
#endif
  std::printf("| ISA level (CMake) | %s |\n| compiler | %s %s |\n| flags | %s |\n", HAPTREE_BUILD_ISA,
              compiler, __VERSION__, HAPTREE_BUILD_FLAGS);
  std::string isa;
  auto add = [&](const char* name, bool on) { if (on) isa += std::string(isa.empty() ? "" : " ") + name; };
  add("SSE2", true);   // x86-64 baseline
#ifdef __AVX__
  add("AVX", true);
#endif
#ifdef __AVX2__
  add("AVX2", true);
#endif
#ifdef __FMA__
  add("FMA", true);
#endif
#ifdef __AVX512F__
  add("AVX-512F", true);
#endif
  std::printf("| compiled for | %s |\n", isa.c_str());
  std::printf("| run-time kernel level (haptree/isa.hpp) | %s (best on this CPU: %s) |\n",
              haptree::isa::name(haptree::isa::active()), haptree::isa::name(haptree::isa::best()));
  // Contraction probe: a·a − fl(a·a) is 0 when rounded twice, the exact 2⁻⁶⁰ when fused.
  volatile double va = 1 + std::ldexp(1.0, -30);
  const double a = va;
  volatile double vp = a * a;
  const double r = square_minus(a, vp);
  std::printf("| a·a − fl(a·a), a = 1 + 2⁻³⁰ | %g (%s) |\n", r,
              r != 0 ? "a·b − c contracted to FMA" : "not contracted");
  std::string cpu = "unknown";
  if (std::FILE* f = std::fopen("/proc/cpuinfo", "r")) {
    char line[512];
    while (std::fgets(line, sizeof line, f))
      if (std::strncmp(line, "model name", 10) == 0) {
        const char* c = std::strchr(line, ':');
        cpu = c ? c + 2 : line;
        if (!cpu.empty() && cpu.back() == '\n') cpu.pop_back();
        break;
      }
    std::fclose(f);
  }
  __builtin_cpu_init();
  std::string rt;
  auto rtadd = [&](const char* name, bool on) { if (on) rt += std::string(rt.empty() ? "" : " ") + name; };
  rtadd("AVX2", __builtin_cpu_supports("avx2"));
  rtadd("FMA", __builtin_cpu_supports("fma"));
  rtadd("AVX-512F", __builtin_cpu_supports("avx512f"));
  std::printf("| CPU | %s (runs %s) |\n", cpu.c_str(), rt.empty() ? "SSE2 only" : rt.c_str());
  std::fflush(stdout);
}

void section_drift(const DriftSettings& cfg) {
  std::printf("\n## Energy drift: conservative runs of the 857-DOF protein-like tree (tau = 0)\n");
  std::printf("rel = max_t |E(t) - E(0)| / max_t KE(t). A run blows up when it goes non-finite (NaN) or "
              "when |E - E0| exceeds %g x the kinetic-energy bound (energy): no physical state has that "
              "energy. t(blow-up) is simulated time.\n", cfg.blowup_factor);
  const char* head =
      "| integrator | dt [s] | steps | simulated [s] | max abs drift [J] | final drift [J] | max KE [J] | "
      "max abs qd [rad/s] | rel | t(blow-up) [s] | wall [s] |\n|---|---|---|---|---|---|---|---|---|---|---|\n";
  for (const auto& scene_name : cfg.scenes) {
    const DriftScene sc = drift_scene(scene_name);
    std::printf("\n### Scene %s: %s\nKinetic-energy bound (E0 - lowest possible potential): %.4e J\n",
                sc.name.c_str(), sc.description.c_str(), sc.ke_bound);
    if (cfg.horizon_s > 0) {
      std::printf("\nFixed horizon of %g s simulated:\n\n%s", cfg.horizon_s, head);
      for (const auto& iname : cfg.integrators) {
        const Integrator method = parse_integrator(iname);
        for (double dt : cfg.dts) {
          const auto t0 = Clock::now();
          const auto r = drift_run(sc, method, dt, static_cast<int>(std::lround(cfg.horizon_s / dt)), cfg);
          print_drift_row(integrator_name(method), dt, r, seconds_since(t0));
        }
      }
    }
    std::printf("\n%d steps per dt (dt list, then halving below it while nothing survives):\n\n%s",
                cfg.steps, head);
    for (const auto& iname : cfg.integrators) {
      const Integrator method = parse_integrator(iname);
      std::vector<double> dts = cfg.dts;
      std::sort(dts.rbegin(), dts.rend());
      double best = NAN, failed_above = NAN, failed_at = NAN, last_cut = NAN;
      auto run = [&](double dt) {
        const auto t0 = Clock::now();
        const auto r = drift_run(sc, method, dt, cfg.steps, cfg);
        print_drift_row(integrator_name(method), dt, r, seconds_since(t0));
        if (r.survived && std::isnan(best)) best = dt;
        if (!r.survived && !r.cut && std::isnan(best)) { failed_above = dt; failed_at = r.t_blowup; }
        if (r.cut && std::isnan(best)) last_cut = dt;
        return r.survived;
      };
      for (double dt : dts) run(dt);
      if (cfg.limit_search && std::isnan(best)) {
        double dt = dts.back();
        for (int h = 0; h < cfg.max_halvings && std::isnan(best) && std::isnan(last_cut); ++h)
          run(dt *= 0.5);
      }
      if (std::isnan(best) && !std::isnan(last_cut))
        std::printf("\nLIMIT drift/%s/%s: not found (runs down to %g s were cut by --max-wall-s; "
                    "smallest dt that blew up: %g s, at t = %.4g s)\n\n",
                    sc.name.c_str(), integrator_name(method), last_cut, failed_above, failed_at);
      else if (std::isnan(best))
        std::printf("\nLIMIT drift/%s/%s: nothing down to the smallest dt tried survives %d steps\n\n",
                    sc.name.c_str(), integrator_name(method), cfg.steps);
      else if (std::isnan(failed_above))
        std::printf("\nLIMIT drift/%s/%s: the largest dt tried (%g s) survives %d steps\n\n",
                    sc.name.c_str(), integrator_name(method), best, cfg.steps);
      else
        std::printf("\nLIMIT drift/%s/%s: largest dt tried that survives %d steps: %g s "
                    "(%g s blows up at t = %.4g s)\n\n",
                    sc.name.c_str(), integrator_name(method), cfg.steps, best, failed_above, failed_at);
      std::fflush(stdout);
    }
  }
}

void section_far(double tol) {
  std::printf("\n## Far from the origin: q̈(model at distance D along (1,1,1)/sqrt3) vs q̈(same model at the origin)\n\n");
  std::printf("| model | D [m] | rel diff DCA far vs near | DCA near vs oracle | oracle far vs near |\n|---|---|---|---|---|\n");
  const Vec3 dir = Vec3(1, 1, 1).normalized();
  struct Case { const char* name; int n; };
  for (Case c : {Case{"chain", 64}, Case{"binary_tree", 63}, Case{"protein_like", 857}}) {
    auto near = scene_at(c.name, c.n, Vec3::Zero());
    const State st = clean_state(*near, 3);
    const auto qn = dca(*near, st).qdd;
    const auto on = oracle_forward_dynamics(*near, st).qdd;
    double limit = NAN;
    for (double D : {1e3, 1e6, 1e9, 1e12, 1e15}) {
      auto far = scene_at(c.name, c.n, D * dir);
      const auto qf = dca(*far, st).qdd;
      const double e = rel_err(qf, qn);
      char eo[32] = "not run";
      if (D <= 1e9) std::snprintf(eo, sizeof eo, "%.3e", rel_err(oracle_forward_dynamics(*far, st).qdd, on));
      std::printf("| %s | %g | %.3e | %.3e | %s |\n", c.name, D, e, rel_err(qn, on), eo);
      std::fflush(stdout);
      if (std::isnan(limit) && !(e <= tol)) limit = D;
    }
    if (std::isnan(limit)) std::printf("\nLIMIT far/%s: DCA within %g of the near model up to 1e15 m\n\n", c.name, tol);
    else std::printf("\nLIMIT far/%s: DCA differs by more than %g at D = %g m\n\n", c.name, tol, limit);
  }
}

// Random models with welds (tests/stress/random_models.hpp): every joint type, fixed roots with
// inertia, chains of welds, welded massive links, welds far from their parent's frame; each model
// translated by 10³ and 10⁶ m and rotated, against the model at the origin and the oracle.
void section_welds(int models) {
  std::printf("\n## Welds and far mounts\n\n### A 127-joint tree (≈ 10 %% fixed) mounted "
              "D off a 1000 kg root link fixed to the ground, against the same tree mounted 0.3 m off it\n\n");
  std::printf("| mount D [m] | vs mounted 0.3 m | vs oracle | err/B | κ(H) | singular pivots |\n"
              "|---|---|---|---|---|---|\n");
  {
    const auto near = build_model(mounted_binary_tree(0.3));
    const State st = testing::random_state(*near, 5);
    const auto q0 = dca(*near, st).qdd;
    for (double mount : {0.3, 1e3, 1e6}) {
      const auto far = build_model(mounted_binary_tree(mount));
      const auto fd = dca(*far, st);
      // The oracle spans the mount itself (about body 1's joint point): (D/L)²·ε_LD ≈ 1e-12 at
      // 1 km, so it is not run beyond.
      char eo[32] = "not run", eb[32] = "", ek[32] = "";
      if (mount <= 1e3) {
        const auto orc = oracle_forward_dynamics(*far, st);
        const double e = rel_err(fd.qdd, orc.qdd);
        std::snprintf(eo, sizeof eo, "%.2e", e);
        std::snprintf(eb, sizeof eb, "%.2e", e / testing::qdd_error_bound(orc, st, testing::kBoundC));
        std::snprintf(ek, sizeof ek, "%.2e", testing::mass_matrix_condition(orc));
      }
      std::printf("| %g | %.2e | %s | %s | %s | %lld |\n", mount, rel_err(fd.qdd, q0), eo, eb, ek,
                  static_cast<long long>(fd.singular_pivots));
      std::fflush(stdout);
    }
  }
  std::printf("\n### Random models translated by up to 1e6 m and rotated\n\n");
  std::printf("B = 10·n·ε·κ(H)·cancel is the error bound of tests/support/oracle.hpp. \"translated\" is the "
              "worst difference to the model at the origin (pure translation), \"rotated\" with a random "
              "rotation as well.\n\n");
  std::printf("| weld length [m] | mass ratio | models | translated | rotated | vs oracle | max err/B | "
              "max κ(H) | singular pivots |\n|---|---|---|---|---|---|---|---|---|\n");
  for (double weld : {0.0, 30.0, 1e3}) {
    for (double ratio : {1.0, 1e2, 1e3}) {
      double wt = 0, wr = 0, wo = 0, wb = 0, wk = 0;
      long pivots = 0;
      for (int i = 0; i < models; ++i) {
        std::mt19937 rng(1000 + i);
        RandomModelOptions o;
        o.n = 8 + i % 25;
        o.fixed_fraction = std::vector<double>{0.0, 0.1, 0.3, 0.6}[i % 4];
        o.mass_ratio = ratio;
        o.weld_length = weld;
        const auto spec = random_model_spec(rng, o);
        const auto near = build_model(spec);
        const State st = testing::random_state(*near, i + 1);
        Data d0(*near);
        const Eigen::VectorXd q0 = forward_dynamics(*near, d0, st);
        for (int p = 0; p < 3; ++p) {
          const Mat3 Rw = p == 2 ? random_rotation(rng) : Mat3::Identity();
          const Vec3 t = (p == 0 ? 1e3 : 1e6) * random_direction(rng);
          const auto far = build_model(placed(spec, Rw, t));
          const State sf = rotated_state(*far, st, Rw);
          Data d(*far);
          forward_dynamics(*far, d, sf);
          pivots += d.diag.singular_pivots;
          const auto orc = oracle_forward_dynamics(*far, sf);
          const double B = testing::qdd_error_bound(orc, sf, testing::kBoundC);
          const double e0 = rel_err(d.qdd, q0), eo = rel_err(d.qdd, orc.qdd);
          (p == 2 ? wr : wt) = std::max(p == 2 ? wr : wt, e0);
          wo = std::max(wo, eo);
          wb = std::max(wb, eo / B);
          wk = std::max(wk, testing::mass_matrix_condition(orc));
        }
      }
      std::printf("| %g | %g | %d | %.2e | %.2e | %.2e | %.2e | %.2e | %ld |\n", weld, ratio, models, wt,
                  wr, wo, wb, wk, pivots);
      std::fflush(stdout);
    }
  }
}

// Light bodies next to heavy ones (the Cα–H body of a torsion-angle protein: smallest principal
// inertia ~1000× below its neighbours'): stress::light_body_chain(32, r), every third link with its
// smallest principal moment / r and its mass / √r; error vs the oracle and vs the bound.
void section_light() {
  std::printf("\n## Light bodies: every third link of a 32-link chain with its smallest principal inertia / r\n\n");
  std::printf("B = 10·n·ε·κ(H)·cancel (tests/support/oracle.hpp); the target is 1e-12 "
              "(NearSingular.LightBodiesBetweenNormalLinks asserts min(1e-12, B) for r ≤ 1e4).\n\n");
  std::printf("| r | κ(H) | error vs oracle | err / B | singular pivots |\n|---|---|---|---|---|\n");
  for (double r : {1.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6}) {
    auto model = light_body_chain(32, r);   // tests/stress/stress_scenes.hpp
    const State st = clean_state(*model, 3);
    const auto orc = oracle_forward_dynamics(*model, st);
    const auto fd = dca(*model, st);
    const double e = rel_err(fd.qdd, orc.qdd);
    std::printf("| %g | %.2e | %.2e | %.2e | %lld |\n", r, testing::mass_matrix_condition(orc), e,
                e / testing::qdd_error_bound(orc, st, testing::kBoundC),
                static_cast<long long>(fd.singular_pivots));
    std::fflush(stdout);
  }
}

void section_ratio(int n, int max_exp, double tol) {
  std::printf("\n## Mass ratio between neighbouring links (chain of %d, masses 1, r, 1, r, …)\n\n", n);
  std::printf("| r | rel err vs oracle | singular pivots | finite |\n|---|---|---|---|\n");
  double lo = NAN, hi = NAN;
  for (int e = -max_exp; e <= max_exp; ++e) {
    const double r = std::pow(10.0, e);
    std::shared_ptr<const Model> m;
    try {
      m = mass_ratio_chain(n, r);
    } catch (const std::exception& ex) {
      std::printf("| 1e%+d | rejected by ModelBuilder: %s | | |\n", e, ex.what());
      continue;
    }
    const State st = clean_state(*m, 7);
    const auto fd = dca(*m, st);
    const double err = rel_err(fd.qdd, oracle_forward_dynamics(*m, st).qdd);
    std::printf("| 1e%+d | %.3e | %lld | %s |\n", e, err, static_cast<long long>(fd.singular_pivots),
                all_finite(fd.qdd) ? "yes" : "no");
    std::fflush(stdout);
    const bool ok = err <= tol;
    if (!ok && e < 0) lo = r;   // last failing ratio below 1
    if (!ok && e > 0 && std::isnan(hi)) hi = r;
  }
  std::printf("\nLIMIT ratio: error > %g for r <= %.0e and for r >= %.0e (NaN: none in range)\n", tol, lo, hi);
}

void section_coaxial(int n, double tol) {
  std::printf("\n## Aligned (coaxial) joint axes: chain of %d, every third body a rod between two coaxial joints\n", n);
  std::printf("axial = that rod's axial inertia / normal value; cond(H) from the oracle's mass matrix.\n\n");
  std::printf("| axial | cond(H) | rel err vs oracle | singular pivots | finite |\n|---|---|---|---|---|\n");
  double limit = NAN;
  for (int e = 0; e >= -16; e -= 2) {
    const double a = std::pow(10.0, e);
    std::shared_ptr<const Model> m;
    try {
      m = coaxial_chain(n, a);
    } catch (const std::exception& ex) {
      std::printf("| 1e%d | | rejected by ModelBuilder: %s | | |\n", e, ex.what());
      if (std::isnan(limit)) limit = a;
      continue;
    }
    const State st = clean_state(*m, 9);
    const auto fd = dca(*m, st);
    const auto orc = oracle_forward_dynamics(*m, st);
    Eigen::SelfAdjointEigenSolver<testing::MatXL> es(orc.H);
    const double cond = static_cast<double>(es.eigenvalues().maxCoeff() / es.eigenvalues().minCoeff());
    const double err = rel_err(fd.qdd, orc.qdd);
    std::printf("| 1e%d | %.2e | %.3e | %lld | %s |\n", e, cond, err,
                static_cast<long long>(fd.singular_pivots), all_finite(fd.qdd) ? "yes" : "no");
    std::fflush(stdout);
    if (std::isnan(limit) && !(err <= tol)) limit = a;
  }
  if (std::isnan(limit)) std::printf("\nLIMIT coaxial: within %g down to axial = 1e-16\n", tol);
  else std::printf("\nLIMIT coaxial: error > %g from axial = %g\n", tol, limit);
}

void section_size(int max_n) {
  std::printf("\n## Error vs the oracle as the model grows (random state, seed 1)\n\n");
  std::printf("| model | n | rel err vs oracle |\n|---|---|---|\n");
  for (const char* name : {"chain", "binary_tree"})
    for (int n = 16; n <= max_n; n *= 4) {
      auto m = scene_at(name, n, Vec3::Zero());
      const State st = clean_state(*m, 1);
      std::printf("| %s | %d | %.3e |\n", name, n,
                  rel_err(dca(*m, st).qdd, oracle_forward_dynamics(*m, st).qdd));
      std::fflush(stdout);
    }
}

void section_long(int max_log2, double tol) {
  std::printf("\n## Long chains: finite q̈ and agreement with the same chain shifted by (1e3, -2e3, 5e2) m\n");
  std::printf("(random state seed 13; the oracle is O(n^3) and not run here)\n\n");
  std::printf("| bodies | finite | singular pivots | max abs q̈ | rel diff shifted | ms per call |\n|---|---|---|---|---|---|\n");
  double limit = NAN;
  for (int l = 10; l <= max_log2; l += 2) {
    const int n = 1 << l;
    auto m = scene_at("chain", n, Vec3::Zero());
    auto ms = scene_at("chain", n, Vec3(1e3, -2e3, 5e2));
    const State st = clean_state(*m, 13);
    Data d(*m);
    const auto t0 = Clock::now();
    forward_dynamics(*m, d, st);
    const double ms_call = 1e3 * seconds_since(t0);
    const Eigen::VectorXd q1 = d.qdd;
    const auto fd2 = dca(*ms, st);
    const bool fin = all_finite(q1) && all_finite(fd2.qdd);
    const double diff = rel_err(fd2.qdd, q1);
    std::printf("| %d | %s | %lld | %.3e | %.3e | %.1f |\n", n, fin ? "yes" : "no",
                static_cast<long long>(d.diag.singular_pivots), q1.cwiseAbs().maxCoeff(), diff, ms_call);
    std::fflush(stdout);
    if (std::isnan(limit) && (!fin || !(diff <= tol))) limit = n;
  }
  if (std::isnan(limit)) std::printf("\nLIMIT long: finite and within %g up to 2^%d bodies\n", tol, max_log2);
  else std::printf("\nLIMIT long: fails (non-finite or > %g) from %g bodies\n", tol, limit);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"haptree numerical stress report (markdown on stdout)"};
  std::vector<std::string> sections{"isa", "drift", "far", "welds", "light", "ratio", "coaxial", "size", "long"};
  int weld_models = 100;
  int ratio_n = 16, ratio_max_exp = 12, coaxial_n = 15, oracle_max_n = 1024, max_log2 = 18;
  DriftSettings drift;
  double tol = 1e-6;
  app.add_option("--sections", sections, "isa drift far welds light ratio coaxial size long")->capture_default_str();
  app.add_option("--weld-models", weld_models, "welds: random models per (weld length, mass ratio)")
      ->capture_default_str()->check(CLI::Range(1, 100000));
  app.add_option("--steps", drift.steps, "drift: steps per dt")->capture_default_str();
  app.add_option("--dt-s", drift.dts, "drift: time steps [s]")->capture_default_str();
  app.add_option("--integrator", drift.integrators, "drift: euler (semi-implicit) and/or rk4")
      ->capture_default_str();
  app.add_option("--drift-scenes", drift.scenes, "drift: fall (gravity, from rest) and/or tumble (no gravity)")
      ->capture_default_str();
  app.add_option("--horizon-s", drift.horizon_s, "drift: short fixed horizon [s] (0: skip)")->capture_default_str();
  app.add_option("--blowup-factor", drift.blowup_factor,
                 "drift: blow-up when |E - E0| > this x the kinetic-energy bound")->capture_default_str();
  app.add_option("--max-halvings", drift.max_halvings,
                 "drift: halvings below the smallest dt while nothing survives")->capture_default_str();
  app.add_flag("!--no-limit-search", drift.limit_search, "drift: only the listed dt");
  app.add_option("--max-wall-s", drift.max_wall_s,
                 "drift: wall-clock limit per run [s] (0: none); a cut run is reported as such")
      ->capture_default_str();
  app.add_option("--progress-steps", drift.progress_every, "drift: progress line (stderr) every N steps")
      ->capture_default_str();
  app.add_option("--tol", tol, "relative q̈ error that counts as broken (far, ratio, coaxial, long)")->capture_default_str();
  app.add_option("--ratio-n", ratio_n, "ratio: chain length")->capture_default_str();
  app.add_option("--ratio-max-exp", ratio_max_exp, "ratio: sweep 1e-k … 1e+k")->capture_default_str();
  app.add_option("--coaxial-n", coaxial_n, "coaxial: chain length")->capture_default_str();
  app.add_option("--oracle-max-n", oracle_max_n, "size: largest n checked against the oracle")->capture_default_str();
  app.add_option("--max-log2", max_log2, "long: largest chain is 2^k bodies")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  spdlog::set_default_logger(spdlog::stderr_color_mt("stress_report"));   // stdout: the markdown
  spdlog::info("stress_report: sections {}", fmt::join(sections, ","));
  std::printf("# haptree stress report\n");
  for (const auto& s : sections) {
    const auto t0 = Clock::now();
    if (s == "isa") section_isa();
    else if (s == "drift") section_drift(drift);
    else if (s == "far") section_far(tol);
    else if (s == "welds") section_welds(weld_models);
    else if (s == "light") section_light();
    else if (s == "ratio") section_ratio(ratio_n, ratio_max_exp, tol);
    else if (s == "coaxial") section_coaxial(coaxial_n, tol);
    else if (s == "size") section_size(oracle_max_n);
    else if (s == "long") section_long(max_log2, tol);
    else {
      spdlog::error("unknown section '{}'", s);
      return 2;
    }
    spdlog::info("section {} took {:.1f} s", s, seconds_since(t0));
  }
  return 0;
}
