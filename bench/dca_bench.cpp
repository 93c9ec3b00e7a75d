// dca_bench: cost of one full forward-dynamics evaluation (forward kinematics, body terms, DCA
// bottom-up and top-down passes) with haptree's divide-and-conquer ABA.
//
//   dca_bench --benchmark_repetitions=3 --benchmark_report_aggregates_only=true
//   dca_bench --benchmark_out=dca.csv --benchmark_out_format=csv      (CSV for plots)
//
// Counters: bodies, dof, and s_per_body (time per call / bodies; printed with an SI prefix,
// e.g. 350n = 0.35 µs per body).
#include <benchmark/benchmark.h>

#include <time.h>

#include <algorithm>
#include <functional>
#include <map>
#include <memory>
#include <queue>
#include <vector>
#include <random>
#include <string>
#include <utility>

#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"

namespace {

using haptree::Model;

struct Case {
  std::shared_ptr<const Model> model;
  std::unique_ptr<haptree::State> state;
  std::unique_ptr<haptree::Data> data;
};

// A non-trivial state: angles and rates in [-1, 1], small torques, unit quaternions.
void randomise(const Model& m, haptree::State& st, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1);
  st.q = haptree::neutral_configuration(m);
  for (int k = 1; k < m.nbodies; ++k) {
    const int a = m.q_adr[k];
    switch (m.joint_type[k]) {
      case haptree::JointType::kRevolute:
      case haptree::JointType::kPrismatic: st.q(a) = u(rng); break;
      case haptree::JointType::kSpherical:
      case haptree::JointType::kFree: {
        const int qa = m.joint_type[k] == haptree::JointType::kFree ? a + 3 : a;
        haptree::Quat q(u(rng), u(rng), u(rng), u(rng));
        q.normalize();
        st.q(qa) = q.w(); st.q(qa + 1) = q.x(); st.q(qa + 2) = q.y(); st.q(qa + 3) = q.z();
        break;
      }
      case haptree::JointType::kFixed: break;
    }
  }
  for (int i = 0; i < m.nv; ++i) {
    st.qd(i) = u(rng);
    st.tau(i) = 0.1 * u(rng);
  }
}

Case& get_case(const std::string& scene, int n, int max_children = 0) {
  static std::map<std::pair<std::string, int>, Case> cache;
  auto key = std::make_pair(scene + "/" + std::to_string(max_children), n);
  auto it = cache.find(key);
  if (it != cache.end()) return it->second;
  haptree::SceneOptions o;
  o.n = n;
  o.seed = 1;
  o.build.max_children = max_children;
  Case c;
  c.model = haptree::make_scene(scene, o);
  c.state = std::make_unique<haptree::State>(*c.model);
  c.data = std::make_unique<haptree::Data>(*c.model);
  randomise(*c.model, *c.state, 42);
  return cache.emplace(key, std::move(c)).first->second;
}

// threads: haptree::set_dca_threads (1 = serial, 0 = automatic); set per run, the cases are shared.
void run(benchmark::State& bs, const std::string& scene, int n, int max_children = 0,
         int threads = 1) {
  Case& c = get_case(scene, n, max_children);
  const Model& m = *c.model;
  bs.counters["threads"] = haptree::set_dca_threads(m, *c.data, threads);
  for (auto _ : bs) {
    const Eigen::VectorXd& qdd = haptree::forward_dynamics(m, *c.data, *c.state);
    benchmark::DoNotOptimize(qdd.data());
    benchmark::ClobberMemory();
  }
  const double bodies = m.nbodies - 1;
  bs.counters["bodies"] = bodies;
  bs.counters["dof"] = m.nv;
  bs.counters["s_per_body"] = benchmark::Counter(
      bodies, benchmark::Counter::kIsIterationInvariantRate | benchmark::Counter::kInvert);
  if (c.data->diag.singular_pivots > 0) bs.SkipWithError("singular joint system");
}

void BM_Chain(benchmark::State& bs) { run(bs, "chain", static_cast<int>(bs.range(0))); }
void BM_BinaryTree(benchmark::State& bs) { run(bs, "binary_tree", static_cast<int>(bs.range(0))); }
void BM_ProteinLike(benchmark::State& bs) { run(bs, "protein_like", 857); }
// A hub with n-1 leaves, split into rigid pieces (max_children = 4) and assembled in inertia form.
// "bodies" counts the pieces too (2n-2 bodies for n-1 DOF leaves + the spherical hub).
void BM_StarSplit(benchmark::State& bs) { run(bs, "star", static_cast<int>(bs.range(0)), 4); }

// The parallel passes on 2 threads: wall time and process CPU time (both threads).
void BM_Chain2T(benchmark::State& bs) { run(bs, "chain", static_cast<int>(bs.range(0)), 0, 2); }
void BM_BinaryTree2T(benchmark::State& bs) {
  run(bs, "binary_tree", static_cast<int>(bs.range(0)), 0, 2);
}
void BM_ProteinLike2T(benchmark::State& bs) { run(bs, "protein_like", 857, 0, 2); }

double thread_cpu_us() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e6 + ts.tv_nsec * 1e-3;
}

