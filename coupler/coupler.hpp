#pragma once
// Coupler: the paper's coupling loop as a class (STYLE.md §7.1), one per user/device.
// Keeps the latest complete coupling snapshot (LatestValue, swapped between two computations) and the
// latest device pose; at --rate-hz computes f_u (virtual coupling), f_feed (coupling_forces on the
// snapshot alone), maps f_feed to device units, guards it (ForceSafety: NaN, watchdog, clamp) and
// publishes FEEDBACK to the device and USER_FORCE to the server.
#include <atomic>
#include <cstdint>
#include <memory>
#include <string>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/latency_histogram.hpp"
#include "haptree/bus/latest_value.hpp"
#include "haptree/bus/shm_channel.hpp"
#include "haptree/coupling.hpp"
#include "haptree/lcmt_device_state.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "haptree/lcmt_scene_state.hpp"
#include "haptree/lcmt_user_force.hpp"
#include "haptree/safety.hpp"

namespace haptree {

struct CouplerOptions {
  int user = 0;
  int device = 0;
  double rate_hz = 10000;             // coupling loop rate
  bool busy_wait = true;              // busy pacing (true) or sleep_until (false)
  double stiffness = 20;              // k_s, scene force / scene length
  double damping = 0;                 // b_s, scene force / scene velocity; < 2 m_eff/dt_sim − k_s dt_sim/2
  double position_scale = 10;         // scene length units per device metre
  double force_scale = 0.5;           // newtons per scene force unit
  Vec3 offset = Vec3::Zero();         // scene position of the device origin
  int grab_body = -1;                 // -1: the body nearest the device point in the latest scene state
  double max_force_n = 3.0;           // clamp (device limit)
  double stale_after_s = 0.005;       // watchdog: snapshot/pose older than this is stale
  double user_force_rate_hz = 1000;   // USER_FORCE publication rate
  uint64_t model_fingerprint = 0;     // 0: lock onto the first snapshot's fingerprint
  bool shm = false;                   // device link over shared memory
  int max_nodes = 8192, max_slots = 16384;   // coupling workspace, reserved once
  std::string channel_suffix;
};

struct CouplerCounters {
  std::atomic<int64_t> iterations{0}, snapshots_accepted{0}, foreign_rejected{0}, stale_rejected{0},
      bad_rejected{0}, feedback_published{0};
  std::atomic<double> rate_hz{0}, p50_us{0}, p99_us{0}, snapshot_age_ms{-1}, force_n{0};
  std::atomic<int64_t> version_in_use{-1};
  std::atomic<int64_t> restarts{0};               // snapshot streams resumed with a lower version (new server)
  std::atomic<int64_t> last_snapshot_utime{0};    // system clock (µs) when the newest snapshot was accepted
};

class Coupler {
 public:
  Coupler(bus::Bus& bus, const CouplerOptions& options);
  ~Coupler();
  int run(const std::atomic<bool>& stop);
  const CouplerCounters& counters() const { return c_; }
  const CouplerOptions& options() const { return opt_; }
  int64_t rejected_messages() const;

 private:
  void on_snapshot(const void* data, uint32_t size);
  bool iterate(double now_s);
  void publish_stats(double period_s, int64_t iterations);

  bus::Bus& bus_;
  CouplerOptions opt_;
  WorkspaceMapping map_;
  VirtualCoupling3 vc_;
  ForceSafety safety_;
  CouplerCounters c_;
  // snapshot mailbox (writer: bus handler thread; reader: loop)
  bus::LatestValue<CouplingSnapshot> snap_box_;
  lcmt_coupling_snapshot snap_msg_;
  int64_t newest_version_ = -1;        // handler-side
  std::atomic<uint64_t> locked_fingerprint_{0};
  bool warned_foreign_ = false, warned_stale_ = false;
  std::atomic<double> snapshot_recv_s_{-1};   // arrival time (loop clock) of the newest accepted snapshot
  // device pose
  bus::LatestValue<lcmt_device_state> pose_box_;
  std::atomic<double> pose_recv_s_{-1};
  std::unique_ptr<bus::ShmReader> shm_pose_;
  std::unique_ptr<bus::ShmWriter> shm_feedback_;
  lcmt_device_state pose_{};
  double pose_time_s_ = -1;
  // scene state (for the nearest-body pick on the grab edge only)
  bus::LatestValue<lcmt_scene_state> scene_box_;
  // loop state
  CouplingWorkspace ws_;
  bool grabbing_ = false;
  int32_t grab_seq_ = 0;               // device's press counter at our grab
  int body_ = -1;
  Vec3 grab_point_ = Vec3::Zero();
  int64_t user_seq_ = 0, feedback_seq_ = 0;
  double next_user_force_s_ = 0;
  lcmt_feedback fb_{};
  lcmt_user_force uf_{};
  Vec6 f_u_ = Vec6::Zero();
  Vec6 f_feed_ = Vec6::Zero();
  bus::LatencyHistogram hist_;
  std::string ch_feedback_, ch_user_force_, ch_stats_;
};

// The coupling computation of one loop iteration as a pure function of the logged inputs, shared by
// the coupler and tools/replay_coupling: device point (device metres) -> feedback force (N, clamped,
// before clamp and watchdog).
struct CouplingInputs {
  Vec3 position_m = Vec3::Zero();
  Vec3 velocity_mps = Vec3::Zero();
};
CouplingStatus coupler_feedback(const CouplerOptions& o, const CouplingSnapshot& snap, const CouplingInputs& in,
                                CouplingWorkspace& ws, Vec6& f_u, Vec6& f_feed, Vec3& force_n) noexcept;
WorkspaceMapping coupler_mapping(const CouplerOptions& o);

}  // namespace haptree
