// The DCA's passes and their parallel schedule (docs/algorithms.md §5, §7). Bottom-up, node ids
// descending (a child's id is above its parent's): each node's coefficients from its children's,
// in the form the node takes (a leaf, a welded cluster's node in inertia form, a light leaf's
// join, or the mobility form). Top-down, ids ascending from f = 0 at every root: each node's
// handle forces split into its children's, and q̈ of its joint. forward_dynamics is kinematics,
// both passes and one step of refinement. With set_dca_threads(n > 1) the subtrees of a
// ParallelCut are the tasks of an OpenMP loop (dynamic schedule): bottom-up the tasks, then the
// nodes above the cut; top-down the nodes above the cut, then the tasks. Every node runs the
// serial kernel on the same inputs, so the result is the serial one, bit for bit.
#include <sched.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>

#include "haptree/dca_detail.hpp"

namespace haptree {

namespace {

inline void bottom_up_node(const Model& m, Data& d, const State& st, int node) {
  dca_bottom_up_node(m, d, node, st.tau);
}

}  // namespace

void dca_bottom_up(const Model& m, Data& d, const State& st) noexcept {
  HAPTREE_DCA_DISPATCH(dca_bottom_up, m, d, st);
  const auto& t = m.tree;
  dca_cluster_offsets(m, d);
  std::int64_t count = 0;
  for (int node = t.nnodes() - 1; node >= 0; --node) {
    bottom_up_node(m, d, st, node);
    ++count;
  }
  d.diag.nodes_bottom_up = count;
}

void dca_top_down(const Model& m, Data& d) noexcept {
  HAPTREE_DCA_DISPATCH(dca_top_down, m, d);
  const auto& t = m.tree;
  for (int root : t.roots)
    for (int s = 0; s < t.handle_num[root]; ++s) d.f(root, s).setZero();
  std::int64_t count = 0;
  for (int node = 0; node < t.nnodes(); ++node) {
    if (t.is_leaf(node)) continue;
    dca_top_down_node(m, d, node);
    ++count;
  }
  d.diag.nodes_top_down = count;
  for (int i = 0; i < m.nv; ++i)
    if (!std::isfinite(d.qdd(i))) { ++d.diag.nonfinite; break; }
}

namespace {

// One task of the parallel passes: the subtree [lo, hi), ids descending; each leaf first computes
// its body's inertia terms (one sweep over memory instead of two).
void bottom_up_task(const Model& m, Data& d, const State& st, int lo, int hi) {
  const auto& t = m.tree;
  for (int node = hi - 1; node >= lo; --node) {
    if (t.is_leaf(node) && t.body[node] > 0) body_inertia_terms(m, d, st, t.body[node]);
    bottom_up_node(m, d, st, node);
  }
}
void top_down_task(const Model& m, Data& d, int lo, int hi) {
  const auto& t = m.tree;
  for (int node = lo; node < hi; ++node)
    if (!t.is_leaf(node)) dca_top_down_node(m, d, node);
}

// forward_dynamics on d.dca_threads threads over d.dca_cut (ParallelCut). Every node runs the same
// kernel on the same inputs as in the serial passes, so the result is bit-for-bit the same.
void parallel_passes(const Model& m, Data& d, const State& st) {
  const auto& t = m.tree;
  const ParallelCut& cut = d.dca_cut;
  const int ntask = static_cast<int>(cut.lo.size());
  d.v[0].setZero();
  for (int k = 1; k < m.nbodies; ++k) joint_motion_terms(m, d, k, st.qd, d.v[m.parent[k]]);
  dca_cluster_offsets(m, d);
#pragma omp parallel for schedule(dynamic, 1) num_threads(d.dca_threads)
  for (int i = 0; i < ntask; ++i) bottom_up_task(m, d, st, cut.lo[i], cut.hi[i]);
  for (size_t i = cut.top.size(); i-- > 0;) bottom_up_node(m, d, st, cut.top[i]);
  d.diag.nodes_bottom_up = t.nnodes();

  for (int root : t.roots)
    for (int s = 0; s < t.handle_num[root]; ++s) d.f(root, s).setZero();
  for (int node : cut.top) dca_top_down_node(m, d, node);
#pragma omp parallel for schedule(dynamic, 1) num_threads(d.dca_threads)
  for (int i = 0; i < ntask; ++i) top_down_task(m, d, cut.lo[i], cut.hi[i]);
  std::int64_t internal = 0;
  for (int node = 0; node < t.nnodes(); ++node) internal += t.is_leaf(node) ? 0 : 1;
  d.diag.nodes_top_down = internal;
  for (int i = 0; i < m.nv; ++i)
    if (!std::isfinite(d.qdd(i))) { ++d.diag.nonfinite; break; }
}

int cpus_available() {
  cpu_set_t set;
  if (sched_getaffinity(0, sizeof(set), &set) != 0) return 1;
  return CPU_COUNT(&set);
}

}  // namespace

int set_dca_threads(const Model& m, Data& d, int threads) {
#ifdef _OPENMP
  if (threads == 0) {
    // A free core: the 1-minute load average (this thread included) leaves at least one CPU idle.
    // On a loaded machine the second thread waits for a core at every barrier: 2 threads at load
    // 20 on 2 CPUs took 5x the serial wall time.
    const int cpus = cpus_available();
    double load = 1e9;
    const bool free_core = getloadavg(&load, 1) == 1 && load <= cpus - 1;
    threads = m.tree.nnodes() >= kDcaParallelMinNodes && cpus >= 2 && free_core ? cpus : 1;
  }
#else
  threads = 1;   // built without OpenMP
#endif
  d.dca_threads = std::max(1, threads);
  // 4 tasks per thread so a dynamic schedule evens out unequal subtrees; none below 64 nodes.
  d.dca_cut = parallel_cut(m.tree, d.dca_threads == 1 ? 1 : 4 * d.dca_threads, 64);
  return d.dca_threads;
}

const Eigen::VectorXd& forward_dynamics(const Model& m, Data& d, const State& st) noexcept {
  HAPTREE_DCA_DISPATCH(forward_dynamics, m, d, st);
  forward_kinematics(m, d, st.q);
  if (d.dca_threads > 1) {
    parallel_passes(m, d, st);
  } else {
    body_dynamics_terms(m, d, st);
    dca_bottom_up(m, d, st);
    dca_top_down(m, d);
  }
  if (d.refine != Refinement::kOff) {   // serial even after parallel passes
    if (!refinement_sized(m, d)) size_refinement(m, d);   // Data::refine assigned, not set_refinement
    detail::refine_step(m, d, st);
  }
  return d.qdd;
}

// One node as dca_bottom_up assembles it (also adaptive.cpp's, for the nodes it reassembles).
void dca_bottom_up_node(const Model& m, Data& d, int node, const Eigen::VectorXd& tau) noexcept {
  HAPTREE_DCA_DISPATCH(dca_bottom_up_node, m, d, node, tau);
  if (m.tree.is_leaf(node)) {
    dca_leaf(m, d, node);
  } else if (m.cluster_index[node] >= 0) {
    detail::assemble_joint_terms(m, d, node, tau);   // W, β for coupling and metric readers
    detail::assemble_inertia_form(m, d, node, tau);
  } else {
    dca_assemble(m, d, node, tau);
  }
}

#if !defined(HAPTREE_ISA_COPY)   // the baseline copy only
#if HAPTREE_DCA_AVX2
static_assert(EIGEN_MAX_STATIC_ALIGN_BYTES == 16 && EIGEN_MAX_ALIGN_BYTES == 16,
              "haptree_isa_copy builds the x86-64-v3 copies with this alignment: it must be the baseline's");
#endif
const detail::DcaKernels* detail::dca_kernels() noexcept {
#if HAPTREE_DCA_AVX2
  if (isa::active() >= isa::Level::avx2) return haptree_dca_kernels_avx2();
#endif
  return nullptr;
}

isa::Level dca_level() noexcept {
#if HAPTREE_DCA_AVX2
  return detail::dca_kernels() ? isa::Level::avx2 : isa::Level::generic;
#elif defined(__AVX512F__) && defined(__AVX512VL__)
  return isa::Level::avx512;   // the whole library compiled for it (-march)
#elif defined(__AVX2__) && defined(__FMA__)
  return isa::Level::avx2;
#else
  return isa::Level::generic;
#endif
}
#endif

}  // namespace haptree
