#include "haptree/model.hpp"

#include <cmath>
#include <cstring>
#include <sstream>
#include <unordered_set>

#include <Eigen/Eigenvalues>

namespace haptree {

const char* joint_type_name(JointType t) {
  switch (t) {
    case JointType::kRevolute: return "revolute";
    case JointType::kPrismatic: return "prismatic";
    case JointType::kSpherical: return "spherical";
    case JointType::kFree: return "free";
    case JointType::kFixed: return "fixed";
  }
  return "?";
}
int joint_dofs(JointType t) {
  switch (t) {
    case JointType::kRevolute:
    case JointType::kPrismatic: return 1;
    case JointType::kSpherical: return 3;
    case JointType::kFree: return 6;
    case JointType::kFixed: return 0;
  }
  return 0;
}
int joint_nq(JointType t) {
  switch (t) {
    case JointType::kRevolute:
    case JointType::kPrismatic: return 1;
    case JointType::kSpherical: return 4;
    case JointType::kFree: return 7;
    case JointType::kFixed: return 0;
  }
  return 0;
}

int Model::joint_index(const std::string& name) const {
  for (int k = 1; k < nbodies; ++k)
    if (joint_name[k] == name) return k;
  return -1;
}
int Model::body_index(const std::string& name) const {
  for (int k = 0; k < nbodies; ++k)
    if (body_name[k] == name) return k;
  return -1;
}

ModelBuilder::ModelBuilder() {
  bodies_.push_back({"world", "", -1, JointType::kFixed, Vec3::Zero(), Mat3::Identity(),
                     Vec3::UnitZ(), 0.0, Vec3::Zero(), Mat3::Zero()});
}

int ModelBuilder::add_body(const std::string& name, int parent, JointType type,
                           const Vec3& joint_offset, const Mat3& joint_rotation, const Vec3& axis,
                           double mass, const Vec3& com, const Mat3& inertia_about_com,
                           const std::string& joint_name) {
  const int id = nbodies();
  auto where = [&] { return "body '" + name + "' (id " + std::to_string(id) + ")"; };
  if (parent < 0 || parent >= id)
    throw ModelError(where() + ": parent " + std::to_string(parent) + " does not exist yet");
  if (!(mass > 0) || !std::isfinite(mass))
    throw ModelError(where() + ": mass must be positive and finite, got " + std::to_string(mass));
  if (!com.allFinite() || !inertia_about_com.allFinite() || !joint_offset.allFinite() ||
      !joint_rotation.allFinite() || !axis.allFinite())
    throw ModelError(where() + ": non-finite geometry or inertia");
  const Mat3 Ic = 0.5 * (inertia_about_com + inertia_about_com.transpose());
  Eigen::SelfAdjointEigenSolver<Mat3> es(Ic);
  const Vec3 ev = es.eigenvalues();
  if (ev.minCoeff() <= 1e-14 * std::max(1.0, ev.maxCoeff()) ||
      ev(0) + ev(1) < ev(2) * (1 - 1e-9))
    throw ModelError(where() + ": inertia about the COM must be positive definite and satisfy "
                     "the triangle inequality (eigenvalues " +
                     std::to_string(ev(0)) + ", " + std::to_string(ev(1)) + ", " +
                     std::to_string(ev(2)) + ")");
  Vec3 a = axis;
  if (type == JointType::kRevolute || type == JointType::kPrismatic) {
    if (a.norm() < 1e-12) throw ModelError(where() + ": joint axis is zero");
    a.normalize();
  }
  if ((joint_rotation.transpose() * joint_rotation - Mat3::Identity()).norm() > 1e-9)
    throw ModelError(where() + ": joint rotation is not orthonormal");
  bodies_.push_back({name, joint_name.empty() ? name : joint_name, parent, type, joint_offset,
                     joint_rotation, a, mass, com, Ic});
  return id;
}

namespace {

// FNV-1a over canonical values (not raw struct bytes).
struct Hasher {
  std::uint64_t h = 1469598103934665603ull;
  void bytes(const void* p, size_t n) {
    auto c = static_cast<const unsigned char*>(p);
    for (size_t i = 0; i < n; ++i) { h ^= c[i]; h *= 1099511628211ull; }
  }
  void i(long long v) { bytes(&v, sizeof v); }
  void d(double v) { if (v == 0) v = 0; bytes(&v, sizeof v); }
  template <class M> void m(const M& x) { for (int k = 0; k < x.size(); ++k) d(x.data()[k]); }
  void s(const std::string& v) { i(static_cast<long long>(v.size())); bytes(v.data(), v.size()); }
};

// Marks the internal nodes that can be assembled in inertia form (Model::cluster_case). A node
// qualifies when all its handles attach to one multi-body fixed-joint cluster and either
//  - its principal joint is fixed and both children are in inertia form on that cluster (merge:
//    M_C = M_P + M_Q), or
//  - one child has a single handle (the principal joint) and the other is in inertia form on the
//    cluster (projection of the one-handle side's articulated inertia across the joint, as in ABA);
//  - one child is the ground and the principal joint enters the cluster's root body: the node keeps
//    the cluster's M and p and is "pinned" by that joint (its mobility is S U⁻¹ Sᵀ, U = SᵀMS).
// Leaves are always in inertia form (their body's inertia). A body fixed to the ground is the root
// of its own cluster, pinned by that fixed joint.
void classify_clusters(Model& m) {
  const auto& t = m.tree;
  const int nn = t.nnodes();
  m.cluster_root.assign(m.nbodies, 0);
  std::vector<int> cluster_size(m.nbodies, 0);
  for (int k = 1; k < m.nbodies; ++k) {
    const int p = m.parent[k];
    m.cluster_root[k] = (m.joint_type[k] == JointType::kFixed && p > 0) ? m.cluster_root[p] : k;
    ++cluster_size[m.cluster_root[k]];
  }
  m.cluster_index.assign(nn, -1);
  m.cluster_case.assign(nn, Model::ClusterCase::kNone);
  m.cluster_pin.assign(nn, -1);
  m.cluster_ref.assign(nn, -1);
  m.ncluster_nodes = 0;
  std::vector<int> root_of_node(nn, -1);   // cluster of a node in inertia form (leaves included)
  std::vector<char> grounded(nn, 0);       // contains the ground: no finite articulated inertia
  std::vector<double> core_mass(nn, 0.0);  // mass of the inertia-form bodies (reference choice)
  for (int node = nn - 1; node >= 0; --node) {
    if (t.is_leaf(node)) {
      const int k = t.body[node];
      if (k > 0) root_of_node[node] = m.cluster_root[k];
      grounded[node] = k == 0;
      m.cluster_ref[node] = k > 0 ? k : -1;
      core_mass[node] = m.mass[k];
      continue;
    }
    grounded[node] = grounded[t.P[node]] || grounded[t.Q[node]];
    const int h = t.handle_num[node];
    if (h == 0) continue;
    const int R = m.cluster_root[t.attached_body(node, 0)];
    // A body welded to the ground counts even alone: in inertia form its pin makes it exactly
    // immovable, where the difference formula leaves a residual mobility ε·|Φ| (large at a far
    // handle: 1e-6 at 10⁶ m).
    const bool welded_to_ground =
        R > 0 && m.joint_type[R] == JointType::kFixed && m.parent[R] == 0;
    bool same = R > 0 && (cluster_size[R] >= 2 || welded_to_ground);
    for (int x = 1; x < h && same; ++x) same = m.cluster_root[t.attached_body(node, x)] == R;
    if (!same) continue;
    const int P = t.P[node], Q = t.Q[node], J = t.joint[node];
    Model::ClusterCase c = Model::ClusterCase::kNone;
    int pin = -1;
    if (t.is_leaf(P) && t.body[P] == 0 && J == R && root_of_node[Q] == R) {
      c = Model::ClusterCase::kGroundPin;   // before the fixed merge: a fixed pin is a pin too
      pin = J;
    } else if (m.joint_type[J] == JointType::kFixed) {
      if (root_of_node[P] == R && root_of_node[Q] == R) c = Model::ClusterCase::kFixedMerge;
      pin = std::max(m.cluster_pin[P], m.cluster_pin[Q]);
    } else if (t.handle_num[P] == 1 && !grounded[P] && root_of_node[Q] == R) {
      c = Model::ClusterCase::kProjectP;
    } else if (t.handle_num[Q] == 1 && !grounded[Q] && root_of_node[P] == R) {
      c = Model::ClusterCase::kProjectQ;
    }
    if (c == Model::ClusterCase::kNone) continue;
    if (c == Model::ClusterCase::kProjectP) pin = m.cluster_pin[Q];
    if (c == Model::ClusterCase::kProjectQ) pin = m.cluster_pin[P];
    // Reference point: the inertia-form side's (the heavier one for a merge), so (M, p) sit at a
    // body of the node near most of its mass, whatever the welds' lengths.
    int ref_child = Q;
    if (c == Model::ClusterCase::kFixedMerge) ref_child = core_mass[P] >= core_mass[Q] ? P : Q;
    if (c == Model::ClusterCase::kProjectQ) ref_child = P;
    m.cluster_ref[node] = m.cluster_ref[ref_child];
    core_mass[node] = c == Model::ClusterCase::kFixedMerge ? core_mass[P] + core_mass[Q]
                                                           : core_mass[ref_child];
    m.cluster_case[node] = c;
    m.cluster_pin[node] = pin;
    m.cluster_index[node] = m.ncluster_nodes++;
    root_of_node[node] = R;
  }
}

}  // namespace

std::shared_ptr<const Model> ModelBuilder::build(const BuildOptions& options) const {
  // Degree reduction (§4.4): a body with > max_children children becomes a chain of pieces joined
  // by fixed joints; each piece has the body's frame and an equal share of its inertia. The
  // pieces are inserted right after the body, so the order of the DOF-carrying joints is kept.
  std::vector<BodyRecord> recs = bodies_;
  if (options.max_children > 0) {
    std::vector<std::vector<int>> kids(recs.size());
    for (size_t k = 1; k < recs.size(); ++k) kids[recs[k].parent].push_back(static_cast<int>(k));
    std::vector<BodyRecord> out;
    std::vector<int> new_id(recs.size(), -1);
    // piece_for_child[c] = the new id of the piece that child c hangs from
    std::vector<int> piece_for_child(recs.size(), -1);
    for (size_t k = 0; k < recs.size(); ++k) {
      BodyRecord rec = recs[k];
      if (k > 0) rec.parent = piece_for_child[k];
      const int d = static_cast<int>(kids[k].size());
      const int id = static_cast<int>(out.size());
      new_id[k] = id;
      if (k == 0 || d <= options.max_children) {
        out.push_back(rec);
        for (int c : kids[k]) piece_for_child[c] = id;
        continue;
      }
      const int npieces = d - 1;
      BodyRecord first = rec;
      first.mass = rec.mass / npieces;
      first.inertia = rec.inertia / npieces;
      out.push_back(first);
      for (int p = 1; p < npieces; ++p) {
        BodyRecord piece = first;
        piece.name = rec.name + "#" + std::to_string(p);
        piece.joint_name = piece.name;
        piece.parent = id + p - 1;
        piece.type = JointType::kFixed;
        piece.offset = Vec3::Zero();
        piece.rotation = Mat3::Identity();
        out.push_back(piece);
      }
      for (int ci = 0; ci < d; ++ci) piece_for_child[kids[k][ci]] = id + std::min(ci, npieces - 1);
    }
    recs = std::move(out);
  }

  auto model = std::make_shared<Model>();
  Model& m = *model;
  m.nbodies = static_cast<int>(recs.size());
  m.gravity = gravity_;
  m.children.resize(m.nbodies);
  for (int k = 0; k < m.nbodies; ++k) {
    const BodyRecord& b = recs[k];
    m.body_name.push_back(b.name);
    m.joint_name.push_back(k == 0 ? "" : b.joint_name);
    m.parent.push_back(b.parent);
    m.joint_type.push_back(b.type);
    m.q_adr.push_back(m.nq);
    m.v_adr.push_back(m.nv);
    const int nv = k == 0 ? 0 : joint_dofs(b.type);
    m.v_num.push_back(nv);
    m.nq += k == 0 ? 0 : joint_nq(b.type);
    m.nv += nv;
    m.joint_rotation.push_back(b.rotation);
    m.joint_offset.push_back(b.offset);
    m.joint_axis.push_back(b.axis);
    m.mass.push_back(b.mass);
    m.com.push_back(b.com);
    m.inertia.push_back(b.inertia);
    if (k > 0) m.children[b.parent].push_back(k);
  }
  std::unordered_set<std::string> names;
  for (int k = 1; k < m.nbodies; ++k)
    if (!names.insert(m.joint_name[k]).second)
      throw ModelError("duplicate joint name '" + m.joint_name[k] + "'");
  m.tree = build_assembly_tree(m.parent);
  classify_clusters(m);

  Hasher h;
  h.i(m.nbodies);
  h.m(m.gravity);
  for (int k = 0; k < m.nbodies; ++k) {
    h.s(m.body_name[k]);
    h.s(m.joint_name[k]);
    h.i(m.parent[k]);
    h.i(static_cast<int>(m.joint_type[k]));
    h.m(m.joint_rotation[k]);
    h.m(m.joint_offset[k]);
    h.m(m.joint_axis[k]);
    h.d(m.mass[k]);
    h.m(m.com[k]);
    h.m(m.inertia[k]);
  }
  for (int v : m.tree.P) h.i(v);
  for (int v : m.tree.Q) h.i(v);
  for (int v : m.tree.joint) h.i(v);
  m.fingerprint = h.h;
  return model;
}

Eigen::VectorXd neutral_configuration(const Model& model) {
  Eigen::VectorXd q = Eigen::VectorXd::Zero(model.nq);
  for (int k = 1; k < model.nbodies; ++k) {
    const int a = model.q_adr[k];
    if (model.joint_type[k] == JointType::kSpherical) q(a) = 1;
    if (model.joint_type[k] == JointType::kFree) q(a + 3) = 1;
  }
  return q;
}

}  // namespace haptree
