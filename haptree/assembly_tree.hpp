/// @file
/// Assembly tree (docs/algorithms.md §4): a balanced binary tree whose leaves are bodies and whose internal
/// nodes each own one joint (the principal joint). Node ids are pre-order (up[i] < i), so "ids
/// descending" is bottom-up and "ascending" is top-down.
#pragma once

#include <cstdint>
#include <vector>

namespace haptree {

/// The assembly tree of a model: per node its children, parent, principal joint and handles.
struct AssemblyTree {
  std::vector<int> roots;        ///< one per connected component; usually exactly one
  std::vector<int> P;            ///< (nnodes) first child, holding the principal joint's predecessor (-1 for leaves)
  std::vector<int> Q;            ///< (nnodes) second child, holding its successor (-1 for leaves)
  std::vector<int> up;           ///< (nnodes) parent (-1 for roots)
  std::vector<int> joint;        ///< (nnodes) principal joint (= successor body id); -1 for leaves
  std::vector<int> body;         ///< (nnodes) body id for leaves; -1 for internal nodes
  std::vector<int> depth;        ///< (nnodes) root = 0
  std::vector<int> slot_j;       ///< (nnodes) slot of the principal joint in P's handles
  std::vector<int> slot_k;       ///< (nnodes) slot of the principal joint in Q's handles
  std::vector<int> handle_adr;   ///< (nnodes) CSR offsets into `handles`
  std::vector<int> handle_num;   ///< (nnodes)
  std::vector<int> handles;      ///< joint ids; order P' then Q' (§5.3)
  std::vector<int> handle_body;  ///< parallel to `handles`: the node's body the handle joint is attached to
  std::vector<int> leaf_of_body;     ///< (nbodies)
  std::vector<int> owner_of_joint;   ///< (nbodies) internal node whose principal joint is J; -1 for 0
  int max_depth = 0;             ///< depth of the deepest node
  int max_handles = 0;           ///< most handles of any node

  int nnodes() const { return static_cast<int>(up.size()); }   ///< leaves and internal nodes
  bool is_leaf(int node) const { return P[node] < 0; }        ///< a leaf is one body
  int nhandles(int node) const { return handle_num[node]; }   ///< joints crossing the node's boundary
  /// Joint id of handle `slot` of `node`.
  int handle(int node, int slot) const { return handles[handle_adr[node] + slot]; }
  /// The body inside `node` that handle `slot` attaches to: the joint's successor or predecessor.
  int attached_body(int node, int slot) const { return handle_body[handle_adr[node] + slot]; }
  /// The other child of `node`'s parent; -1 for a root.
  int sibling(int node) const {
    const int u = up[node];
    return u < 0 ? -1 : (P[u] == node ? Q[u] : P[u]);
  }
  /// Up-region of a leaf: the leaf and all its ancestors, ids ascending (root first).
  std::vector<int> up_region(int leaf) const;
};

/// Builds the tree for bodies 0..n-1 with parent[k] < k (parent[0] = -1) by centroid-edge
/// decomposition (§4.3); chains give the middle-split tree of §4.2.
AssemblyTree build_assembly_tree(const std::vector<int>& parent);

/// A static schedule for the DCA passes on several threads. Node ids are pre-order, so
/// every subtree is an id range: the tasks are disjoint subtrees [lo, hi), each swept by one thread
/// (ids descending bottom-up, ascending top-down); `top` holds the nodes above them, ids ascending,
/// run by one thread after the tasks bottom-up and before them top-down. No other synchronisation.
struct ParallelCut {
  std::vector<int> lo;       ///< first node id of each task subtree
  std::vector<int> hi;       ///< one past its last node id
  std::vector<int> top;      ///< the split nodes
};
/// Splits the largest subtree until there are `ntasks` tasks or the largest has at most `grain`
/// nodes. ntasks = 1 gives one task per root.
ParallelCut parallel_cut(const AssemblyTree& t, int ntasks, int grain);
/// Node-count model of one pass on p threads: tasks assigned longest first to the least loaded
/// thread, plus the top nodes in series. Returns that makespan in nodes; nnodes / makespan is the
/// modelled speed-up (a count, for tests and the 16-core model, not a timing).
std::int64_t cut_makespan(const ParallelCut& c, int p);

}  // namespace haptree
