/// @file
/// Adaptive (hybrid) articulated-body dynamics (docs/algorithms.md §6, §8–§10; Redon et al.).
///
/// Only the joints of the *active region* — a rooted subtree of the assembly tree — move. Each child
/// of an active node that is not active is a *frontier* node: a rigid body (its whole subtree locked)
/// whose coefficients come from a cached composite inertia in O(h²) (§6.2), so a step costs
/// O(|active| + |frontier|) whatever n is.
///
/// Velocity policy (§10.3, model V1): inactive joints have q̇ = 0. A frontier node is then one true
/// rigid body, its composite inertia and internal geometry are constant while it stays rigid (cached
/// in its reference body's frame and only rotated on use), and nothing inside it is ever revisited.
/// Joints that are deactivated while moving are locked *impulsively* (lock_velocities): the active
/// joints take the velocities that momentum conservation under the new constraints gives, so the
/// kinetic energy can only drop (by the energy of the removed relative motion — an energy sink,
/// measured by tools/adaptive_sweep). Simply zeroing q̇ of the locked joints was measured to *add*
/// energy (a counter-rotating child sped up), which is why the projection is worth its O(n) cost.
///
/// Selection (§9): a full-articulated pass computes the acceleration metric coefficients Ψ, p, η
/// of every node (§8), and a greedy top-down walk activates the nodes with the largest metric until
/// the neglected metric Σ_{inactive} q̈ᵀ A q̈ is ≤ ε (threshold mode) or the DOF budget is used.
/// When it runs: when ε or the budget changes, and then — with reselect_every = 0, the
/// default — at an error-controlled interval: each selection first computes, exactly, the
/// neglected metric the replaced region has *now* (a check costing |active| top-down steps on the
/// full pass it needs anyway), measures how fast it grew since that region was selected, and sets
/// the next interval to half the predicted time until the new region's neglected metric reaches
/// its bound (ε, or (1 + estimate_growth)× its value in budget mode). A steady scene therefore
/// reselects rarely (the interval grows ×4 per selection up to interval_max), a changing one often.
/// reselect_every > 0 keeps the fixed count.
/// A selection is cheap (incremental_metric, docs/algorithms.md §10.2/§10.4): under V1 only the active
/// region's joints move between selections, so every other node keeps its configuration-only
/// coefficients Φ, W, Ψ (cached in its reference body's frame, rotated on use) and recomputes only
/// its bias terms b, β, p, η by matrix–vector recurrences; the nodes with a moved joint — at most
/// the old region's — are assembled in full. The result equals the full recompute up to round-off
/// (tested), and every exact_refresh_every-th selection is that full recompute (§10.4-A).
#pragma once

#include <vector>

#include "haptree/data.hpp"

