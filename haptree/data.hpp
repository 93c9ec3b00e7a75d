/// @file
/// State (what a checkpoint needs) and Data (the preallocated workspace every pass writes).
/// Data is sized once from the Model; nothing in a dynamics step allocates.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "haptree/assembly_tree.hpp"
#include "haptree/inverse_dynamics.hpp"
#include "haptree/model.hpp"

namespace haptree {

/// The simulated state: joint positions, velocities, torques, applied forces and time.
struct State {
  /// Zero state of `model` (quaternions at identity), sized once.
  explicit State(const Model& model);
  ///@{
  /// (nq) joint positions, (nv) velocities, (nv) torques / forces
  Eigen::VectorXd q, qd, tau;
  ///@}
  std::vector<Vec6> f_ext;      ///< (nbodies) applied forces, world axes, at each body's origin r_k
  double t = 0;                 ///< time, s (ps for molecules)
};

/// What a node of the assembly tree is in the current pass.


enum class NodeKind : std::uint8_t { kLeaf, kActive, kRigid };   ///< a body; a moving joint's node; a locked subtree's node

/// Iterative refinement in forward_dynamics (Data::refine).
enum class Refinement : std::uint8_t {
  kOff,        ///< one pass: 1.2–1.3× faster, 1e-12-level errors on trees and proteins
  kDouble,     ///< one refinement step, residual in double from the pass's kinematics (the default)
  kExtended,   ///< one refinement step, residual in long double from q itself (set_refinement)
};

/// Counters instead of logging on the hot path (MuJoCo's warning counters).
struct Diagnostics {
  std::int64_t nodes_bottom_up = 0;   ///< nodes assembled in the last bottom-up pass
  std::int64_t nodes_top_down = 0;    ///< nodes visited in the last top-down pass
  std::int64_t singular_pivots = 0;   ///< joint systems T^T Φ̂ T that were not positive definite
  std::int64_t nonfinite = 0;         ///< non-finite accelerations produced
  std::int64_t refine_rejected = 0;   ///< Data::refine corrections dropped (larger than q̈, or not finite)
  int last_bad_node = -1;             ///< the last node with a singular pivot or a non-finite result
};

using MatMap = Eigen::Map<Eigen::MatrixXd>;                         ///< a matrix in a buffer
using CMatMap = Eigen::Map<const Eigen::MatrixXd>;                  ///< a read-only matrix in a buffer
///@{
/// a 6×6 block of a node's Φ
using BlockMap = Eigen::Map<Mat6, 0, Eigen::OuterStride<>>;
///@}
///@{
/// a read-only 6×6 block of Φ
using CBlockMap = Eigen::Map<const Mat6, 0, Eigen::OuterStride<>>;
///@}
using VecMap = Eigen::Map<Vec6>;                                    ///< a handle's 6-vector in a buffer
using CVecMap = Eigen::Map<const Vec6>;                             ///< a read-only handle 6-vector

/// The workspace of the dynamics passes, sized once from a Model: kinematics per body, assembly
/// coefficients per node, the refinement's buffers, the parallel schedule and the counters.
struct Data {
  /// `refine` sets Data::refine; Refinement::kOff leaves the refinement buffers unallocated (the
  /// background selection's copy, which runs no forward_dynamics) until set_refinement asks for them.
  explicit Data(const Model& model, Refinement refine = Refinement::kDouble);

  /// Kinematics (world axes). r_k is body k's origin = handle point of joint k.
  std::vector<Mat3> R;          ///< (nbodies) body rotation
  std::vector<Vec3> r;          ///< (nbodies) body origin
  std::vector<Vec3> d;          ///< (nbodies) r_k - r_parent, from local offsets (never a far subtraction)
  std::vector<Vec6> v;          ///< (nbodies) spatial velocity at r_k
  std::vector<Vec6> S;          ///< (nbodies) 1-DOF motion subspace at r_k (rev/prism)
  std::vector<Vec6> c;          ///< (nbodies) velocity-product term c_J at r_k
  std::vector<Mat6> I;          ///< (nbodies) spatial inertia at r_k
  std::vector<Mat6> Iinv;       ///< (nbodies) inverse spatial inertia
  std::vector<Vec6> f_total;    ///< (nbodies) gravity + state.f_ext, at r_k
  std::vector<Vec6> p_bias;     ///< (nbodies) f_total - v ×* I v

