// dca_bench: cost of one full forward-dynamics evaluation (forward kinematics, body terms, DCA
// bottom-up and top-down passes) with haptree's divide-and-conquer ABA.
//
//   dca_bench --benchmark_repetitions=3 --benchmark_report_aggregates_only=true
//   dca_bench --benchmark_out=dca.csv --benchmark_out_format=csv      (CSV for plots)
//
// Counters: bodies, dof, and s_per_body (time per call / bodies; printed with an SI prefix,
// e.g. 350n = 0.35 µs per body).
#include <benchmark/benchmark.h>

#include <map>
#include <memory>
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

void run(benchmark::State& bs, const std::string& scene, int n, int max_children = 0) {
  Case& c = get_case(scene, n, max_children);
  const Model& m = *c.model;
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

void sizes(benchmark::internal::Benchmark* b) {
  for (int n = 16; n <= 65536; n *= 4) b->Arg(n);
}

BENCHMARK(BM_Chain)->Apply(sizes)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_BinaryTree)->Apply(sizes)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_ProteinLike)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_StarSplit)->Arg(64)->Arg(256)->Arg(1024)->Arg(4096)->Unit(benchmark::kMicrosecond);

}  // namespace

BENCHMARK_MAIN();
