// Coupling benchmark (plain runner): µs per coupling_forces() call (median, p99 of individually timed
// calls; median over back-to-back 100-call batches), nodes read,
// |U| and snapshot payload bytes vs n for balanced chains n = 2^4 … 2^16 and the 857-DOF
// protein-like tree, with n_f = 1, 2, 4, 8 simultaneous grabs. Prints a Markdown table.
//   coupling_bench --calls 2000 --sets 16 --max-log2 16
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "haptree/coupling.hpp"
#include "haptree/dca.hpp"
#include "haptree/fp_env.hpp"
#include "haptree/scenes.hpp"

namespace {

using namespace haptree;
using Clock = std::chrono::steady_clock;

// Random revolute/prismatic angles, velocities and torques (other joints stay neutral).
State bench_state(const Model& m, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  State st(m);
  for (int k = 1; k < m.nbodies; ++k) {
    if (m.joint_type[k] != JointType::kRevolute && m.joint_type[k] != JointType::kPrismatic) continue;
    st.q(m.q_adr[k]) = u(rng);
    st.qd(m.v_adr[k]) = 0.3 * u(rng);
    st.tau(m.v_adr[k]) = 0.1 * u(rng);
  }
  return st;
}

struct Row {
  std::string scene;
  int n = 0, dofs = 0, nf = 0, depth = 0;
  double median_us = 0, p99_us = 0, mean_us = 0;
  double nodes_mean = 0, u_mean = 0;
  long nodes_max = 0;
  std::size_t bytes_mean = 0, bytes_max = 0;
  std::size_t subnormals = 0;   // subnormal snapshot values, summed over the grab sets
};

bool g_keep_subnormals = false;   // --keep-subnormals: snapshots with subnormal values kept (for comparison)

double percentile(std::vector<double>& v, double p) {
  const std::size_t i = std::min(v.size() - 1, static_cast<std::size_t>(p * (v.size() - 1) + 0.5));
  std::nth_element(v.begin(), v.begin() + i, v.end());
  return v[i];
}

__attribute__((noinline)) CouplingStatus call(const CouplingSnapshot& s, const Vec6* fu,
                                              CouplingWorkspace& ws, Vec6* out) {
  return coupling_forces(s, fu, ws, out);
}

Row run(const std::string& scene, const Model& m, const Data& d, int nf, int sets, int calls,
        unsigned seed) {
  std::mt19937 rng(seed * 31 + nf);
  std::uniform_int_distribution<int> body(1, m.nbodies - 1);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<Vec6> forces(64 * nf);
  for (auto& f : forces) f << 0, 0, 0, 5 * u(rng), 5 * u(rng), 5 * u(rng);
  std::vector<double> per_call;
  per_call.reserve(static_cast<std::size_t>(sets) * calls);
  Row row;
  row.scene = scene;
  row.n = m.nbodies - 1;
  row.dofs = m.nv;
  row.nf = nf;
  row.depth = m.tree.max_depth;
  CouplingSnapshot snap;
  CouplingWorkspace ws;
  std::vector<Vec6> out(nf);
  std::vector<double> batch_mean;
  double nodes_sum = 0, u_sum = 0;
  std::size_t bytes_sum = 0;
  for (int s = 0; s < sets; ++s) {
    std::vector<Grab> grabs;
    for (int g = 0; g < nf; ++g) grabs.push_back(make_grab(d, body(rng), Vec3(0.1 * u(rng), 0.1 * u(rng), 0)));
    make_coupling_snapshot(m, d, grabs, {}, s, 0, snap, !g_keep_subnormals);
    row.subnormals += count_subnormals(snap.values.data(), snap.values.size());
    ws.reserve_for(snap);
    if (call(snap, forces.data(), ws, out.data()) != CouplingStatus::kOk) {
      std::fprintf(stderr, "coupling failed\n");
      std::exit(1);
    }
    nodes_sum += ws.nodes_read;
    row.nodes_max = std::max<long>(row.nodes_max, ws.nodes_read);
    u_sum += snap.ints[2];
    const std::size_t bytes = snapshot_payload_bytes(snap);
    bytes_sum += bytes;
    row.bytes_max = std::max(row.bytes_max, bytes);
    for (int w = 0; w < 200; ++w) call(snap, forces.data() + nf * (w % 64), ws, out.data());   // warm
    for (int c = 0; c < calls; ++c) {
      const auto t0 = Clock::now();
      call(snap, forces.data() + nf * (c % 64), ws, out.data());
      const auto t1 = Clock::now();
      per_call.push_back(std::chrono::duration<double, std::micro>(t1 - t0).count());
    }
    for (int b = 0; b + 100 <= calls; b += 100) {   // back-to-back batches of 100 calls, no timer inside
      const auto b0 = Clock::now();
      for (int c = b; c < b + 100; ++c) call(snap, forces.data() + nf * (c % 64), ws, out.data());
      batch_mean.push_back(std::chrono::duration<double, std::micro>(Clock::now() - b0).count() / 100);
    }
  }
  row.median_us = percentile(per_call, 0.5);
  row.p99_us = percentile(per_call, 0.99);
  row.mean_us = batch_mean.empty() ? 0 : percentile(batch_mean, 0.5);
  row.nodes_mean = nodes_sum / sets;
  row.u_mean = u_sum / sets;
  row.bytes_mean = bytes_sum / sets;
  return row;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"O(log n) coupling benchmark: µs per coupling_forces call, nodes read, snapshot bytes"};
  int calls = 2000, sets = 16, min_log2 = 4, max_log2 = 16;
  std::vector<int> nfs{1, 2, 4, 8};
  app.add_option("--calls", calls, "timed calls per grab set")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--sets", sets, "random grab sets per (scene, n_f)")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--min-log2", min_log2, "smallest chain: 2^min bodies")->capture_default_str()->check(CLI::Range(1, 20));
  app.add_option("--max-log2", max_log2, "largest chain: 2^max bodies")->capture_default_str()->check(CLI::Range(1, 20));
  app.add_option("--nf", nfs, "numbers of simultaneous grabs")->capture_default_str();
  bool ftz = false;
  app.add_flag("--ftz", ftz, "set flush-to-zero/denormals-are-zero (MXCSR) in the benchmark thread");
  app.add_flag("--keep-subnormals", g_keep_subnormals,
               "build snapshots without flushing subnormal values (to measure what flushing them saves)");
  CLI11_PARSE(app, argc, argv);
  std::unique_ptr<ScopedFlushDenormals> fp;
  if (ftz) fp = std::make_unique<ScopedFlushDenormals>();
  std::printf("snapshots: %s; FTZ/DAZ in this thread: %s\n",
              g_keep_subnormals ? "subnormals kept" : "subnormals flushed (default)",
              ScopedFlushDenormals::active() ? "on" : "off");

  // Timer overhead (steady_clock pair), for reading the per-call figures.
  std::vector<double> empty(20000);
  for (auto& e : empty) {
    const auto t0 = Clock::now();
    const auto t1 = Clock::now();
    e = std::chrono::duration<double, std::micro>(t1 - t0).count();
  }
  std::printf("timer overhead (steady_clock pair): median %.3f µs\n\n", percentile(empty, 0.5));
  std::printf("| scene | n bodies | DOF | tree depth | n_f | median µs | p99 µs | batch µs/call (median of 100-call batches) | nodes read (mean/max) | mean size of U | snapshot bytes (mean/max) | subnormal values (all sets) |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  auto print = [](const Row& r) {
    std::printf("| %s | %d | %d | %d | %d | %.3f | %.3f | %.3f | %.1f / %ld | %.1f | %zu / %zu | %zu |\n",
                r.scene.c_str(), r.n, r.dofs, r.depth, r.nf, r.median_us, r.p99_us, r.mean_us,
                r.nodes_mean, r.nodes_max, r.u_mean, r.bytes_mean, r.bytes_max, r.subnormals);
    std::fflush(stdout);
  };
  for (int e = min_log2; e <= max_log2; ++e) {
    SceneOptions o;
    o.n = 1 << e;
    o.seed = 1;
    auto model = make_chain(o);
    Data d(*model);
    forward_dynamics(*model, d, bench_state(*model, 7));
    for (int nf : nfs) print(run("chain", *model, d, nf, sets, calls, 7));
  }
  auto protein = make_protein_like({});
  Data dp(*protein);
  forward_dynamics(*protein, dp, bench_state(*protein, 7));
  for (int nf : nfs) print(run("protein_like", *protein, dp, nf, sets, calls, 7));
  return 0;
}