  /// Assembly coefficients, per node: Φ (6h×6h, column-major) and b, f (6h).
  std::vector<NodeKind> kind;   ///< (nnodes) leaf / active / rigid
  std::vector<double> Phi_buf;         ///< every node's Φ, at Phi_adr[node]
  std::vector<std::int64_t> Phi_adr;   ///< (nnodes)
  ///@{
  /// handle-vector storage of b (bias accelerations) and f (forces)
  std::vector<double> b_buf, f_buf;
  ///@}
  std::vector<int> vec_adr;            ///< (nnodes)
  std::vector<Mat6> W;                 ///< (nnodes) internal nodes
  std::vector<Vec6> beta;              ///< (nnodes)
  std::vector<Vec6> taut;              ///< (nnodes) (1 - WΦ̂) D τ, kept so β splits cleanly

  /// Inertia form of cluster nodes (Model::cluster_index; full DCA only): the node's articulated
  /// inertia M and bias force p at its reference point o = r_{Model::cluster_ref[node]},
  /// a_o = cMinv Σ X_xᵀ f_x + cb with
  /// cMinv = M⁻¹, cb = M⁻¹p (or their pinned versions when the node holds the cluster's ground
  /// joint); for projection nodes also the one-handle side's articulated inertia IA and bias pA.
  /// r_k − r_{cluster_root[k]} is kept as an unevaluated sum hi + lo (compensated summation of the
  /// d's), so the offset between two bodies on the far side of a long weld is exact to O(ε) of
  /// their own distance, not O(ε) of the weld's length.
  std::vector<Vec3> cluster_offset;    ///< (nbodies if clusters) hi part
  std::vector<Vec3> cluster_offset_lo; ///< (nbodies if clusters) lo part
  ///@{
  /// (ncluster_nodes) M at o, M⁻¹ (or pinned), one side's IA
  std::vector<Mat6> cM, cMinv, cIA;
  ///@}
  ///@{
  /// (ncluster_nodes) bias force p at o, one side's bias pA
  std::vector<Vec6> cp, cpA;
  ///@}
  std::vector<Vec6> cqa;               ///< (ncluster_nodes) U⁻¹(στ + Sᵀ pA), first nJ entries
  std::vector<Vec6> ca;                ///< (ncluster_nodes) acceleration of the reference point
  std::vector<Vec6> cb;                ///< (ncluster_nodes) a_o with no handle forces (cMinv = ∂a_o/∂F_o)
  std::vector<std::uint8_t> cluster_live;   ///< (nnodes) assembled in inertia form in this pass

  /// Light-leaf form (dca_light_leaf.cpp): a node joining a leaf body to the stiffer side of its
  /// joint is assembled from the leaf's inertia, not from its mobility. leaf_adr: slot of a node
  /// with a (non-ground) leaf child, else −1; leaf_side: 0 mobility form, 1 P is the leaf, 2 Q is;
  /// leaf_F: ∂f_J/∂f_L, the joint force on the leaf per force on its other handles (at r_J).
  std::vector<int> leaf_adr;                ///< (nnodes)
  std::vector<std::uint8_t> leaf_side;      ///< (nnodes)
  std::vector<Mat6> leaf_F;                 ///< (nodes with a leaf child)
  std::vector<Mat6> leaf_G;                 ///< (nodes with a leaf child) ∂f_J/∂τ_J (σ-signed), nJ cols

  Eigen::VectorXd qdd;          ///< (nv) output of forward_dynamics

