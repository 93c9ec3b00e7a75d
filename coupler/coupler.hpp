#pragma once
// Coupler: the paper's coupling loop as a class (main.cpp is a thin shell over it), one per user/device.
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
#include "haptree/bus/origin.hpp"
#include "haptree/bus/shm_channel.hpp"
#include "haptree/coupling.hpp"
#include "haptree/lcmt_coupler_settings.hpp"
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
  bool busy_poll = false;             // while busy pacing, iterate as soon as a new device pose arrives
  double stiffness = 20;              // k_s, scene force / scene length
  double damping = 0;                 // b_s, scene force / scene velocity; < 2 m_eff/dt_sim − k_s dt_sim/2
  double position_scale = 10;         // scene length units per device metre
  double force_scale = 0.5;           // newtons per scene force unit
  Vec3 offset = Vec3::Zero();         // scene position of the device origin
  int grab_body = -1;                 // -1: the body nearest the device point in the latest scene state
  double grab_radius = 0;             // scene units: a press grabs the nearest body only within this distance
                                      // of the device point (the proxy); 0: the nearest body wherever it is
  double max_force_n = 3.0;           // clamp (device limit)
  double stale_after_s = 0.05;        // watchdog: snapshot/pose older than this is stale (measured default:
                                      // docs/performance.md; 5 ms tripped 5-17 times/s on 2 cores)
  double user_force_rate_hz = 1000;   // USER_FORCE publication rate
  uint64_t model_fingerprint = 0;     // expected model (--model-fingerprint); 0: lock onto the first one heard
  double max_device_position_m = 1.0; // a device position farther than this from the device origin (or
                                      // non-finite) is a glitch: refused, counted, the watchdog zeroes the force
  bool shm = false;                   // device link over shared memory
  int max_nodes = 8192, max_slots = 16384;   // coupling workspace, reserved once
  std::string channel_suffix;
};

struct CouplerCounters {
  std::atomic<int64_t> iterations{0}, snapshots_accepted{0}, foreign_rejected{0}, stale_rejected{0},
      bad_rejected{0}, feedback_published{0};
  std::atomic<double> rate_hz{0}, p50_us{0}, p99_us{0}, snapshot_age_ms{-1}, force_n{0};
  std::atomic<int64_t> version_in_use{-1};
  std::atomic<int> grab_body{0};                  // body held at the last stats window; 0: none
  std::atomic<int64_t> restarts{0};               // a new server instance after the old stream went silent
  std::atomic<int64_t> duplicate_rejected{0};     // snapshots of a second live server instance
  std::atomic<int64_t> implausible_rejected{0};   // version jumps beyond what the elapsed time allows
  std::atomic<int64_t> pose_rejected{0};          // DEVICE_STATE from another device instance, or absurd/non-finite
  std::atomic<int64_t> device_restarts{0};        // a new device_bridge instance after the old went silent
  std::atomic<int64_t> other_feedback_writer{0};  // another instance's FEEDBACK seen on our device's channel (shm: segment, 1/s)
  std::atomic<int64_t> user_force_clamps{0};      // f_u clamped to the scene-side limit
  std::atomic<int64_t> grab_feedbacks{0};         // feedback messages sent while grabbing
  std::atomic<int64_t> grab_watchdog_zeros{0};    // ... of which exactly zero because of the watchdog
  std::atomic<int64_t> last_snapshot_utime{0};    // system clock (µs) when the newest snapshot was accepted
  std::atomic<int64_t> subnormals_flushed{0};     // subnormal values of accepted snapshots set to 0
  std::atomic<bool> ftz_daz{false};               // run()'s thread computes with flush-to-zero + denormals-are-zero
  // Largest input age (snapshot or device pose, whichever is older) the watchdog saw while a grab's
  // coefficients were in use, ms.
  std::atomic<double> max_grab_input_age_ms{0};
  std::atomic<int64_t> grab_watchdog_trips{0};   // trips while a grab was held (the user's force taken away)
};

class Coupler {
 public:
  Coupler(bus::Bus& bus, const CouplerOptions& options);
  ~Coupler();
  int run(const std::atomic<bool>& stop);
  const CouplerCounters& counters() const { return c_; }
  const CouplerOptions& options() const { return opt_; }
  int64_t rejected_messages() const;
  int64_t instance_id() const { return instance_id_; }
  int64_t watchdog_trips() const { return safety_.watchdog().trips(); }   // read after run() returned

 private:
  void on_snapshot(const void* data, uint32_t size);
  bool iterate(double now_s);
  bool new_pose_waiting() const noexcept;                     // a device pose the loop has not taken yet
  void publish_stats(double period_s, int64_t iterations);
  bool take_pose(const lcmt_device_state& m, double now_s);   // origin + sanity; false = refused
  void report_problems();                                     // once-only warnings, outside the loop
  void publish_settings();   // HAPTREE_COUPLER_SETTINGS_<user>: at start, then every kSettingsEvery_s

