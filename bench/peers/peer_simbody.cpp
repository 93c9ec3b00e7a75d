// Simbody translation: MobilizedBody::Pin per revolute joint (Weld per fixed joint). Pin rotates
// about the common z axis of its frames F (in the parent) and M (in the child), so
//   X_PF = (joint_rotation · Ra, joint_offset),  X_BM = (Ra, 0),  Ra·ẑ = joint axis,
// which gives R_PB(q) = joint_rotation · Rot(axis, q), as in haptree. Mass properties are given
// about the body origin (Simbody's convention). Gravity: Force::UniformGravity; τ:
// Force::DiscreteForces mobility forces.
#include "bench/peers/peer_engine.hpp"

#include <Simbody.h>

#include <stdexcept>

namespace haptree::peers {

namespace {

SimTK::Vec3 sv(const Vec3& v) { return SimTK::Vec3(v.x(), v.y(), v.z()); }
SimTK::Mat33 sm(const Mat3& m) {
  SimTK::Mat33 r;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) r(i, j) = m(i, j);
  return r;
}
SimTK::Rotation srot(const Mat3& m) { return SimTK::Rotation(sm(m), true); }   // trusted orthonormal

class SimbodyEngine final : public PeerEngine {
 public:
  explicit SimbodyEngine(const Model& model)
      : hm_(model), matter_(system_), forces_(system_),
        gravity_(forces_, matter_, sv(model.gravity)), discrete_(forces_, matter_) {
    std::vector<SimTK::MobilizedBody> mob(model.nbodies);
    mob[0] = matter_.Ground();
    for (int k = 1; k < model.nbodies; ++k) {
      const double m = model.mass[k];
      const Vec3 c = model.com[k];
      Mat3 Io = model.inertia[k] + m * (c.dot(c) * Mat3::Identity() - c * c.transpose());
      Io = 0.5 * (Io + Io.transpose()).eval();
      const SimTK::Body::Rigid body(SimTK::MassProperties(m, sv(c), SimTK::Inertia(sm(Io))));
      switch (model.joint_type[k]) {
        case JointType::kRevolute: {
          const Mat3 Ra = frame_with_z(model.joint_axis[k]);
          mob[k] = SimTK::MobilizedBody::Pin(
              mob[model.parent[k]],
              SimTK::Transform(srot(model.joint_rotation[k] * Ra), sv(model.joint_offset[k])),
              body, SimTK::Transform(srot(Ra), SimTK::Vec3(0)));
          break;
        }
        case JointType::kFixed:
          mob[k] = SimTK::MobilizedBody::Weld(
              mob[model.parent[k]],
              SimTK::Transform(srot(model.joint_rotation[k]), sv(model.joint_offset[k])), body,
              SimTK::Transform());
          break;
        default:
          throw std::runtime_error("simbody peer: joint " + std::to_string(k) + " of type " +
                                   joint_type_name(model.joint_type[k]) + " is not translated");
      }
    }
    state_ = system_.realizeTopology();
    system_.realizeModel(state_);
    if (state_.getNU() != model.nv) throw std::runtime_error("simbody peer: nu != nv");
    tau_.resize(model.nv);
    qdd_.setZero(model.nv);
  }
  std::string name() const override { return "simbody"; }
  std::string timed_call() const override {
    return "set Q, U, DiscreteForces mobility forces + realize(Stage::Acceleration), read UDot";
  }
  void compute(const State& st) override {
    const int nv = hm_.nv;
    SimTK::Vector& Q = state_.updQ();
    for (int i = 0; i < nv; ++i) Q[i] = st.q(i);
    SimTK::Vector& U = state_.updU();
    for (int i = 0; i < nv; ++i) U[i] = st.qd(i);
    for (int i = 0; i < nv; ++i) tau_[i] = st.tau(i);
    discrete_.setAllMobilityForces(state_, tau_);
    system_.realize(state_, SimTK::Stage::Acceleration);
    const SimTK::Vector& udot = state_.getUDot();
    for (int i = 0; i < nv; ++i) qdd_(i) = udot[i];
  }
  const Eigen::VectorXd& qdd() const override { return qdd_; }

 private:
  const Model& hm_;
  SimTK::MultibodySystem system_;
  SimTK::SimbodyMatterSubsystem matter_;
  SimTK::GeneralForceSubsystem forces_;
  SimTK::Force::UniformGravity gravity_;
  SimTK::Force::DiscreteForces discrete_;
  SimTK::State state_;
  SimTK::Vector tau_;
  Eigen::VectorXd qdd_;
};

}  // namespace

std::unique_ptr<PeerEngine> make_simbody_engine(const Model& model) {
  for (int k = 1; k < model.nbodies; ++k)
    if (model.joint_type[k] == JointType::kRevolute && model.q_adr[k] != model.v_adr[k])
      throw std::runtime_error("simbody peer: q/v layout differs (non-revolute joints present)");
  return std::make_unique<SimbodyEngine>(model);
}

}  // namespace haptree::peers
