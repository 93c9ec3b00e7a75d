#pragma once

#include <limits>
// SimServer: the paper's simulation loop as a class. Loads a scene, steps adaptive DCA
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
#include "haptree/lcmt_scene_state.hpp"
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
  // Watchdog on user forces: a user whose USER_FORCE has not arrived for user_force_stale_s has the force
  // ramped to zero over user_force_ramp_s (and back up over 0.1 s once fresh). The coupler sends at 1 kHz,
  // so 100 ms is 100 lost messages, and 2x the coupler's own stale time (50 ms): a stall of the coupler's
  // inputs is handled by the coupler first, a dead coupler or link by this watchdog.
  double user_force_stale_s = 0.1;
  double user_force_ramp_s = 0.05;
  // Scene-side limit on an incoming user force (norm of the force part; the moment part gets the same
  // number per scene length unit); larger ones are clamped, non-finite ones zeroed, both counted. The
  // default follows from the coupler's defaults: it clamps f_u to 2 x max_force_n / force_scale =
  // 2 x 3 N / 0.5 N per unit = 12 scene force units; the launcher passes the value of its own options.
  double max_user_force = 12.0;
  // ---- trajectory: atoms (molecules) or body origins to a .dcd or .pdb file ----
  std::string trajectory;              // "" = none
  int trajectory_every_steps = 100;
  double trajectory_every_time = 0;    // > 0: a frame every this much scene time instead
  // ---- end trajectory ----
};

// Health counters of the server (relaxed atomics; the stats message carries them).
struct SimServerCounters {
  std::atomic<int64_t> user_forces_in{0};     // USER_FORCE messages accepted (decoded, from the locked coupler)
  std::atomic<int64_t> foreign_rejected{0};   // USER_FORCE from a second coupler instance while one is live
  std::atomic<int64_t> stale_rejected{0};     // USER_FORCE older than the newest one of the same coupler
  std::atomic<int64_t> watchdog_events{0};    // user-force watchdog trips (fresh -> stale)
  std::atomic<int64_t> clamp_events{0};       // user forces above max_user_force, clamped
  std::atomic<int64_t> nonfinite_events{0};   // non-finite user forces, zeroed
  std::atomic<double> user_force_gap_max_s{0};  // longest time between two USER_FORCE of a user (whole run)
  std::atomic<bool> ftz_daz{false};           // run()'s thread steps with flush-to-zero + denormals-are-zero
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
  // ... of which undone within the active region (no selection in the step): resets() - this selected in the step.
  int64_t local_resets() const { return local_resets_.load(std::memory_order_relaxed); }
  // Longest whole step of the run after the first (step, snapshot, scene chunks), ms, and which step it
  // was (0: none yet). The first step selects the first region, a pass over the whole tree.
  double longest_step_ms() const { return longest_step_ms_.load(std::memory_order_relaxed); }
  int64_t longest_step_index() const { return longest_step_index_.load(std::memory_order_relaxed); }
  const SimServerCounters& counters() const { return c_; }
  int64_t instance_id() const { return instance_id_; }
  // Force (at the grab point, world axes) applied to user u in the last step, after the watchdog and
  // the clamp. Read it from the thread that runs the server (or after run() returned).
  Vec6 applied_user_force(int u) const;
  // |force part| of the same, readable from any thread (telemetry).
  double applied_user_force_norm(int u) const;

 private:
  struct UserSlot;
  void step_once();
  void publish_snapshots();
  void publish_scene_state(double step_ms);
  void publish_stats(double rate_hz);
  // Real-time accounting of the last stats window.
  void check_rate(double steps_per_s, double mean_step_ms, double max_step_ms);
  double window_step_ms_sum_ = 0, window_step_ms_max_ = 0;
  int slow_windows_ = 0;
  bool warned_rate_ = false;
  double last_rate_fraction_ = 0, last_real_time_factor_ = 0, last_max_step_ms_ = 0;

  void take_user_force(UserSlot& u, double now_s);
  bus::Bus& bus_;
  SimServerOptions opt_;
  int64_t instance_id_;
  SimServerCounters c_;
  int64_t stats_seq_ = 0;
  double max_step_ms_ = 0;   // over the current stats period
  std::atomic<double> longest_step_ms_{0};        // over the whole run
  std::atomic<int64_t> longest_step_index_{0};
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
  int64_t checkpoint_selections_ = -1;  // AdaptiveReport::selections of the region at the checkpoint
  std::atomic<int64_t> resets_{0}, local_resets_{0};
  bool just_reset_ = false;
  bool resync_ = false;             // next step selects synchronously (after a reset of the state)
  std::vector<int> loaded_, keep_;  // bodies with a user force (robot scenes); grabbed bodies
  int scene_chunk_ = -1;            // next scene-state chunk to publish (-1: none pending)
  lcmt_scene_state scene_msg_;      // reused (no allocation per chunk once sized)
  bool guard_state();
  void publish_scene_chunks();
  // Trajectory (--trajectory): written after a healthy step when due; an I/O error stops the
  // recording (one log line), never the session.
  std::unique_ptr<mol::TrajectoryRecorder> trajectory_;
  std::vector<Vec3> trajectory_x_;
  void record_trajectory();
  std::atomic<int64_t> steps_{0}, snapshots_{0};
  std::atomic<double> step_ms_{0};
  std::atomic<int> active_dofs_{0};
  std::atomic<size_t> snapshot_bytes_{0};
  // Last member: destroyed first, so no callback (they capture this) runs into freed members.
  bus::SubscriptionGuard subs_;
};

}  // namespace haptree
