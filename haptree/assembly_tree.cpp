#include "haptree/assembly_tree.hpp"

#include <algorithm>
#include <cstdlib>
#include <functional>
#include <queue>
#include <stdexcept>

namespace haptree {

std::vector<int> AssemblyTree::up_region(int leaf) const {
  std::vector<int> path;
  for (int n = leaf; n >= 0; n = up[n]) path.push_back(n);
  std::reverse(path.begin(), path.end());
  return path;
}

AssemblyTree build_assembly_tree(const std::vector<int>& parent) {
  const int nb = static_cast<int>(parent.size());
  if (nb == 0) throw std::invalid_argument("build_assembly_tree: no bodies");
  for (int k = 1; k < nb; ++k)
    if (parent[k] < 0 || parent[k] >= k)
      throw std::invalid_argument("build_assembly_tree: parent[k] must be < k");

  AssemblyTree t;
  t.leaf_of_body.assign(nb, -1);
  t.owner_of_joint.assign(nb, -1);
  auto new_node = [&](int up_node, int depth) {
    t.P.push_back(-1); t.Q.push_back(-1); t.up.push_back(up_node);
    t.joint.push_back(-1); t.body.push_back(-1); t.depth.push_back(depth);
    t.slot_j.push_back(-1); t.slot_k.push_back(-1);
    return static_cast<int>(t.up.size()) - 1;
  };

  // Explicit stack (stars can be deep); P pushed last so it is created first: pre-order ids.
  struct Item { std::vector<int> bodies; int up_node; bool is_P; };
  std::vector<Item> stack;
  std::vector<int> all(nb);
  for (int k = 0; k < nb; ++k) all[k] = k;
  stack.push_back({std::move(all), -1, false});
  std::vector<int> stamp(nb, -1), size(nb, 0), inQ(nb, -1);
  int stamp_id = 0;

  while (!stack.empty()) {
    Item item = std::move(stack.back());
    stack.pop_back();
    const int depth = item.up_node < 0 ? 0 : t.depth[item.up_node] + 1;
    const int node = new_node(item.up_node, depth);
    if (item.up_node < 0) t.roots.push_back(node);
    else if (item.is_P) t.P[item.up_node] = node;
    else t.Q[item.up_node] = node;
    const std::vector<int>& B = item.bodies;   // ascending; B[0] is the top of the subtree
    if (B.size() == 1) {
      t.body[node] = B[0];
      t.leaf_of_body[B[0]] = node;
      continue;
    }
    ++stamp_id;
    for (int b : B) { stamp[b] = stamp_id; size[b] = 1; }
    for (size_t i = B.size(); i-- > 1;) size[parent[B[i]]] += size[B[i]];
    // Centroid edge: minimise | |B| - 2 size(s) |; ties go to the later (smaller-Q) edge, which on
    // chains reproduces the middle split of §4.2.
    const long n = static_cast<long>(B.size());
    int best = -1;
    long best_cost = n + 1;
    for (size_t i = 1; i < B.size(); ++i) {
      const long cost = std::labs(n - 2L * size[B[i]]);
      if (cost <= best_cost) { best_cost = cost; best = B[i]; }
    }
    std::vector<int> Pb, Qb;
    for (int b : B) {
      const bool q = (b == best) || (b != B[0] && inQ[parent[b]] == stamp_id);
      if (q) { inQ[b] = stamp_id; Qb.push_back(b); } else Pb.push_back(b);
    }
    t.joint[node] = best;
    t.owner_of_joint[best] = node;
    stack.push_back({std::move(Qb), node, false});
    stack.push_back({std::move(Pb), node, true});
  }

  // Handles, bottom-up (ids descending).
  const int nn = t.nnodes();
  std::vector<std::vector<int>> hs(nn), hb(nn);
  std::vector<std::vector<int>> kids(nb);
  for (int c = 1; c < nb; ++c) kids[parent[c]].push_back(c);
  for (int node = nn - 1; node >= 0; --node) {
    if (t.P[node] < 0) {
      const int k = t.body[node];
      if (k > 0) { hs[node].push_back(k); hb[node].push_back(k); }
      for (int c : kids[k]) { hs[node].push_back(c); hb[node].push_back(k); }
      continue;
    }
    const int J = t.joint[node];
    const int Pn = t.P[node], Qn = t.Q[node];
    for (size_t i = 0; i < hs[Pn].size(); ++i) {
      if (hs[Pn][i] == J) { t.slot_j[node] = static_cast<int>(i); continue; }
      hs[node].push_back(hs[Pn][i]);
      hb[node].push_back(hb[Pn][i]);
    }
    for (size_t i = 0; i < hs[Qn].size(); ++i) {
      if (hs[Qn][i] == J) { t.slot_k[node] = static_cast<int>(i); continue; }
      hs[node].push_back(hs[Qn][i]);
      hb[node].push_back(hb[Qn][i]);
    }
    if (t.slot_j[node] < 0 || t.slot_k[node] < 0)
      throw std::logic_error("build_assembly_tree: principal joint missing from a child's handles");
  }
  t.handle_adr.resize(nn);
  t.handle_num.resize(nn);
  for (int node = 0; node < nn; ++node) {
    t.handle_adr[node] = static_cast<int>(t.handles.size());
    t.handle_num[node] = static_cast<int>(hs[node].size());
    t.handles.insert(t.handles.end(), hs[node].begin(), hs[node].end());
    t.handle_body.insert(t.handle_body.end(), hb[node].begin(), hb[node].end());
    t.max_handles = std::max(t.max_handles, t.handle_num[node]);
    t.max_depth = std::max(t.max_depth, t.depth[node]);
  }
  return t;
}

ParallelCut parallel_cut(const AssemblyTree& t, int ntasks, int grain) {
  const int nn = t.nnodes();
  std::vector<int> size(nn, 1);
  for (int node = nn - 1; node >= 0; --node)
    if (!t.is_leaf(node)) size[node] = 1 + size[t.P[node]] + size[t.Q[node]];
  using Item = std::pair<int, int>;   // (subtree size, node): the largest is split first
  std::priority_queue<Item> heap;
  for (int r : t.roots) heap.push({size[r], r});
  ParallelCut c;
  while (static_cast<int>(heap.size()) < ntasks && heap.top().first > grain &&
         !t.is_leaf(heap.top().second)) {
    const int node = heap.top().second;
    heap.pop();
    c.top.push_back(node);
    heap.push({size[t.P[node]], t.P[node]});
    heap.push({size[t.Q[node]], t.Q[node]});
  }
  for (; !heap.empty(); heap.pop()) {   // largest first: the order a dynamic schedule should take
    c.lo.push_back(heap.top().second);
    c.hi.push_back(heap.top().second + heap.top().first);
  }
  std::sort(c.top.begin(), c.top.end());
  return c;
}

std::int64_t cut_makespan(const ParallelCut& c, int p) {
  std::priority_queue<std::int64_t, std::vector<std::int64_t>, std::greater<>> load;
  for (int i = 0; i < std::max(p, 1); ++i) load.push(0);
  for (size_t i = 0; i < c.lo.size(); ++i) {   // tasks are stored largest first
    const std::int64_t l = load.top();
    load.pop();
    load.push(l + (c.hi[i] - c.lo[i]));
  }
  std::int64_t span = 0;
  for (; !load.empty(); load.pop()) span = std::max(span, load.top());
  return span + static_cast<std::int64_t>(c.top.size());
}

}  // namespace haptree
