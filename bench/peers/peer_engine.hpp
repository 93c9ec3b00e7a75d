// Peer engines for bench_peers: the same haptree::Model rebuilt in MuJoCo, Simbody and Bullet
// btMultiBody, each exposing one "forward dynamics from (q, q̇, τ)" call that the benchmark times.
// Only revolute and fixed joints are translated (the benchmark models use nothing else).
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "haptree/data.hpp"

namespace haptree::peers {

class PeerEngine {
 public:
  virtual ~PeerEngine() = default;
  virtual std::string name() const = 0;
  // What one timed call does, for the CSV/docs.
  virtual std::string timed_call() const = 0;
  // Copies q, q̇, τ (gravity is the model's) into the engine and computes q̈ (haptree order).
  // This is the call that is timed. State::f_ext must be zero (not translated).
  virtual void compute(const State& state) = 0;
  virtual const Eigen::VectorXd& qdd() const = 0;
};

// Every factory throws std::runtime_error with the reason when the model cannot be translated.
std::unique_ptr<PeerEngine> make_haptree_engine(const Model& model);
// forward_dynamics with set_dca_threads(…, 0): parallel passes where they pay.
std::unique_ptr<PeerEngine> make_haptree_auto_engine(const Model& model);
std::unique_ptr<PeerEngine> make_haptree_plain_engine(const Model& model);
std::unique_ptr<PeerEngine> make_haptree_exact_engine(const Model& model);
#ifdef HAPTREE_PEER_MUJOCO
// diaginertia = false: <inertial fullinertia=…> (MuJoCo's compiler finds the principal axes);
// true: principal axes computed by Eigen and written as quat + diaginertia.
std::unique_ptr<PeerEngine> make_mujoco_engine(const Model& model, bool diaginertia = false);
// MJCF files (name, text); the first is the main file, the rest are <include>d parts.
std::vector<std::pair<std::string, std::string>> mujoco_xml(const Model& model,
                                                            bool diaginertia = false);
#endif
#ifdef HAPTREE_PEER_SIMBODY
std::unique_ptr<PeerEngine> make_simbody_engine(const Model& model);
#endif
#ifdef HAPTREE_PEER_BULLET
std::unique_ptr<PeerEngine> make_bullet_engine(const Model& model);
#endif

// Names of the peers compiled in (besides "haptree").
std::vector<std::string> compiled_peers();

// Orthonormal rotation whose third column is the unit vector a (z axis onto a).
Mat3 frame_with_z(const Vec3& a);

}  // namespace haptree::peers