  bus::Bus& bus_;
  CouplerOptions opt_;
  int64_t instance_id_;
  WorkspaceMapping map_;
  VirtualCoupling3 vc_;
  ForceSafety safety_;
  CouplerCounters c_;
  // snapshot mailbox (writer: bus handler thread; reader: loop)
  bus::LatestValue<CouplingSnapshot> snap_box_;
  lcmt_coupling_snapshot snap_msg_;
  int64_t newest_version_ = -1;        // handler-side
  double newest_accept_s_ = -1;        // handler-side: when newest_version_ was accepted
  bus::OriginLock server_lock_;        // handler-side: one live server instance
  std::atomic<uint64_t> locked_fingerprint_{0};
  // What the snapshot handler refused, for report_problems (the handler never logs): the first case of each.
  std::atomic<uint64_t> foreign_fp_{0};
  std::atomic<int64_t> old_snapshots_{0}, old_snapshot_instance_{0}, duplicate_instance_{0}, duplicate_locked_{0},
      takeover_instance_{0}, takeover_version_{0}, implausible_version_{0}, implausible_after_{0};
  std::atomic<double> old_snapshot_age_s_{0}, implausible_dt_s_{0};
  bool warned_foreign_ = false, warned_duplicate_ = false, warned_implausible_ = false, warned_old_snapshot_ = false,
       reported_lock_ = false;
  int64_t reported_restarts_ = 0;
  std::atomic<double> snapshot_recv_s_{-1};   // arrival time (loop clock) of the newest accepted snapshot
  // device pose
  bus::LatestValue<lcmt_device_state> pose_box_;
  std::atomic<double> pose_recv_s_{-1};
  std::unique_ptr<bus::ShmReader> shm_pose_;
  std::unique_ptr<bus::ShmWriter> shm_feedback_;
  std::unique_ptr<bus::ShmReader> shm_feedback_check_;   // 1 Hz look at our own segment: another writer?
  // LCM: our device's FEEDBACK channel is delivered only kWriterCheckWindow_s after each stats tick (our
  // own messages would otherwise wake the handler thread at the loop rate).
  bus::RawSubscription* feedback_check_ = nullptr;
  double feedback_check_until_s_ = -1;
  static constexpr double kWriterCheckWindow_s = 0.02;
  bus::OriginLock device_lock_;        // pose thread (handler for LCM, loop for shm): one device instance
  int64_t newest_pose_seq_ = -1;
  std::atomic<int64_t> refused_device_{0}, refused_writer_{0}, followed_device_{0}, old_device_{0};
  std::atomic<bool> bad_pose_value_{false};
  bool warned_device_ = false, warned_bad_pose_ = false, warned_writer_ = false, warned_clamp_ = false,
       warned_old_device_ = false;
  int64_t reported_device_restarts_ = 0;  lcmt_device_state pose_{}, shm_pose_msg_{};
  lcmt_feedback fb_check_{};
  int64_t stats_seq_ = 0;
  double pose_time_s_ = -1;
  // scene state (for the nearest-body pick on the grab edge only)
  bus::LatestValue<lcmt_scene_state> scene_box_;
  // loop state
  CouplingWorkspace ws_;
  bool grabbing_ = false;
  int32_t grab_seq_ = 0;               // device's press counter at our grab
  int body_ = -1;
  Vec3 grab_point_ = Vec3::Zero();
  // The snapshot in hand at the grab edge: it belongs to an earlier grab (the server sends snapshots only
  // while it holds a grab), so it is not used for this one, even for the same body (its grab point is the
  // old one: a spring force up to the clamp at once instead of zero).
  int64_t grab_old_version_ = -1, grab_old_instance_ = 0;
  int64_t user_seq_ = 0, feedback_seq_ = 0;
  double next_user_force_s_ = 0;
  lcmt_feedback fb_{};
  lcmt_user_force uf_{};
  Vec6 f_u_ = Vec6::Zero();
  Vec6 f_feed_ = Vec6::Zero();
  bus::LatencyHistogram hist_;
  std::string ch_feedback_, ch_user_force_, ch_stats_;
  // settings message (replay_coupling reads it from the log), built once
  static constexpr double kSettingsEvery_s = 5.0;
  lcmt_coupler_settings settings_msg_{};
  std::string ch_settings_;
  // Last member: destroyed first, so no callback (they capture this) runs into freed members.
  bus::SubscriptionGuard subs_;
};

// The settings message of a coupler's options, and back (replay_coupling). to_settings stamps it.
void to_settings(const CouplerOptions& o, int64_t instance_id, lcmt_coupler_settings& m);
void from_settings(const lcmt_coupler_settings& m, CouplerOptions& o);

// The coupling computation of one loop iteration as a pure function of the logged inputs, shared by
// the coupler and tools/replay_coupling: device point (device metres) -> feedback force (N, clamped,
// before clamp and watchdog).
struct CouplingInputs {
  Vec3 position_m = Vec3::Zero();
  Vec3 velocity_mps = Vec3::Zero();
};
// f_u is clamped to user_force_limit(o) before coupling_forces, so the feedback answers the force the
// server will apply (*clamped tells whether it was).
CouplingStatus coupler_feedback(const CouplerOptions& o, const CouplingSnapshot& snap, const CouplingInputs& in,
                                CouplingWorkspace& ws, Vec6& f_u, Vec6& f_feed, Vec3& force_n,
                                bool* clamped = nullptr) noexcept;
// Scene-side limit on the user force: what the device clamp allows through the force mapping,
// max_force_n / force_scale, times kUserForceMargin = 2 so that it stays out of the way while the
// device clamp alone limits what is felt (f_feed differs from f_u by the body's dynamic response)
// and bounds a device glitch to a known, finite force.
constexpr double kUserForceMargin = 2.0;
double user_force_limit(const CouplerOptions& o) noexcept;
// Throws std::invalid_argument naming the option when a value is out of range.
void check_coupler_options(const CouplerOptions& o);
WorkspaceMapping coupler_mapping(const CouplerOptions& o);

}  // namespace haptree
