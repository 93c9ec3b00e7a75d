/// @file
/// O(log n) force-feedback coupling (docs/algorithms.md §11–§12; Morin & Redon §III–IV), single- and
/// multi-point, computed from a self-contained coefficient snapshot, plus the virtual coupling that
/// turns a device pose into the user force and the device <-> scene unit mapping.
///
/// Data flow. After a DCA pass (full or hybrid) the simulation calls make_coupling_snapshot() for the
/// current grabs. The snapshot is a plain flat value (it maps 1:1 onto lcmt_coupling_snapshot) holding
/// exactly what the feedback computation needs for the union U of the grabbed leaves' up-regions:
///   * per internal node C of U: W_C, β_ext,C (β with the user forces removed), and the off-diagonal
///     part of both children's principal columns, Φ^P_{ij} (i ∈ P') and Φ^Q_{lk} (l ∈ Q'), stored in
///     C's own handle order (P' then Q'); the diagonal blocks Φ^P_{jj}, Φ^Q_{kk} are never needed
///     and are dropped;
///   * per grabbed leaf L (body k): I_k^{-1} at r_k, f_ext,k (gravity + applied loads, user forces
///     excluded, at r_k), r_k, the offsets (handle point − r_k) of its handles;
///   * per grab: x_s − r_k, the body rotation R_k and angular velocity ω_k (for 6-DOF coupling).
/// The siblings of U's nodes (the rest of the extended up-region E) contribute only their principal
/// columns, folded into their parent's record; b is never needed because β_ext already contains it.
/// coupling_forces() then runs, on the snapshot alone, the linear bottom-up pass for b_u over U, the
/// top-down pass with β = β_ext + Δβ over U, and f_feed = f_ext + Σ f_i (seed eq. 12).
///
/// POINT AND FRAME CONVENTIONS (the coupler and the sim_server rely on these):
///   * Every spatial force is [moment; force] with WORLD-aligned axes, scene units.
///   * f_u[g] (input of coupling_forces, and f_u_applied[g] of make_coupling_snapshot) is the user
///     force of grab g as a spatial force AT THE GRAB POINT x_s = grabs[g].point. A 3-DOF device gives
///     [0; F]; a 6-DOF device adds the couple in the moment part.
///   * f_feed[g] (output) is f_ext + Σ f_i of the grabbed body, expressed AT THE SAME GRAB POINT x_s.
///     Its force part is what a 3-DOF device renders; a 6-DOF device also takes the moment. It is the
///     load the rest of the world (gravity, applied loads, joints) puts on the grabbed body, so on an
///     anchored body pulled by f_u it is ≈ −f_u (resistance) and on a free body it is f_ext (§11.5).
///     With several grabs on the same body, each grab gets that body's f_feed (which excludes ALL
///     user forces on the body), expressed at its own point.
///   * To apply f_u in the simulation, add grab_force_at_body_origin(snap, g, f_u[g]) (i.e. f_u moved
///     from x_s to r_k) to State::f_ext[body]: State::f_ext lives at the body origin r_k.
///
/// Hybrid (adaptive) bodies: the snapshot reads whatever Data holds for the nodes of E — W, β, Φ —
/// so rigid nodes work unchanged provided the simulation has filled W and β of every rigid node of U
/// (§6.3: T = 1₆, W = Φ̂^{-1}) and Φ of every node of E (including the grabbed leaf and any rigid
/// sibling) before make_coupling_snapshot() is called. Every coefficient used is linear in the user
/// force with the same recurrence for active and rigid nodes, so β_ext recovery (below) is exact too.
#pragma once

#include <cstdint>
#include <vector>

#include "haptree/data.hpp"

