#pragma once

#include <limits>
// SimServer: the paper's simulation loop as a class (STYLE.md §7.1). Loads a scene, steps adaptive DCA
// dynamics, applies the latest user force of every user, and after every step publishes one coupling
// snapshot per user with an active grab (HAPTREE_COEFFS_<user>), the scene state at a display rate and
// process stats at 1 Hz. No math here: the formulas live in haptree/.
#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "haptree/adaptive.hpp"
#include "haptree/bus/bus.hpp"
#include "haptree/coupling.hpp"
#include "haptree/data.hpp"
#include "haptree/lcmt_user_force.hpp"

namespace haptree {
namespace molecule_fwd {
struct Holder;
}
namespace mol {
class TrajectoryRecorder;
}

struct SimServerOptions {
  std::string scene = "protein_like";  // procedural name, or molecule name / PDB path
  int n = 64;                          // bodies for procedural scenes
  std::string urdf;                    // URDF file (overrides --scene)
  // Gravity of procedural scenes and URDF models; NaN = the default: none for protein_like (it
  // stands for a molecule, and a 100-m floppy tree falling under gravity whips its light ends until
  // the explicit step diverges, docs/accuracy_and_stability.md), −9.81 z for the robot scenes.
  // Molecules always have none.
  Vec3 gravity = Vec3::Constant(std::numeric_limits<double>::quiet_NaN());
  int budget_dofs = 48;                // budget mode (default)
  double epsilon = 0;                  // > 0: threshold mode with this ε
  int reselect_every = 10;
  double dt = 1e-3;                    // scene time units (s for procedural scenes, ps for molecules)
  int64_t steps = 0;                   // 0: run until stopped
  double rate_hz = 0;                  // 0: free-running
  double display_rate_hz = 30;
  int users = 1;                       // users 0..users-1 listened to
  std::string channel_suffix;
  // Blow-up guard: a non-finite state or a joint rate above this (rad or scene length per scene
  // time unit) restores the last checkpoint at rest instead of serving a diverged body.
  double max_joint_rate = 1e3;
  int checkpoint_every = 500;          // steps between checkpoints of a healthy state
  // ---- trajectory (issue 12): atoms (molecules) or body origins to a .dcd or .pdb file ----
  std::string trajectory;              // "" = none
  int trajectory_every_steps = 100;
  double trajectory_every_time = 0;    // > 0: a frame every this much scene time instead
  // ---- end trajectory ----
};

class SimServer {
 public:
  SimServer(bus::Bus& bus, const SimServerOptions& options);
  ~SimServer();
  // Runs until `stop` is true or --steps are done. Returns 0.
  int run(const std::atomic<bool>& stop);
  const Model& model() const { return *model_; }
  // Telemetry for the launcher (relaxed atomics, read from another thread).
  int64_t steps_done() const { return steps_.load(std::memory_order_relaxed); }
  double last_step_ms() const { return step_ms_.load(std::memory_order_relaxed); }
  int active_dofs() const { return active_dofs_.load(std::memory_order_relaxed); }
  int64_t snapshots_published() const { return snapshots_.load(std::memory_order_relaxed); }
  size_t last_snapshot_bytes() const { return snapshot_bytes_.load(std::memory_order_relaxed); }
  int64_t resets() const { return resets_.load(std::memory_order_relaxed); }

 private:
  struct UserSlot;
  void step_once();
  void publish_snapshots();
  void publish_scene_state(double step_ms);
  void publish_stats(double rate_hz);

  bus::Bus& bus_;
  SimServerOptions opt_;
  std::shared_ptr<const Model> model_;
  std::unique_ptr<molecule_fwd::Holder> molecule_;
  std::unique_ptr<Data> data_;
  std::unique_ptr<State> state_;
  std::unique_ptr<AdaptiveData> ad_;
  AdaptiveOptions adaptive_;
  std::vector<std::unique_ptr<UserSlot>> users_;
  std::vector<char> active_mask_;
  int64_t version_ = 0;
  int64_t snapshot_errors_ = 0;
  std::unique_ptr<State> checkpoint_;   // last healthy state (q, t); restored at rest on blow-up
  int64_t steps_since_checkpoint_ = 0;
  std::atomic<int64_t> resets_{0};
  bool just_reset_ = false;
  bool guard_state();
  // Trajectory (--trajectory): written after a healthy step when due; an I/O error stops the
  // recording (one log line), never the session.
  std::unique_ptr<mol::TrajectoryRecorder> trajectory_;
  std::vector<Vec3> trajectory_x_;
  void record_trajectory();
  std::atomic<int64_t> steps_{0}, snapshots_{0};
  std::atomic<double> step_ms_{0};
  std::atomic<int> active_dofs_{0};
  std::atomic<size_t> snapshot_bytes_{0};
};

}  // namespace haptree
