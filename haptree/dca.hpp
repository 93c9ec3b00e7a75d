/// @file
/// Divide-and-conquer articulated-body algorithm (docs/algorithms.md §5–§7) in handle-point coordinates:
/// kinematics, the bottom-up assembly of every node's coefficients, the top-down back-substitution,
/// integration, and the energies used by the drift checks.
#pragma once

#include "haptree/data.hpp"
#include "haptree/isa.hpp"

namespace haptree {

/// Pose of body k from its parent's rotation Rp: rotation Rk and offset dk = r_k − r_parent.
void joint_placement(const Model& model, int k, const Eigen::VectorXd& q, const Mat3& Rp, Mat3& Rk,
                     Vec3& dk) noexcept;
/// S (1-DOF), v_k = shift(v_parent) + S q̇, c_J for joint k (needs R[k], d[k]); returns v_k.
Vec6 joint_motion_terms(const Model& model, Data& data, int k, const Eigen::VectorXd& qd,
                        const Vec6& v_parent) noexcept;
/// One joint of integrate_positions.
void integrate_joint(const Model& model, int k, Eigen::VectorXd& q, const Eigen::VectorXd& qd,
                     double dt) noexcept;

/// Body rotations and origins from q; relative offsets d_k from local data.
void forward_kinematics(const Model& model, Data& data, const Eigen::VectorXd& q) noexcept;
/// Body velocities, motion subspaces, c_J, inertias, bias forces (needs forward_kinematics).
void body_dynamics_terms(const Model& model, Data& data, const State& state) noexcept;

/// Leaf coefficients (§5.1) for one leaf node.
void dca_leaf(const Model& model, Data& data, int node) noexcept;
/// Assembly of one internal node from its children (§5.2), τ taken from `tau`.
void dca_assemble(const Model& model, Data& data, int node, const Eigen::VectorXd& tau) noexcept;
/// Back-substitution at one internal node (§7): children's handle forces, and q̈ if active.
void dca_top_down_node(const Model& model, Data& data, int node) noexcept;

/// Bottom-up pass (§5): every node's coefficients, leaves first (needs forward_kinematics and
/// body_dynamics_terms).
void dca_bottom_up(const Model& model, Data& data, const State& state) noexcept;
/// First of the two parts of dca_bottom_up, for callers that assemble only some nodes (adaptive.cpp's
/// incremental metric): the cluster offsets, once per pass, before any node (dca_bottom_up_node is
/// the other part).
void dca_cluster_offsets(const Model& model, Data& data) noexcept;
/// One body's step of it: data.cluster_offset[k] (+ _lo) = its parent's + d_k, compensated
/// (two-sum), for a body k that is not its cluster's root (also adaptive.cpp's hybrid pass).
void chain_cluster_offset(const Model& model, Data& data, int k) noexcept;
/// One node as dca_bottom_up assembles it: a leaf, a welded cluster's node in inertia form, or an
/// ordinary node; τ from `tau`.
void dca_bottom_up_node(const Model& model, Data& data, int node, const Eigen::VectorXd& tau) noexcept;
/// Top-down pass (§7): handle forces from the root down, and q̈ of every joint into data.qdd.
void dca_top_down(const Model& model, Data& data) noexcept;

/// Full forward dynamics: kinematics, both passes. Returns data.qdd. With data.dca_threads > 1 the
/// passes run on that many OpenMP threads over disjoint subtrees (bit-for-bit the serial result).
const Eigen::VectorXd& forward_dynamics(const Model& model, Data& data, const State& state) noexcept;
/// The instruction set the DCA's functions run at now. In the default (portable) build: avx2 when
/// isa::active() is avx2 or avx512 (the x86-64-v3 copy of the DCA), generic otherwise. In a build
/// for one CPU (-DHAPTREE_NATIVE=ON, HAPTREE_MARCH): the level its -march gives, whatever isa::active().
isa::Level dca_level() noexcept;

/// Data::refine. Sizes the refinement buffers a Data built with Refinement::kOff lacks and, for
/// kExtended, the long-double inverse-dynamics buffers (O(nbodies), 480 bytes per body); call it
/// before the pass, not in it.
void set_refinement(const Model& model, Data& data, Refinement r);

constexpr int kDcaParallelMinNodes = 1023;   ///< assembly nodes (≥ 512 bodies) below which threads do not pay
/// Threads for forward_dynamics. threads = 1: serial (the default). threads > 1: that
/// many, if the build has OpenMP. threads = 0: automatic, i.e. on only where it pays: at least
/// kDcaParallelMinNodes assembly nodes, at least 2 CPUs in this process's affinity mask and a free
/// core now (1-minute load average ≤ CPUs − 1); then one thread per CPU. Decided at this call (call
/// again to re-decide). Allocates the schedule; not per step. Returns the threads used.
/// Off by default because the embedded session's sim shares its 2 cores with the coupler and the
/// device bridge: a second DCA thread would take the coupler's core.
int set_dca_threads(const Model& model, Data& data, int threads);

using JointMat = Eigen::Matrix<double, 6, Eigen::Dynamic, 0, 6, 6>;   ///< 6 × (0..6), never allocates
/// Joint motion subspace S (6×n), constraint basis T (6×(6−n)) and D (6×n) at the handle point, world
/// axes (§1 table). Fixed-max-size matrices: no allocation.
void joint_subspaces(const Model& model, const Data& data, int joint, JointMat& S, JointMat& T,
                     JointMat& D) noexcept;

/// Semi-implicit Euler: qd += dt·qdd, then q integrated with the new qd (quaternions by exponential).
void integrate(const Model& model, Eigen::VectorXd& q, Eigen::VectorXd& qd,
               const Eigen::VectorXd& qdd, double dt) noexcept;
/// q integrated over dt with velocities qd (quaternions by exponential), every joint.
void integrate_positions(const Model& model, Eigen::VectorXd& q, const Eigen::VectorXd& qd,
                         double dt) noexcept;

/// Kinetic and gravitational potential energy (for drift checks).
double kinetic_energy(const Model& model, const Data& data) noexcept;
/// Gravitational potential energy of the bodies at their current origins (for drift checks).
double potential_energy(const Model& model, const Data& data) noexcept;

}  // namespace haptree