namespace haptree {

/// One user's grab: the body and the material point held, as the simulation last saw them.
struct Grab {
  int body = -1;                    ///< grabbed body id (1 … nbodies−1; the ground cannot be grabbed)
  Vec3 point = Vec3::Zero();        ///< x_s: grab point, world frame, scene units
  Vec3 velocity = Vec3::Zero();     ///< ẋ_s: velocity of that material point, world frame
};

/// A flat value that maps 1:1 onto lcmt_coupling_snapshot. `ints` and `values` hold the per-node
/// records (layout below, owned by this file; `ints[0]` is kSnapshotLayout so a reader can tell).
struct CouplingSnapshot {
  std::uint64_t model_fingerprint = 0;   ///< Model::fingerprint of the model it was made from
  std::int64_t version = -1;        ///< server step counter
  std::int64_t source_instance = 0; ///< instance_id of the message it came from (set by its receiver; 0 in-process)
  double sim_time = 0;              ///< simulated time of the step, scene units
  std::vector<Grab> grabs;          ///< the grabs it serves, in the order of coupling_forces' f_u
  std::vector<std::int32_t> ints;   ///< header, grab and node records (layout below)
  std::vector<double> values;       ///< node coefficients (layout below)
};

/// Layout of CouplingSnapshot::ints / values (version kSnapshotLayout).
///   ints  = header[kHeaderInts] | grab records (kGrabInts each) | node records (kNodeInts each)
///   header: [layout, n_grabs, n_nodes (= |U|), n_leaves, n_slots (Σ_U h), max_h, n_extended (= |E|),
///            n_values]
///   grab record: [body, local node of its leaf, value offset]
///   node record (local nodes are U in ascending assembly-tree id: 0 is the root, parents first):
///     [tree node id, local parent (-1 root), local P (-1 if P ∉ U), local Q (-1 if Q ∉ U),
///      slot_j, slot_k, h, h_P, value offset, slot offset (prefix Σ h), kind (NodeKind), body (leaves)]
///   values: internal node: W (21: upper triangle, column by column) | β_ext (6) |
///                          h blocks of 36 (column-major 6×6):
///             block c = Φ^P_{i j} for C-slot c < h_P−1 (i = c-th handle of P', in P's order),
///                       Φ^Q_{l k} for c ≥ h_P−1 (l = (c−h_P+1)-th handle of Q')
///           leaf:          I^{-1} (36) | f_ext (6) | r_k (3) | h offsets (3 each: handle point − r_k)
///           grab:          x_s − r_k (3) | R_k (9, column-major) | ω_k (3)
constexpr std::int32_t kSnapshotLayout = 0x48435031;   ///< "HCP1"
constexpr int kHeaderInts = 8;    ///< ints of the header
constexpr int kGrabInts = 3;      ///< ints per grab record
constexpr int kNodeInts = 12;     ///< ints per node record
constexpr int kGrabValues = 15;   ///< values per grab: offset (3), rotation (9), angular velocity (3)

/// Builds the snapshot for `grabs` from a Data that has just completed a DCA pass (Φ, W, β of the
/// nodes of E; Iinv, f_total, r, d, R, v of the grabbed bodies).
/// `f_u_applied`: the user forces that pass applied (one per grab, at grabs[g].point, world axes, the
/// same convention as coupling_forces' f_u), or empty if none was applied. β_ext and f_ext are
/// recovered exactly by removing their contribution: f_ext,k = f_total,k − Σ f_u (moved to r_k), and
/// β_ext = β − Δβ_applied, with Δβ_applied from the same linear O(|U|) bottom-up recurrence that
/// coupling_forces uses. Repeated bodies are allowed.
/// Throws std::invalid_argument (with the grab index) on a bad body id or a size mismatch.
/// Reuses `out`'s capacity: once sized by an equal or larger grab set, it does not allocate.
/// Subnormals: every subnormal value of the snapshot is set to 0 (an absolute change
/// below 2⁻¹⁰²² ≈ 2.2e-308 per value). On a 65 536-chain the Φ columns of deep, long segments decay
/// to 5e-324, and each subnormal operand costs Intel CPUs ~100 cycles in coupling_forces; the
/// consumer of a snapshot (another process, Python) then needs no FP-mode change. `flush_tiny =
/// false` keeps them (tests).
void make_coupling_snapshot(const Model& model, const Data& data, const std::vector<Grab>& grabs,
                            const std::vector<Vec6>& f_u_applied, std::int64_t version,
                            double sim_time, CouplingSnapshot& out, bool flush_tiny = true);

/// Number of subnormal doubles in [p, p + n) (diagnostics and tests).
std::size_t count_subnormals(const double* p, std::size_t n) noexcept;
/// Sets every subnormal value of [v, v + n) to 0 (each changes by less than 2⁻¹⁰²²); returns how many.
std::size_t flush_subnormals(double* v, std::size_t n) noexcept;

/// Grab g's world point and point velocity from body-local coordinates, from Data after kinematics
/// and body_dynamics_terms (forward_dynamics does both).
Grab make_grab(const Data& data, int body, const Vec3& local_point);

/// Result of coupling_forces.
enum class CouplingStatus : int {
  kOk = 0,               ///< f_feed written
  kEmpty,                 ///< snapshot has no grabs: nothing written
  kBadSnapshot,           ///< inconsistent layout / sizes / indices (e.g. corrupt or foreign message)
  kWorkspaceTooSmall,     ///< call CouplingWorkspace::reserve_for(snapshot) outside the hot loop
  kNonFinite,             ///< non-finite f_u or result: f_feed set to zero (never render NaN)
};
const char* coupling_status_name(CouplingStatus s);   ///< "ok", "empty", …

/// Scratch for coupling_forces, sized once; a call touches only O(|U|) entries (nothing O(n)).
struct CouplingWorkspace {
  CouplingWorkspace() = default;
  /// Room for snapshots of up to `max_nodes` up-region nodes and `max_slots` handle slots.
  CouplingWorkspace(int max_nodes, int max_slots);
  /// Room for `snapshot` (and any snapshot no larger).
  explicit CouplingWorkspace(const CouplingSnapshot& snapshot) { reserve_for(snapshot); }
  /// Grows (allocates) if `snapshot` needs more room; never shrinks. Not for the hot loop.
  void reserve_for(const CouplingSnapshot& snapshot);
  bool fits(const CouplingSnapshot& snapshot) const;   ///< whether coupling_forces can run without growing

