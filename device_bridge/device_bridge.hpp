#pragma once
// DeviceBridge: the paper's haptics loop as a class, one per device. Runs a device from
// the registry (scripted, virtual_hand, replay, or a plugged-in SDK) at its rate, publishes
// DEVICE_STATE and applies the latest FEEDBACK. Link to the coupler: LCM, or same-host shared memory
// (latest value) mirrored onto LCM at --mirror-rate-hz for lcm-logger.
#include <array>
#include <cstdio>
#include <atomic>
#include <cstdint>
#include <map>
#include <memory>
#include <string>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/latency_histogram.hpp"
#include "haptree/bus/latest_value.hpp"
#include "haptree/bus/origin.hpp"
#include "haptree/safety.hpp"
#include "haptree/bus/shm_channel.hpp"
#include "haptree/device/buttons.hpp"
#include "haptree/device/device.hpp"
#include "haptree/device/registry.hpp"
#include "haptree/lcmt_device_state.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "haptree/lcmt_process_stats.hpp"

namespace haptree {

struct DeviceBridgeOptions {
  int device = 0;
  std::string kind = "scripted";                 // registry name
  std::map<std::string, std::string> options;    // device options (key=value), see haptree/device/registry.cpp
  double rate_hz = 1000;                         // device loop rate
  double max_force_n = 3.0;
  double feedback_timeout_s = 0.01;              // no feedback for this long -> ramp to zero (feedback_ramp_down_s);
                                                 // also the silence after which another coupler instance may take over
  double feedback_ramp_down_s = 0.005;           // ramps of the device's own watchdog (as the coupler's): after the
  double feedback_ramp_up_s = 0.1;               // timeout down to zero, and back once FEEDBACK arrives again
  double max_force_rate_n_per_s = 0;             // bound on every change of the rendered force; 0: the clamp
                                                 // within feedback_ramp_down_s (600 N/s for 3 N)
  bool shm = false;
  double mirror_rate_hz = 100;
  bool busy_poll = false;                        // poll shm feedback until this tick's answer (latency)
  std::string channel_suffix;
};

// Exit codes of run(): stopped on request (SIGINT/SIGTERM), or the device failed (a vendor error, a failed
// read or write, a lost device): then the last thing written was zero force and torque, force output
// was turned off and the device closed.
constexpr int kExitStopped = 0;
constexpr int kExitDeviceFault = 3;

// The DeviceConfig a bridge with these options builds its device from (bus: for devices fed from it).
device::DeviceConfig device_config(const DeviceBridgeOptions& o, bus::Bus* bus);

// device_bridge --probe: opens the device, reads it for `duration_s`, prints to `out` its model, serial,
// limits, position and buttons (one "key: value" per line), closes it. 0, or 1 after printing why to `err`.
int probe_device(const DeviceBridgeOptions& o, double duration_s, std::FILE* out, std::FILE* err);

// Fatal signals (SIGSEGV, SIGBUS, SIGFPE, SIGILL, SIGABRT) and std::terminate: zero force and force
// output off on every open vendor device (device::emergency_stop_devices), then the default action.
void install_device_crash_handlers();

// The renderer a bridge with these options uses: its feedback watchdog, clamp and rate limit (default: the
// clamp within feedback_ramp_down_s, i.e. 0.6 N per 1 ms tick for 3 N).
FeedbackRenderer feedback_renderer(const DeviceBridgeOptions& o);

class DeviceBridge {
 public:
  DeviceBridge(bus::Bus& bus, const DeviceBridgeOptions& options);
  ~DeviceBridge();
  int run(const std::atomic<bool>& stop);
  device::Device& device() { return *device_; }
  int64_t readings() const { return readings_.load(); }
  int64_t feedbacks() const { return feedbacks_.load(); }
  double last_force_n() const { return last_force_n_.load(); }
  double max_force_seen_n() const { return max_force_n_.load(); }
  // Why run() stopped with kExitDeviceFault ("" otherwise).
  const std::string& fault() const { return fault_; }
  // The force limit in use: --max-force-n, lowered to the device's own maximum if it reports a lower one.
  double max_force_n() const { return opt_.max_force_n; }
  // What the device reported at open: model, limits (NaN where it reports none), buttons, axes.
  const device::DeviceDescription& description() const { return desc_; }
  // This bridge's health numbers and its device's reported limits (device/reported_limits.hpp), which
  // run() publishes on HAPTREE_STATS_DEVICE_BRIDGE_<id> as it starts and then once a second: a coupler
  // started with --device-limits-wait-s checks its gains against those limits.
  const lcmt_process_stats& stats_message();
  // Largest change of the rendered force between two device ticks (N): what the hand feels as a jerk.
  double max_force_step_n() const { return max_force_step_n_.load(); }
  // pose-to-force latency: DEVICE_STATE seq s published -> first FEEDBACK echoing s received (µs)
  double latency_percentile_us(double q) const;
  uint64_t latency_samples() const;
  int64_t instance_id() const { return instance_id_; }
  // FEEDBACK messages refused because another coupler instance (the one followed) is live.
  int64_t feedback_refused() const { return refused_.load(); }
  int64_t coupler_takeovers() const { return takeovers_.load(); }
  // run()'s thread computes with flush-to-zero + denormals-are-zero.
  bool ftz_daz() const { return ftz_daz_.load(); }