// Parallel passes on p free cores, from measured pieces. This 2-core machine is shared
// by several processes, so a wall-clock speed-up of 2 threads measures the load, not the code.
// Instead each piece of the schedule (haptree::parallel_cut for p threads) is timed on one thread
// by its CPU clock: the serial part (kinematics, velocities), every task (its leaves' inertia terms,
// bottom-up, top-down) and the top nodes; then T_p = serial + top + the longest-first assignment
// of the task times to p threads. Counters: serial_us, work_us (one thread), T2_us, T16_us, and
// the modelled speed-ups S2, S16. No cluster (inertia-form) nodes in these scenes.
void span_model(benchmark::State& bs, const std::string& scene, int n) {
  Case& c = get_case(scene, n);
  const Model& m = *c.model;
  haptree::Data& d = *c.data;
  const haptree::State& st = *c.state;
  const auto& t = m.tree;
  haptree::set_dca_threads(m, d, 1);
  double serial = 0, inertia_per_body = 0, work = 0;
  double T[2] = {0, 0};
  const int P[2] = {2, 16};
  for (auto _ : bs) {
    double c0 = thread_cpu_us();
    haptree::forward_kinematics(m, d, st.q);
    d.v[0].setZero();
    for (int k = 1; k < m.nbodies; ++k) haptree::joint_motion_terms(m, d, k, st.qd, d.v[m.parent[k]]);
    double c1 = thread_cpu_us();
    serial = c1 - c0;
    haptree::body_dynamics_terms(m, d, st);   // velocities again + the per-body inertia terms
    inertia_per_body = std::max(0.0, (thread_cpu_us() - c1) - serial) / (m.nbodies - 1);
    for (int pi = 0; pi < 2; ++pi) {
      const haptree::ParallelCut cut = haptree::parallel_cut(t, 4 * P[pi], 64);
      std::vector<double> task(cut.lo.size(), 0.0);
      for (size_t i = 0; i < cut.lo.size(); ++i) {
        const double a = thread_cpu_us();
        for (int node = cut.hi[i] - 1; node >= cut.lo[i]; --node)
          if (t.is_leaf(node)) haptree::dca_leaf(m, d, node);
          else haptree::dca_assemble(m, d, node, st.tau);
        task[i] = thread_cpu_us() - a;
        for (int node = cut.lo[i]; node < cut.hi[i]; ++node)
          if (t.is_leaf(node) && t.body[node] > 0) task[i] += inertia_per_body;
      }
      double a = thread_cpu_us();
      for (size_t i = cut.top.size(); i-- > 0;) haptree::dca_assemble(m, d, cut.top[i], st.tau);
      for (int r : t.roots)
        for (int s = 0; s < t.handle_num[r]; ++s) d.f(r, s).setZero();
      for (int node : cut.top) haptree::dca_top_down_node(m, d, node);
      double top = thread_cpu_us() - a;
      for (size_t i = 0; i < cut.lo.size(); ++i) {
        a = thread_cpu_us();
        for (int node = cut.lo[i]; node < cut.hi[i]; ++node)
          if (!t.is_leaf(node)) haptree::dca_top_down_node(m, d, node);
        task[i] += thread_cpu_us() - a;
      }
      std::sort(task.begin(), task.end(), std::greater<>());
      std::priority_queue<double, std::vector<double>, std::greater<>> load;
      for (int k = 0; k < P[pi]; ++k) load.push(0);
      double sum = 0;
      for (double x : task) {
        const double l = load.top();
        load.pop();
        load.push(l + x);
        sum += x;
      }
      double span = 0;
      for (; !load.empty(); load.pop()) span = std::max(span, load.top());
      T[pi] = serial + top + span;
      if (pi == 0) work = serial + top + sum;
    }
    benchmark::DoNotOptimize(d.qdd.data());
  }
  bs.counters["serial_us"] = serial;
  bs.counters["work_us"] = work;
  bs.counters["T2_us"] = T[0];
  bs.counters["T16_us"] = T[1];
  bs.counters["S2"] = work / T[0];
  bs.counters["S16"] = work / T[1];
}
void BM_SpanChain(benchmark::State& bs) { span_model(bs, "chain", static_cast<int>(bs.range(0))); }
void BM_SpanBinaryTree(benchmark::State& bs) {
  span_model(bs, "binary_tree", static_cast<int>(bs.range(0)));
}
void BM_SpanProteinLike(benchmark::State& bs) { span_model(bs, "protein_like", 857); }

void sizes(benchmark::internal::Benchmark* b) {
  for (int n = 16; n <= 65536; n *= 4) b->Arg(n);
}

BENCHMARK(BM_Chain)->Apply(sizes)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_BinaryTree)->Apply(sizes)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_ProteinLike)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_Chain2T)->Apply(sizes)->Unit(benchmark::kMicrosecond)->UseRealTime()->MeasureProcessCPUTime();
BENCHMARK(BM_BinaryTree2T)->Apply(sizes)->Unit(benchmark::kMicrosecond)->UseRealTime()->MeasureProcessCPUTime();
BENCHMARK(BM_ProteinLike2T)->Unit(benchmark::kMicrosecond)->UseRealTime()->MeasureProcessCPUTime();
BENCHMARK(BM_SpanChain)->Arg(1024)->Arg(65536)->Unit(benchmark::kMicrosecond)->Iterations(5);
BENCHMARK(BM_SpanBinaryTree)->Arg(1024)->Arg(65536)->Unit(benchmark::kMicrosecond)->Iterations(5);
BENCHMARK(BM_SpanProteinLike)->Unit(benchmark::kMicrosecond)->Iterations(5);
BENCHMARK(BM_StarSplit)->Arg(64)->Arg(256)->Arg(1024)->Arg(4096)->Unit(benchmark::kMicrosecond);

}  // namespace

BENCHMARK_MAIN();