  std::vector<double> bu;        ///< 6 × n_slots: b_u per handle slot of each U node
  std::vector<double> f;         ///< 6 × n_slots: handle forces per slot of each U node
  std::vector<double> dbeta;       ///< 6 × n_nodes: Δβ per U node
  std::vector<double> fu_leaf;     ///< 6 × n_nodes (leaves only): Σ user forces at r_k
  std::vector<double> feed_leaf;   ///< 6 × n_nodes (leaves only): f_feed at r_k
  std::vector<double> W;           ///< 36 × n_nodes: W unpacked by the bottom-up for the top-down
  /// Instrumentation: assembly-tree nodes whose coefficients the last call read (= |E|: the nodes
  /// of U plus every child of a U node that is not in U); 2·depth(L)+1 for a single grab.
  std::int64_t nodes_read = 0;
};

/// Feedback forces for every grab of `snapshot` under the user forces `f_u` (snapshot.grabs.size()
/// entries, at the grab points, world axes). Writes f_feed[g] at grabs[g].point (world axes).
/// No allocation, no locks, O(|U|·h²) (= O(n_f log(n/n_f)) on balanced trees).
CouplingStatus coupling_forces(const CouplingSnapshot& snapshot, const Vec6* f_u,
                               CouplingWorkspace& ws, Vec6* f_feed) noexcept;

/// Cheap structural check (O(|U|) integer compares); coupling_forces calls it on every call.
CouplingStatus validate_coupling_snapshot(const CouplingSnapshot& snapshot) noexcept;

/// Grab g's record, decoded from the snapshot (no allocation).
Vec3 snapshot_grab_offset(const CouplingSnapshot& s, int g);            ///< x_s − r_k
Mat3 snapshot_grab_rotation(const CouplingSnapshot& s, int g);          ///< R_k (body → world)
Vec3 snapshot_grab_angular_velocity(const CouplingSnapshot& s, int g);  ///< ω_k, world axes
/// f (at x_s) moved to the body origin r_k: what to add to State::f_ext[body].
Vec6 grab_force_at_body_origin(const CouplingSnapshot& s, int g, const Vec6& f_at_grab_point);
/// Payload size of the snapshot in bytes (the LCM message adds ~60 bytes of fixed fields).
std::size_t snapshot_payload_bytes(const CouplingSnapshot& s);

// ---------------------------------------------------------------------------------------------------
// Virtual coupling (seed eq. 9 + damping) and device <-> scene units.

/// The ONE place where device units (metres, newtons, N·m, device axes) meet scene units.
///   scene point  = offset + rotation · (position_scale · device point)
///   scene vel.   = rotation · (position_scale / time_scale · device velocity)
///   device force = force_scale · rotationᵀ · scene force;   device torque = torque_scale · rotationᵀ · τ
struct WorkspaceMapping {
  double position_scale = 1.0;        ///< scene length units per device metre
  double force_scale = 1.0;           ///< newtons per scene force unit
  double torque_scale = 1.0;          ///< N·m per scene torque unit
  double time_scale = 1.0;            ///< scene time units per device second (velocities only)
  Vec3 offset = Vec3::Zero();         ///< scene position of the device origin
  Mat3 rotation = Mat3::Identity();   ///< device axes → scene axes (orthonormal)