  /// One step of iterative refinement in forward_dynamics (kDouble by default): the
  /// residual r = τ − ID(q, q̇, q̈) by inverse dynamics at the handle points, then δ = H⁻¹ r by the
  /// bias half of the assembly (q̇ = 0, no gravity, no f_ext, τ = r; the factors Φ, W of the pass
  /// reused) and a top-down, and q̈ += δ. The mobility-form assembly Φ_C = Φ_L − Φ_L W Φ_L is not
  /// backward stable next to light bodies or between large subassemblies; inverse dynamics is, so
  /// one step recovers the digits it loses (binary tree 1024: 1.2e-12 → 5e-16; bacteriorhodopsin
  /// 2.4e-12 → 2.8e-15) for 1.1–1.4× the plain pass (docs/performance.md).
  /// kDouble computes r in double from the pass's poses: q̈ then solves the problem of the *rounded*
  /// poses, whose own distance from the exact one is the model's conditioning times ε (chain 1024:
  /// 6e-12, as Bullet and Simbody). kExtended computes r in long double from q (kinematics
  /// included), the mixed-precision refinement of Wilkinson: q̈ converges to the solution for the
  /// inputs as given, for 2–2.8× the plain pass. The node coefficients b, β, f, τ̃ and the cluster
  /// vectors (the coupling snapshot's inputs) keep the plain pass's values; only q̈ is corrected.
  /// Set it with set_refinement (it sizes the buffers below there, not in the pass; a Data built with
  /// kOff and given another mode by assignment sizes them in its next forward_dynamics).
  Refinement refine = Refinement::kDouble;
  ///@{
  /// (nv) first solve, residual τ − ID(q, q̇, q̈)
  Eigen::VectorXd refine_qdd, refine_r;
  ///@}
  ///@{
  /// (nbodies) inverse dynamics: accelerations, forces
  std::vector<Vec6> refine_a, refine_f;
  ///@}
  /// The correction pass runs on these, swapped in (O(1), no copy) for the pass's own bias terms and
  /// swapped back after it: p_bias and c become zero (refine_p, refine_c are always all zero), and
  /// the node coefficients the pass left (b, f, β, τ̃ and the cluster vectors, the coupling
  /// snapshot's inputs) are kept as the plain pass wrote them.
  ///@{
  /// (nbodies) zero: the correction pass's p_bias and c
  std::vector<Vec6> refine_p, refine_c;
  ///@}
  ///@{
  /// the correction pass's b and f
  std::vector<double> refine_b_buf, refine_f_buf;
  ///@}
  ///@{
  /// (nnodes) its β, τ̃
  std::vector<Vec6> refine_beta, refine_taut;
  ///@}
  ///@{
  /// (ncluster_nodes) its cluster vectors
  std::vector<Vec6> refine_cp, refine_cpA, refine_cqa, refine_ca, refine_cb;
  ///@}
  /// kExtended's inverse dynamics (empty until set_refinement asks for it).
  InverseDynamicsScratch<long double> refine_x;   ///< kExtended's long-double inverse dynamics

  /// Threads of forward_dynamics' passes and their schedule (set_dca_threads). 1 (the
  /// default) runs everything on the calling thread.
  int dca_threads = 1;
  ParallelCut dca_cut;          ///< one task per root until set_dca_threads splits it
  Diagnostics diag;             ///< counters of the last passes

  /// Handles of `node`.
  int h(const Model& m, int node) const { return m.tree.handle_num[node]; }
  /// Block (a, b) of node's Φ (h handles).
  BlockMap Phi(int node, int h, int a, int b) {
    return BlockMap(Phi_buf.data() + Phi_adr[node] + 6 * a + 36 * h * b, Eigen::OuterStride<>(6 * h));
  }
  /// Block (a, b) of node's Φ (h handles), read-only.
  CBlockMap Phi(int node, int h, int a, int b) const {
    return CBlockMap(Phi_buf.data() + Phi_adr[node] + 6 * a + 36 * h * b, Eigen::OuterStride<>(6 * h));
  }
  /// b at a handle slot of node.
  VecMap b(int node, int slot) { return VecMap(b_buf.data() + vec_adr[node] + 6 * slot); }
  /// b at a handle slot of node, read-only.
  CVecMap b(int node, int slot) const { return CVecMap(b_buf.data() + vec_adr[node] + 6 * slot); }
  /// f at a handle slot of node.
  VecMap f(int node, int slot) { return VecMap(f_buf.data() + vec_adr[node] + 6 * slot); }
  /// f at a handle slot of node, read-only.
  CVecMap f(int node, int slot) const { return CVecMap(f_buf.data() + vec_adr[node] + 6 * slot); }
};

/// Heap memory a workspace holds, container by container (its capacity, not its size), for
/// memory reports (scaling_bench --memory). Names are prefix + the member's name.
struct MemoryItem {
  std::string name;        ///< prefix + the member's name
  std::size_t bytes = 0;   ///< heap bytes it holds (capacity)
};
/// Sizes (allocates) the double-precision refinement buffers of `d`; set_refinement calls it, and
/// also sizes kExtended's long-double ones (refine_x) when asked for that mode.
void size_refinement(const Model& model, Data& d);
/// True when the refinement buffers of `d` are sized for its mode.
bool refinement_sized(const Model& model, const Data& d);

/// Heap bytes of each container of a State.
std::vector<MemoryItem> memory_usage(const State& s, const std::string& prefix = "State.");
/// Heap bytes of each container of a Data.
std::vector<MemoryItem> memory_usage(const Data& d, const std::string& prefix = "Data.");
/// Sum of the items' bytes.
std::size_t total_bytes(const std::vector<MemoryItem>& items);

}  // namespace haptree
