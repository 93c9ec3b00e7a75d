// stress_report: the longer numerical-stability report behind docs/accuracy_and_stability.md.
// Sections (all by default):
//   drift    energy drift of the conservative 857-DOF protein-like run (semi-implicit Euler) over
//            --steps steps at several dt, then a dt sweep (doubling) that finds where it blows up;
//   far      q̈ of models placed 10^3 … 10^15 m from the origin against the same model at the origin
//            (and what the world-origin long-double oracle does there);
//   ratio    mass ratio 10^-k … 10^k between neighbouring links: error vs the long-double oracle;
//   coaxial  aligned (coaxial) joint axes with a vanishing axial inertia: error vs the oracle;
//   size     error vs the oracle as chains grow (n = 16 … --oracle-max-n);
//   long     chains of 2^10 … 2^--max-log2 bodies: finite q̈, agreement with a shifted origin, time.
// Every "limit" reported is the first sweep value at which the stated criterion fails.
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <Eigen/Eigenvalues>
#include <chrono>
#include <cstdio>

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

void print_drift_row(double dt, const DriftResult& r, double wall) {
  char tn[32] = "never";
  if (r.t_nonfinite >= 0) std::snprintf(tn, sizeof tn, "%.4g", r.t_nonfinite);
  std::printf("| %g | %d | %g | %.3e | %.3e | %.3e | %.3e | %s | %.1f |\n", dt, r.steps_done,
              r.steps_done * dt, r.max_abs_drift, r.final_drift, r.max_kinetic, r.rel_drift, tn, wall);
  std::fflush(stdout);
}

void section_drift(int steps, const std::vector<double>& dts, double vel_scale, double horizon_s) {
  std::printf("\n## Energy drift: protein-like tree, 857 DOF, gravity on, tau = 0, semi-implicit Euler\n");
  std::printf("Initial state: testing::random_state(seed 11): angles in [-1, 1] rad, rates x %g, no external "
              "forces.\nrel = max_t |E(t) - E(0)| / max_t KE(t) (steps until the state first goes non-finite).\n\n", vel_scale);
  SceneOptions o;
  auto m = make_protein_like(o);
  const State st0 = clean_state(*m, 11, vel_scale);
  const char* head =
      "| dt [s] | steps | simulated [s] | max abs drift [J] | final drift [J] | max KE [J] | rel | "
      "t(non-finite) [s] | wall [s] |\n|---|---|---|---|---|---|---|---|---|\n";
  std::printf("Fixed horizon of %g s simulated:\n\n", horizon_s);
  std::printf(head);
  for (double dt : dts) {
    const auto t0 = Clock::now();
    const auto r = energy_drift(*m, st0, dt, static_cast<int>(std::lround(horizon_s / dt)));
    print_drift_row(dt, r, seconds_since(t0));
  }
  std::printf("\n%d steps per dt:\n\n", steps);
  std::printf(head);
  double longest_ok = NAN;
  for (double dt : dts) {
    const auto t0 = Clock::now();
    const auto r = energy_drift(*m, st0, dt, steps);
    print_drift_row(dt, r, seconds_since(t0));
    if (r.finite && std::isnan(longest_ok)) longest_ok = dt;
  }
  if (std::isnan(longest_ok))
    std::printf("\nLIMIT drift: no dt in the list survives %d steps (times above show where each fails)\n", steps);
  else
    std::printf("\nLIMIT drift: largest dt in the list that stays finite for %d steps: %g s\n", steps, longest_ok);
}

void section_far(double tol) {
  std::printf("\n## Far from the origin: q̈(model at distance D along (1,1,1)/sqrt3) vs q̈(same model at the origin)\n\n");
  std::printf("| model | D [m] | rel diff DCA far vs near | DCA near vs oracle | world-origin oracle far vs near |\n|---|---|---|---|---|\n");
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
  std::vector<std::string> sections{"drift", "far", "ratio", "coaxial", "size", "long"};
  int steps = 100000, ratio_n = 16, ratio_max_exp = 12, coaxial_n = 15,
      oracle_max_n = 1024, max_log2 = 18;
  std::vector<double> dts{1e-3, 5e-4, 2.5e-4, 1e-4};
  double tol = 1e-6, vel_scale = 0, horizon = 0.25;
  app.add_option("--sections", sections, "drift far ratio coaxial size long")->capture_default_str();
  app.add_option("--steps", steps, "drift: steps per dt")->capture_default_str();
  app.add_option("--dt-s", dts, "drift: time steps [s]")->capture_default_str();
  app.add_option("--vel-scale", vel_scale, "drift: initial joint rates x this (0: released from rest)")->capture_default_str();
  app.add_option("--horizon-s", horizon, "drift: short fixed horizon [s]")->capture_default_str();
  app.add_option("--tol", tol, "relative q̈ error that counts as broken (far, ratio, coaxial, long)")->capture_default_str();
  app.add_option("--ratio-n", ratio_n, "ratio: chain length")->capture_default_str();
  app.add_option("--ratio-max-exp", ratio_max_exp, "ratio: sweep 1e-k … 1e+k")->capture_default_str();
  app.add_option("--coaxial-n", coaxial_n, "coaxial: chain length")->capture_default_str();
  app.add_option("--oracle-max-n", oracle_max_n, "size: largest n checked against the oracle")->capture_default_str();
  app.add_option("--max-log2", max_log2, "long: largest chain is 2^k bodies")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  spdlog::info("stress_report: sections {}", fmt::join(sections, ","));
  std::printf("# haptree stress report\n");
  for (const auto& s : sections) {
    const auto t0 = Clock::now();
    if (s == "drift") section_drift(steps, dts, vel_scale, horizon);
    else if (s == "far") section_far(tol);
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
