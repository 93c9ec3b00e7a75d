// Bullet btMultiBody translation (double-precision build, BT_USE_DOUBLE_PRECISION). Bullet keeps
// each link frame at the link's COM with a diagonal inertia, so link k's Bullet frame is haptree
// body k's frame rotated by the inertia eigenvectors Q_k:  B_k = R_k Q_k.  Then
//   rotParentToThis = Q_kᵀ J_kᵀ Q_p       (J_k = joint_rotation; Q_ground = I)
//   jointAxis        = Q_kᵀ a_k            (this link's frame)
//   parentComToThisPivotOffset = Q_pᵀ (joint_offset_k − com_p)   (parent frame)
//   thisPivotToThisComOffset   = Q_kᵀ com_k                        (this frame)
// Bullet has no forward-dynamics-only entry point; the timed call is what a step does before
// integrating: setJointPos (updates each link's cached transform = kinematics), setJointVel,
// clearForcesAndTorques, addLinkForce(m g) at each COM (btMultiBodyDynamicsWorld's gravity),
// addJointTorque(τ), then computeAccelerationsArticulatedBodyAlgorithmMultiDof(dt = 0, …) with
// reused scratch buffers (dt = 0: velocities are not updated); q̈ is read from the scratch output
// (scratch_r[ndof + 6 + dof]). Damping (default 0.04) is set to 0; gyro term on (default).
#include "bench/peers/peer_engine.hpp"

#include <BulletDynamics/Featherstone/btMultiBody.h>
#include <BulletDynamics/Featherstone/btMultiBodyLink.h>

#include <Eigen/Eigenvalues>
#include <stdexcept>

namespace haptree::peers {

namespace {

btVector3 bv(const Vec3& v) { return btVector3(v.x(), v.y(), v.z()); }
btQuaternion bq(const Mat3& m) {
  const Quat q(m);
  return btQuaternion(q.x(), q.y(), q.z(), q.w());
}

class BulletEngine final : public PeerEngine {
 public:
  explicit BulletEngine(const Model& model) : hm_(model) {
    const int nl = model.nbodies - 1;
    mb_ = std::make_unique<btMultiBody>(nl, 1.0, btVector3(1, 1, 1), true, false);
    mb_->setLinearDamping(0);
    mb_->setAngularDamping(0);
    mb_->setUseGyroTerm(true);
    mb_->setMaxCoordinateVelocity(1e30);
    std::vector<Mat3> Q(model.nbodies, Mat3::Identity());
    link_of_dof_.assign(model.nv, -1);
    for (int k = 1; k < model.nbodies; ++k) {
      Eigen::SelfAdjointEigenSolver<Mat3> es(0.5 * (model.inertia[k] + model.inertia[k].transpose()));
      Mat3 Qk = es.eigenvectors();
      if (Qk.determinant() < 0) Qk.col(2) = -Qk.col(2);
      Q[k] = Qk;
      const int p = model.parent[k];
      const Vec3 com_p = p == 0 ? Vec3::Zero() : model.com[p];
      const Mat3 rot_parent_to_this = Qk.transpose() * model.joint_rotation[k].transpose() * Q[p];
      const Vec3 e = Q[p].transpose() * (model.joint_offset[k] - com_p);
      const Vec3 d = Qk.transpose() * model.com[k];
      const btVector3 inertia = bv(es.eigenvalues());
      switch (model.joint_type[k]) {
        case JointType::kRevolute:
          mb_->setupRevolute(k - 1, model.mass[k], inertia, p - 1, bq(rot_parent_to_this),
                             bv(Qk.transpose() * model.joint_axis[k]), bv(e), bv(d), true);
          link_of_dof_[model.v_adr[k]] = k - 1;
          break;
        case JointType::kFixed:
          mb_->setupFixed(k - 1, model.mass[k], inertia, p - 1, bq(rot_parent_to_this), bv(e),
                          bv(d));
          break;
        default:
          throw std::runtime_error("bullet peer: joint " + std::to_string(k) + " of type " +
                                   joint_type_name(model.joint_type[k]) + " is not translated");
      }
    }
    mb_->finalizeMultiDof();
    if (mb_->getNumDofs() != model.nv) throw std::runtime_error("bullet peer: ndof != nv");
    for (int k = 1; k < model.nbodies; ++k) gravity_force_.push_back(bv(model.mass[k] * model.gravity));
    qdd_.setZero(model.nv);
    State st(model);
    compute(st);   // size the scratch buffers once
  }
  std::string name() const override { return "bullet"; }
  std::string timed_call() const override {
    return "setJointPos/Vel + clearForcesAndTorques + addLinkForce(m g) + addJointTorque + "
           "computeAccelerationsArticulatedBodyAlgorithmMultiDof(dt=0)";
  }
  void compute(const State& st) override {
    const int nv = hm_.nv;
    for (int i = 0; i < nv; ++i) {
      mb_->setJointPos(link_of_dof_[i], st.q(i));
      mb_->setJointVel(link_of_dof_[i], st.qd(i));
    }
    mb_->clearForcesAndTorques();
    const int nl = hm_.nbodies - 1;
    for (int l = 0; l < nl; ++l) mb_->addLinkForce(l, gravity_force_[l]);
    for (int i = 0; i < nv; ++i) mb_->addJointTorque(link_of_dof_[i], st.tau(i));
    mb_->computeAccelerationsArticulatedBodyAlgorithmMultiDof(0, scratch_r_, scratch_v_, scratch_m_,
                                                              false, false, false);
    const btScalar* out = &scratch_r_[nv + 6];
    for (int i = 0; i < nv; ++i) qdd_(i) = out[i];
  }
  const Eigen::VectorXd& qdd() const override { return qdd_; }

 private:
  const Model& hm_;
  std::unique_ptr<btMultiBody> mb_;
  std::vector<int> link_of_dof_;
  btAlignedObjectArray<btVector3> gravity_force_;
  btAlignedObjectArray<btScalar> scratch_r_;
  btAlignedObjectArray<btVector3> scratch_v_;
  btAlignedObjectArray<btMatrix3x3> scratch_m_;
  Eigen::VectorXd qdd_;
};

}  // namespace

std::unique_ptr<PeerEngine> make_bullet_engine(const Model& model) {
  for (int k = 1; k < model.nbodies; ++k)
    if (model.joint_type[k] == JointType::kRevolute && model.q_adr[k] != model.v_adr[k])
      throw std::runtime_error("bullet peer: q/v layout differs (non-revolute joints present)");
  return std::make_unique<BulletEngine>(model);
}

}  // namespace haptree::peers