namespace haptree {

/// How the active region is chosen and when it is chosen again.
struct AdaptiveOptions {
  /// Error threshold ε, or a budget of active DOFs.
  enum class Mode { kThreshold, kBudget };
  Mode mode = Mode::kBudget;                 ///< how the region's size is decided
  double epsilon = 1e-3;     ///< threshold mode: bound on Σ_{inactive} q̈ᵀ A q̈ (A = 1)
  int budget = 48;           ///< budget mode: max active DOFs
  int reselect_every = 0;     ///< > 0: select every this many steps; 0: error-controlled interval
  int interval_first = 25;    ///< error-controlled: first interval (and after ε/budget changes)
  int interval_max = 1000;    ///< error-controlled: longest interval
  double estimate_growth = 1.0;      ///< budget mode: bound = (1 + this)× the selection's value
  double estimate_floor_rel = 1e-6;  ///< ... + this × the total metric (round-off level values)
  /// Selection cost (docs/algorithms.md §10.2/§10.4): a node whose subtree has no joint that
  /// moved since the last selection keeps its configuration-only coefficients Φ, W, Ψ (cached in its
  /// reference body's frame, only rotated on use); only its bias terms b, β, p, η are recomputed,
  /// with matrix–vector products. Nodes with a moved joint (the active region's) get the full
  /// assembly. Exact (equal to the full recompute up to round-off); false: every node in full.
  bool incremental_metric = true;
  /// Every this many selections the coefficients are recomputed from scratch (§10.4-A, the check
  /// and reset of the incremental ones); 0: never, except when nothing is cached yet.
  int exact_refresh_every = 16;
  /// Background selection (docs/algorithms.md §10.5, "selection off the step"): once a first region is in force,
  /// a due reselection is computed on a worker thread from a consistent copy of the state (q, q̇, τ
  /// and the loaded bodies' f_ext at the step it is due), while the steps go on with the region in
  /// force; the first adaptive_step after the worker is done installs the new region in
  /// O(|old region| + |new region|) (no pass over the whole tree inside a step). Every step's
  /// dynamics are exactly those of the region in force; the report's neglected metric is that of the
  /// region in force, evaluated at the state it was selected from. The handover step depends on the
  /// worker's speed (call adaptive_selection_wait for a reproducible one). false: every selection
  /// runs inside the step that is due, as a synchronous select_active_region. The first selection,
  /// and one after ε, the budget or the mode changed, are always synchronous; a change of
  /// AdaptiveData::keep_active_bodies (a new grab) makes one due that runs in the background too. The
  /// worker thread runs at a lower scheduling priority (nice +10) than the caller's, so on a machine
  /// with fewer free cores than busy threads the steps keep their rate and the selection waits.
  bool background_selection = true;
};

/// What the last adaptive_step and the last selection did.
struct AdaptiveReport {
  int active_dofs = 0;      ///< DOFs of the active joints
  int active_nodes = 0;     ///< active internal nodes
  int frontier_nodes = 0;   ///< frontier nodes (rigid subtrees) in force
  double neglected_metric = 0;   ///< Σ over inactive joints of q̈ᵀq̈ at the last selection
  double total_metric = 0;       ///< Σ over all joints (root metric) at the last selection
  ///@{
  /// last hybrid pass
  std::int64_t nodes_bottom_up = 0, nodes_top_down = 0;
  ///@}
  bool reselected = false;   ///< the last adaptive_step installed a new region
  bool kinematics_reused = false;   ///< last adaptive_step reused the previous step's kinematics
  std::int64_t selections = 0;   ///< selections so far
  /// At the last selection: the exact neglected metric of the region it replaced, at that time
  /// (−1: none, e.g. the first selection), and the interval chosen until the next one.
  double check_exact = -1;   ///< the replaced region's exact neglected metric (−1: none)
  int interval = 0;          ///< steps until the next selection
  /// At the last selection: nodes assembled in full (Φ, W, Ψ) and nodes whose bias terms only were
  /// recomputed (incremental_metric), and whether it was an exact refresh (every node in full).
  ///@{
  /// nodes assembled in full; nodes whose bias terms only were recomputed
  std::int64_t metric_nodes_full = 0, metric_nodes_bias = 0;
  ///@}
  bool exact_refresh = false;   ///< the last selection recomputed every node in full
  /// Background selection: a selection is being computed off the step; steps since it was asked for
  /// at the last handover (the region in force lagged the state it was selected from by this many).
  bool selection_pending = false;   ///< a selection is being computed off the step
  int handover_lag = 0;             ///< steps the region in force lagged its state at the last handover
};

struct AsyncSelector;   ///< adaptive.cpp: the background selection's worker (thread, copies)
/// Owner of the worker: a copied AdaptiveData starts without one (a worker serves one AdaptiveData).
struct AsyncSelectorHandle {
  AsyncSelectorHandle() = default;                                              ///< no worker
  AsyncSelectorHandle(const AsyncSelectorHandle&) {}                            ///< a copy has no worker
  AsyncSelectorHandle& operator=(const AsyncSelectorHandle&) { return *this; }  ///< keeps its own worker
  ~AsyncSelectorHandle();   ///< stops and joins the worker
  AsyncSelector* p = nullptr;   ///< the worker, once started
};

/// Per-run adaptive workspace, sized once from the Model.
struct AdaptiveData {
  explicit AdaptiveData(const Model& model);   ///< the full workspace of a run
  /// selection_only: only what a selection and its frontier caches use (the background worker's
  /// copy): the buffers of the hybrid pass, the handover and the impulsive lock stay empty.
  AdaptiveData(const Model& model, bool selection_only);
  /// Active region.
  std::vector<char> active;            ///< (nnodes) internal node is active
  std::vector<int> active_nodes;       ///< ids ascending (top-down order)
  std::vector<int> frontier;           ///< non-active children of active nodes (+ rigid roots)
  std::vector<int> active_joints;      ///< ascending body order (reduced kinematics order)
  /// Two-level frontier: frontier_of_body[k] is the *fine* frontier node of body k, local_R/local_r
  /// (below) its pose relative to the fine node's reference body; coarse_of[f] is the frontier node
  /// in force that contains the fine node f, X_R[f]/X_r[f] the pose of f's reference body relative
  /// to the coarse node's (identity when f is itself a frontier node in force, as after every
  /// synchronous selection). A background handover swaps in the fine level computed off the step
  /// (the frontier of the union of the old and the new region, whose joints did not move meanwhile)
  /// and builds the coarse level over it in O(|old| + |new|). frontier_of(ad, k) is body k's node.
  std::vector<int> frontier_of_body;   ///< (nbodies) fine frontier node containing the body
  std::vector<int> fine_frontier;      ///< the fine frontier nodes
  std::vector<int> coarse_of;          ///< (nnodes) frontier node in force of a fine node
  std::vector<Mat3> X_R;               ///< (nnodes) fine reference pose in the coarse node's frame
  std::vector<Vec3> X_r;               ///< (nnodes)
  /// Composite rigid data of frontier nodes, in the reference body's frame.
  std::vector<int> ref_body;           ///< (nnodes) first (smallest-id) body of the node
  std::vector<double> comp_mass;       ///< (nnodes)
  std::vector<Vec3> comp_com;          ///< (nnodes) COM, ref frame, relative to ref origin
  std::vector<Mat3> comp_Ic;           ///< (nnodes) rotational inertia about COM, ref frame
  std::vector<char> comp_ground;       ///< (nnodes) contains the ground (immovable)
  /// Every body's pose relative to its frontier node's reference body (valid while rigid).
  std::vector<Mat3> local_R;           ///< (nbodies)
  std::vector<Vec3> local_r;           ///< (nbodies)
  std::vector<Vec6> ref_velocity;      ///< (nnodes) frontier node velocity at its reference origin
  std::vector<Vec3> pred_offset;       ///< (nbodies) r_J − r_ref of J's predecessor's frontier node
  /// Active fixed-joint cluster nodes assembled in inertia form, as the full pass does: a weld
  /// joined by the mobility difference formula cancels ~(weld length/gyration radius)² of the
  /// digits. Eligible: those whose inertia-form children are leaves or such nodes.
  /// if_bodies: their bodies, ascending, for the compensated cluster offsets; if_top: the first
  /// body of each such region.
  std::vector<char> inertia_form;      ///< (nnodes)
  std::vector<int> if_bodies;          ///< bodies of the inertia-form nodes, ascending
  std::vector<char> if_top;            ///< (nbodies)
  /// Metric coefficients (§8), full-articulated, from the last selection. Lent to the background
  /// worker while a selection is in flight (the worker's copy has none of its own).
  ///@{
  /// Ψ (Data's Φ layout) and p of every node
  std::vector<double> Psi_buf, p_buf;
  ///@}
  std::vector<double> eta;             ///< (nnodes)
  /// Incremental metric (AdaptiveOptions::incremental_metric): Φ, Ψ (Data's Φ layout) and W of
  /// every node in the frame of its reference body at the time they were assembled (valid while no
  /// joint inside the node, nor a translating joint at its handles, has moved: the bitwise q of
  /// the last selection, q_cached, tells); which nodes hold the current world values in Data/Psi_buf.
  /// Lent to the background worker with Ψ, p, η: one cache serves every selection, whichever thread
  /// runs it.
  ///@{
  /// Φ and Ψ of every node in its reference body's frame
  std::vector<double> Phi_loc, Psi_loc;
  ///@}
  std::vector<Mat6> W_loc;               ///< W of every node in its reference body's frame
  Eigen::VectorXd q_cached;              ///< q of the last selection (bitwise check)
  bool metric_cached = false;            ///< the caches above hold values
  int selections_since_refresh = 0;      ///< selections since the last exact refresh
  ///@{
  /// per node: a joint inside moved; Data/Psi_buf hold its current world values; per joint: moved
  std::vector<char> node_moved, world_ok, scratch_joint_moved;
  ///@}
  bool body_terms_current = false;   ///< Data's v, I are body_dynamics_terms of the current state
  /// The reduced kinematics in Data (poses of reference bodies and active-joint ends, S, c, v,
  /// ref_velocity, pred_offset) are those adaptive_step computed at the end of the last step, for
  /// the active joints' q, q̇ kept in kin_q (in active_joints order): the next step reuses them
  /// instead of recomputing the same values (bitwise check of q, q̇; cleared by every other writer).
  /// A caller that rewrites Data's poses between steps (forward_kinematics) with the same q changes
  /// them only by round-off.
  bool kin_current = false;
  std::vector<double> kin_q;   ///< q, q̇ of the active joints the reduced kinematics were computed for
  /// Bodies whose leaf every selection keeps in the active tree (its whole root path active, beyond
  /// the budget if need be): grabbed bodies, whose coupling snapshot needs an active path.
  std::vector<int> keep_active_bodies;
  /// keep_active_bodies as the region in force was selected with: a change of keep_active_bodies
  /// makes a selection due (in the background once a region is in force, like any other).
  std::vector<int> keep_selected;
  /// Bodies with a non-zero State::f_ext; empty + scan_forces = scan every body each step.
  std::vector<int> loaded_bodies;
  bool scan_forces = true;             ///< loaded_bodies empty: scan every body's f_ext each step
  double gravity_scale = 1;            ///< 0 inside lock_velocities (impulse balance)
  AdaptiveOptions last_options;        ///< options of the last step (a change forces a selection)
  int steps_since_selection = 1 << 30; ///< steps since the region in force was installed
  AdaptiveReport report;               ///< what the last step and selection did
  /// Scratch for the metric coefficients (sized once from the largest handle count).
  ///@{
  /// metric coefficient scratch (per handle)
  std::vector<Mat6> scratch_K, scratch_V, scratch_Y;
  ///@}
  ///@{
  /// frontier Φ blocks (per handle)
  std::vector<Mat3> scratch_U, scratch_Vb, scratch_Sk;
  ///@}
  std::vector<Vec6> scratch_f;                            ///< handle forces in a node's frame
  std::vector<std::pair<double, int>> heap;   ///< budget mode: candidate nodes by metric
  bool region_selected = false;   ///< the region came from select_active_region (checkable)
  int interval = 25;              ///< steps until the next selection (error-controlled mode)
  std::int64_t region_version = 0;   ///< bumped by every region built in full (set/select)
  std::int64_t step_count = 0;       ///< adaptive_step calls
  std::int64_t selected_at = 0;      ///< step_count of the state the region in force was selected from
  /// Scratch (sized once; nothing in a step or a selection allocates).
  std::vector<int> scratch_stack;          ///< tree walks
  std::vector<char> scratch_joint_active;  ///< (nbodies) joint marks
  std::vector<Vec6> scratch_h;             ///< momenta
  std::vector<Vec6> scratch_hn;        ///< (nnodes) fine-node momenta at a handover
  ///@{
  /// node, joint and union lists of a handover
  std::vector<int> scratch_nodes, scratch_joints, scratch_union;
  ///@}
  std::vector<int> scan_loaded;        ///< bodies the last force scan found loaded
  std::vector<char> scratch_mark;      ///< (nnodes) zero between uses
  State impulse;                       ///< lock_velocities' impulse balance state
  /// Work of the last adaptive_step on the calling thread, in nodes and bodies visited (a measure
  /// of cost that does not depend on the machine; the background worker's is not counted).
  std::int64_t step_work = 0;
  AsyncSelectorHandle worker;          ///< the background selection's worker
};

/// Frontier node in force containing body k.
inline int frontier_of(const AdaptiveData& ad, int k) {
  const int f = ad.frontier_of_body[k];
  return f < 0 ? -1 : ad.coarse_of[f];
}

/// Starts the background selection's worker (its Data, State, AdaptiveData and thread) now, so that
/// its allocation is not paid inside a step; adaptive_step starts it with its first selection
/// otherwise. `model` must outlive `ad`.
void start_background_selection(const Model& model, AdaptiveData& ad);

/// Heap memory of `ad`'s containers (prefix + name) and, once started, of the background worker's
/// Data, State, AdaptiveData and job buffers (names "worker." + ...). Capacity, not size.
std::vector<MemoryItem> memory_usage(const AdaptiveData& ad, const std::string& prefix = "AdaptiveData.");

/// World pose of body k after an adaptive step, from its frontier node's reference body. O(1).
inline void body_pose(const Data& d, const AdaptiveData& ad, int k, Mat3& R, Vec3& r) {
  const int f = ad.frontier_of_body[k];
  if (f < 0) {
    R = d.R[k];
    r = d.r[k];
    return;
  }
  const int ref = ad.ref_body[ad.coarse_of[f]];
  if (ref == k) {
    R = d.R[k];
    r = d.r[k];
    return;
  }
  const Mat3 lR = ad.X_R[f] * ad.local_R[k];
  const Vec3 lr = ad.X_r[f] + ad.X_R[f] * ad.local_r[k];
  R = d.R[ref] * lR;
  r = d.r[ref] + d.R[ref] * lr;
}

/// Whether body k's leaf is a node of the active tree in force: its whole root path is active (or it is a
/// root), so a coupling snapshot of a grab on k reads only that path. False before any region. O(1).
inline bool body_in_active_tree(const Model& model, const AdaptiveData& ad, int k) {
  return k >= 0 && k < model.nbodies && frontier_of(ad, k) == model.tree.leaf_of_body[k];
}

/// The caller changed the state outside adaptive_step: only the active joints' q and q̇ (a restore of
/// a checkpoint taken under the region in force; the frontier caches stay valid). A background selection
/// in flight, computed from the old state, is dropped; the next adaptive_step asks for a new one (in the
/// background once a region is in force) and recomputes its kinematics. Any other change of the state
/// needs select_active_region or set_active_region. O(1).
void request_reselection(AdaptiveData& ad);

/// Blocks until a pending background selection is computed (the next adaptive_step installs it);
/// returns false if none is pending. For reproducible runs and tests.
bool adaptive_selection_wait(AdaptiveData& ad);

/// Acceleration metric coefficients (§8) of every node from a completed full DCA bottom-up pass.
void compute_metric_coefficients(const Model& model, const Data& data, AdaptiveData& ad);
/// Metric value A(node, f) = fᵀΨf + fᵀp + η for handle forces f (6h). NaN while a background
/// selection is in flight (the worker holds Ψ, p, η; adaptive_selection_wait, then the next
/// adaptive_step or select_active_region takes them back).
double metric_value(const Model& model, const AdaptiveData& ad, int node, const double* f);

/// Full pass + metric + greedy selection (§9); sets the active region, zeroes q̇ of inactive joints
/// (V1) and builds the frontier caches. O(n). Returns the neglected metric.
double select_active_region(const Model& model, Data& data, State& state, AdaptiveData& ad,
                            const AdaptiveOptions& options);
/// Sets an explicit active region (a rooted subtree: every ancestor of an active node is active).
/// Zeroes q̇ of inactive joints and builds the frontier caches. O(n).
void set_active_region(const Model& model, Data& data, State& state, AdaptiveData& ad,
                       const std::vector<char>& active_internal_nodes);

/// Impulsive lock of the joints outside the region in `ad` (called by the region setters): inactive
/// joints get q̇ = 0, active ones q̇ₐ + Hₐₐ⁻¹Hₐᵢq̇ᵢ (momentum kept, kinetic energy non-increasing).
/// Needs the region's caches and forward_kinematics in `data`. O(n).
void lock_velocities(const Model& model, Data& data, State& state, AdaptiveData& ad);

/// Hybrid forward dynamics on the current active region: reduced kinematics, bottom-up over active
/// nodes with composite frontier nodes, top-down. q̈ = 0 for inactive joints. No allocation.
const Eigen::VectorXd& adaptive_forward_dynamics(const Model& model, Data& data, const State& state,
                                                 AdaptiveData& ad) noexcept;

/// Whether the next adaptive_step with these options will select (so callers can prepare loads).
bool reselection_due(const AdaptiveData& ad, const AdaptiveOptions& options);

/// One adaptive step: reselect if due (options changed, or the interval has passed), hybrid
/// dynamics, semi-implicit Euler on the active joints only.
const AdaptiveReport& adaptive_step(const Model& model, Data& data, State& state, AdaptiveData& ad,
                                    const AdaptiveOptions& options, double dt);

/// Poses of every body (Data::R, Data::r) from the frontier caches after an adaptive step. O(n):
/// for display and for snapshots of bodies deep inside rigid regions. Reference bodies keep the
/// poses and joint placements d_k of the step's reduced kinematics (the next step reuses them).
void update_all_body_poses(const Model& model, Data& data, const AdaptiveData& ad) noexcept;

}  // namespace haptree