 private:
  void on_feedback(const lcmt_feedback& m, double now_s);
  bool from_followed_coupler(const lcmt_feedback& m, double now_s);   // one writer per FEEDBACK channel
  void poll_shm_feedback();
  void report_problems();
  void publish_stats();   // from run()'s thread only: one thread publishes (LCM's tcpq sends are not atomic)
  int loop(const std::atomic<bool>& stop);
  // Zero force and torque (ramped at the rate limit when `ramp`), force output off, device closed.
  void shut_device(bool ramp) noexcept;
  int64_t instance_id_;
  std::atomic<bool> ftz_daz_{false};
  bus::OriginLock coupler_lock_;   // used by the thread that receives feedback (handler for LCM, loop for shm)
  std::atomic<int64_t> refused_{0}, takeovers_{0}, refused_id_{0}, followed_id_{0}, too_old_{0};
  int64_t reported_takeovers_ = 0;
  bool warned_refused_ = false, warned_too_old_ = false;
  bus::Bus& bus_;
  DeviceBridgeOptions opt_;
  std::unique_ptr<device::Device> device_;
  device::DeviceDescription desc_;
  int64_t stats_seq_ = 0;
  lcmt_process_stats stats_msg_{};   // built at the first publish (after open), then updated in place
  std::unique_ptr<bus::ShmWriter> shm_state_;
  std::unique_ptr<bus::ShmReader> shm_feedback_;
  bus::LatestValue<lcmt_feedback> fb_box_;
  lcmt_feedback fb_{}, fb_shm_{}, fb_scratch_{};
  std::string ch_state_, ch_feedback_, ch_stats_;
  // Device states written to shared memory, by seq: the mirror publishes the one a FEEDBACK answers.
  static constexpr int kStateRing = 256;
  std::array<lcmt_device_state, kStateRing> shm_states_{};
  int64_t mirrored_feedback_seq_ = 0;
  static constexpr int kRing = 8192;
  std::array<std::atomic<double>, kRing> sent_s_{};
  std::atomic<int64_t> last_echo_{0};
  bus::LatencyHistogram hist_;           // written by whoever receives feedback (one thread at a time)
  std::atomic<int64_t> readings_{0}, feedbacks_{0};
  std::atomic<double> last_force_n_{0}, max_force_n_{0}, max_force_step_n_{0}, feedback_time_s_{-1};
  FeedbackRenderer renderer_;      // loop thread: feedback -> the force written to the device
  FeedbackRenderer torque_renderer_;   // the same for the torque (devices that render one)
  bool render_torque_ = false;
  device::ButtonStage buttons_;    // grab press count and clutch, for every kind
  bool force_enabled_ = false;     // device force output on (after the first valid FEEDBACK)
  bool shut_ = false;              // shut_device() ran: the device is closed
  std::atomic<bool> valid_feedback_{false};
  std::string fault_;
  // Last member: destroyed first, so no callback (they capture this) runs into freed members.
  bus::SubscriptionGuard subs_;
};

}  // namespace haptree