  Vec3 device_to_scene_point(const Vec3& x_device_m) const;        ///< device metres → scene point
  Vec3 device_to_scene_velocity(const Vec3& v_device_mps) const;   ///< m/s → scene velocity
  Mat3 device_to_scene_rotation(const Mat3& R_device) const;      ///< orientation in scene axes
  Vec3 device_to_scene_angular_velocity(const Vec3& w_device) const;   ///< rad/s → rad per scene time
  Vec3 scene_to_device_force(const Vec3& f_scene) const;          ///< → N
  Vec3 scene_to_device_torque(const Vec3& tau_scene) const;       ///< → N·m
};

/// 3-DOF: f = k_s (x_h − x_s) + b_s (ẋ_h − ẋ_s), applied at x_s: spring and damper both pull the
/// body towards the hand's motion (b_s > 0 damps the relative velocity). Scene units throughout.
/// Explicit integration bounds b_s on the simulated side: b_s < 2 m_eff/dt − k_s dt/2 (measured
/// by tools/passivity_sweep --bs-threshold, docs/accuracy_and_stability.md).
struct VirtualCoupling3 {
  double k_s = 0;   ///< stiffness, scene force / scene length
  double b_s = 0;   ///< damping, scene force / scene velocity
  /// Spatial user force at x_s: [0; f].
  Vec6 user_force(const Vec3& x_h, const Vec3& xd_h, const Vec3& x_s, const Vec3& xd_s) const;
};

/// 6-DOF: the 3-DOF spring-damper on the point plus a rotational spring-damper
/// τ = k_r · log(R_h (R_s R_grab)ᵀ) + b_r (ω_h − ω_s), where R_grab is the device-to-body relative
/// orientation captured at grab time (R_grab = R_sᵀ R_h then, so the torque starts at zero).
/// log(·) is the rotation vector (axis · angle, angle in [0, π]).
struct VirtualCoupling6 {
  VirtualCoupling3 linear;          ///< the point's spring-damper
  double k_r = 0;   ///< scene torque / rad
  double b_r = 0;   ///< scene torque / (rad / scene time)
  Mat3 R_grab = Mat3::Identity();   ///< device-to-body orientation captured at grab time
  /// Spatial user force at x_s: [τ; f].
  Vec6 user_force(const Vec3& x_h, const Vec3& xd_h, const Mat3& R_h, const Vec3& w_h,
                  const Vec3& x_s, const Vec3& xd_s, const Mat3& R_s, const Vec3& w_s) const;
};

/// Rotation vector of R (axis · angle), robust near 0 and π.
Vec3 rotation_log(const Mat3& R);

}  // namespace haptree
