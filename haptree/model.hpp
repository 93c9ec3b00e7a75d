/// @file
/// Model: the immutable description of an articulated body (bodies, joints, assembly tree).
/// Built once by ModelBuilder::build() (validates, builds the balanced assembly tree, computes the
/// fingerprint) and shared as std::shared_ptr<const Model>. Algorithms never write it.
#pragma once

#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "haptree/assembly_tree.hpp"
#include "haptree/spatial.hpp"

/// The core library: spatial algebra, the model and its data, the assembly tree, the DCA, the
/// adaptive layer, the coupling and the safety functions (docs/concepts.md, docs/algorithms.md).
namespace haptree {

/// Joint types: 1-DOF revolute and prismatic, 3-DOF spherical (quaternion), 6-DOF free, 0-DOF fixed.
enum class JointType { kRevolute, kPrismatic, kSpherical, kFree, kFixed };

const char* joint_type_name(JointType t);   ///< "revolute", "prismatic", …
int joint_dofs(JointType t);        ///< 1, 1, 3, 6, 0
int joint_nq(JointType t);          ///< 1, 1, 4 (quaternion w,x,y,z), 7 (x,y,z, w,x,y,z), 0

/// An invalid model or a model the algorithms cannot take; the message names the body or joint.
struct ModelError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

/// Units are the scene's: SI for robots; nm, ps, amu, kJ/mol, e for molecules (docs/molecules.md).
struct Model {
  int nbodies = 0;   ///< body 0 is the ground (world); joint k (k >= 1) connects parent[k] -> k
  int nq = 0;        ///< configuration coordinates
  int nv = 0;        ///< joint DOFs
  std::vector<std::string> body_name;               ///< (nbodies)
  std::vector<std::string> joint_name;              ///< (nbodies); joint_name[0] = ""
  std::vector<int> parent;                          ///< (nbodies); parent[0] = -1, parent[k] < k
  std::vector<JointType> joint_type;                ///< (nbodies)
  std::vector<int> q_adr;                           ///< (nbodies) joint k's first entry in q
  std::vector<int> v_adr;                           ///< (nbodies) joint k's first entry in q̇, q̈, τ
  std::vector<int> v_num;                           ///< (nbodies) joint k's DOFs
  /// Joint frame placement in the parent body frame (at q = 0). The successor body frame is the
  /// joint frame moved by the joint: its origin is the joint's handle point (docs/algorithms.md §2.3).
  std::vector<Mat3> joint_rotation;                 ///< (nbodies)
  std::vector<Vec3> joint_offset;                   ///< (nbodies)
  std::vector<Vec3> joint_axis;                     ///< (nbodies) unit, joint frame (rev/prism)
  std::vector<double> mass;                         ///< (nbodies); mass[0] = 0 (ground)
  std::vector<Vec3> com;                            ///< (nbodies) body frame
  std::vector<Mat3> inertia;                        ///< (nbodies) about the COM, body frame
  std::vector<std::vector<int>> children;           ///< (nbodies)
  Vec3 gravity{0, 0, -9.81};                        ///< world axes, scene units
  AssemblyTree tree;                                ///< derived, constant
  /// Rigid clusters: bodies joined by fixed joints (e.g. the pieces of a degree-reduced hub). An
  /// internal assembly node whose handles all attach to one cluster is assembled in inertia form
  /// (ABA-style sums of articulated inertias) instead of by the mobility difference formula, which
  /// cancels when a light piece is joined rigidly to a heavy assembly (docs/algorithms.md §4.4).
  enum class ClusterCase : std::uint8_t { kNone, kFixedMerge, kProjectP, kProjectQ, kGroundPin };
  std::vector<int> cluster_root;                    ///< (nbodies) top body of k's fixed-joint cluster
  std::vector<int> cluster_index;                   ///< (nnodes) slot in Data's cluster arrays, or -1
  std::vector<ClusterCase> cluster_case;            ///< (nnodes) how the node is assembled in inertia form
  std::vector<int> cluster_pin;                     ///< (nnodes) joint pinning the cluster to the ground, or -1
  /// Body whose origin is the reference point of a leaf or an inertia-form node's (M, p): the leaf's
  /// body; for a merge the reference of the heavier side. Never the cluster root as such: a weld far
  /// from its parent's frame would put every inertia of the far side at a far point (an ill-conditioned shift).
  std::vector<int> cluster_ref;                     ///< (nnodes) body id, or -1
  int ncluster_nodes = 0;                           ///< nodes assembled in inertia form
  std::uint64_t fingerprint = 0;                    ///< hash of everything above (canonical order)

  int joint_index(const std::string& name) const;   ///< -1 if absent
  int body_index(const std::string& name) const;    ///< -1 if absent
  int max_depth() const { return tree.max_depth; }  ///< depth of the assembly tree
};

/// Options of ModelBuilder::build.
struct BuildOptions {
  /// Bodies with more children than this are split into a chain of pieces joined by fixed joints so
  /// the assembly tree stays logarithmic (docs/algorithms.md §4.4). Costs accuracy in proportion to the
  /// degree; 0 disables it. The ground is never split.
  int max_children = 0;
};

/// Builds a Model body by body (each body after its parent), then checks and freezes it.
class ModelBuilder {
 public:
  ModelBuilder();
  /// Adds body `name` attached to `parent` (0 = ground) by a joint placed at `joint_offset`,
  /// rotated by `joint_rotation` in the parent frame; `axis` is in the joint frame. Mass properties
  /// are in the new body's frame (origin at the joint point). Returns the body id.
  int add_body(const std::string& name, int parent, JointType type, const Vec3& joint_offset,
               const Mat3& joint_rotation, const Vec3& axis, double mass, const Vec3& com,
               const Mat3& inertia_about_com, const std::string& joint_name = "");
  void set_gravity(const Vec3& g) { gravity_ = g; }                 ///< world axes, scene units
  int nbodies() const { return static_cast<int>(bodies_.size()); }  ///< including the ground
  /// Checks every body (finite geometry, positive mass, valid inertia) and builds the Model with its
  /// assembly tree; throws ModelError naming what is wrong.
  std::shared_ptr<const Model> build(const BuildOptions& options = {}) const;

 private:
  struct BodyRecord {
    std::string name, joint_name;
    int parent;
    JointType type;
    Vec3 offset;
    Mat3 rotation;
    Vec3 axis;
    double mass;
    Vec3 com;
    Mat3 inertia;
  };
  std::vector<BodyRecord> bodies_;
  Vec3 gravity_{0, 0, -9.81};
};

/// Neutral configuration (zero angles, identity quaternions).
Eigen::VectorXd neutral_configuration(const Model& model);

}  // namespace haptree
