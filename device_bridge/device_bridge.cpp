#include "device_bridge/device_bridge.hpp"

#include <spdlog/spdlog.h>

#include <signal.h>

#include <chrono>
#include <cmath>
#include <cstring>
#include <exception>
#include <limits>
#include <stdexcept>
#include <thread>

#include "haptree/fp_env.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/pacing.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/device/convert.hpp"
#include "haptree/device/reported_limits.hpp"
#include "haptree/device/registry.hpp"
#include "haptree/device/vendor_library.hpp"
#include "haptree/safety.hpp"

namespace haptree {

using Clock = std::chrono::steady_clock;
static const Clock::time_point kEpoch = Clock::now();
static double now_s() { return std::chrono::duration<double>(Clock::now() - kEpoch).count(); }

FeedbackRenderer feedback_renderer(const DeviceBridgeOptions& o) {
  const double rate = o.max_force_rate_n_per_s > 0 ? o.max_force_rate_n_per_s : o.max_force_n / o.feedback_ramp_down_s;
  return FeedbackRenderer(WatchdogParams{o.feedback_timeout_s, o.feedback_ramp_down_s, o.feedback_ramp_up_s},
                          o.max_force_n, rate / o.rate_hz);
}

device::DeviceConfig device_config(const DeviceBridgeOptions& o, bus::Bus* bus) {
  device::DeviceConfig cfg;
  cfg.spec.name = o.kind + "_" + std::to_string(o.device);
  cfg.spec.max_force_n = o.max_force_n;
  cfg.spec.rate_hz = o.rate_hz;
  cfg.options = o.options;
  cfg.bus = bus;   // devices fed from the bus (browser) subscribe here
  cfg.device_id = o.device;
  cfg.channel_suffix = o.channel_suffix;
  return cfg;
}

namespace {

std::string limit(double v, const char* unit) {
  if (!std::isfinite(v)) return "not reported";
  char b[64];
  std::snprintf(b, sizeof b, "%.4g %s", v, unit);
  return b;
}

void crash_handler(int sig) {
  device::emergency_stop_devices();
  ::signal(sig, SIG_DFL);
  ::raise(sig);
}

}  // namespace

void install_device_crash_handlers() {
  for (int sig : {SIGSEGV, SIGBUS, SIGFPE, SIGILL, SIGABRT}) {
    struct sigaction sa {};
    sa.sa_handler = crash_handler;
    sigemptyset(&sa.sa_mask);
    sa.sa_flags = SA_RESETHAND | SA_NODEFER;
    ::sigaction(sig, &sa, nullptr);
  }
  std::set_terminate([] {
    device::emergency_stop_devices();
    std::abort();
  });
}

int probe_device(const DeviceBridgeOptions& o, double duration_s, std::FILE* out, std::FILE* err) {
  std::unique_ptr<device::Device> dev;
  try {
    dev = device::make_device(o.kind, device_config(o, nullptr));
  } catch (const std::exception& e) {
    std::fprintf(err, "device_bridge --probe: %s\n", e.what());
    return 1;
  }
  const device::Status s = dev->open();
  if (!s.ok()) {
    std::fprintf(err, "device_bridge --probe: %s\n", s.reason);
    return 1;
  }
  device::DeviceReading r;
  device::Status rs = device::Status::Error("no reading");
  const auto t0 = std::chrono::steady_clock::now();
  double t = 0;
  do {
    rs = dev->read(t, r);
    if (rs.ok()) dev->write(Vec3::Zero(), Vec3::Zero());   // keeps a vendor watchdog fed; force output is off
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
    t = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  } while (t < duration_s);
  const device::DeviceDescription d = dev->describe();
  std::fprintf(out, "kind: %s\n", o.kind.c_str());
  std::fprintf(out, "model: %s\n", d.model.empty() ? "(not reported)" : d.model.c_str());
  std::fprintf(out, "serial: %s\n", d.serial.empty() ? "(none reported)" : d.serial.c_str());
  std::fprintf(out, "max force: %s\n", limit(d.max_force_n, "N").c_str());
  std::fprintf(out, "max continuous force: %s\n", limit(d.max_continuous_force_n, "N").c_str());
  std::fprintf(out, "max torque: %s\n", limit(d.max_torque_nm, "N m").c_str());
  std::fprintf(out, "max stiffness: %s\n", limit(d.max_stiffness_n_per_m, "N/m").c_str());
  std::fprintf(out, "max damping: %s\n", limit(d.max_damping_n_s_per_m, "N s/m").c_str());
  std::fprintf(out, "workspace radius: %s\n", limit(d.workspace_radius_m, "m").c_str());
  std::fprintf(out, "orientation: %s, torque output: %s\n", d.orientation ? "yes" : "no", d.torque ? "yes" : "no");
  std::fprintf(out, "axes: %s\n", d.axes.empty() ? "(none)" : d.axes.c_str());
  int rc = 0;
  if (rs.ok()) {
    std::fprintf(out, "position: %.6f %.6f %.6f m\n", r.position_m.x(), r.position_m.y(), r.position_m.z());
    std::fprintf(out, "orientation (w x y z): %.4f %.4f %.4f %.4f\n", r.orientation.w(), r.orientation.x(),
                 r.orientation.y(), r.orientation.z());
    std::fprintf(out, "buttons: %d (grab %s, clutch %s)\n", r.buttons, (r.buttons & device::kButtonGrab) ? "down" : "up",
                 (r.buttons & device::kButtonClutch) ? "down" : "up");
  } else {
    std::fprintf(err, "device_bridge --probe: reading the device failed: %s\n", rs.reason);
    rc = 1;
  }
  dev->close();
  return rc;
}

DeviceBridge::DeviceBridge(bus::Bus& bus, const DeviceBridgeOptions& options)
    : instance_id_(bus::new_instance_id()), coupler_lock_(options.feedback_timeout_s), bus_(bus),
      opt_(options) {   // declaration order
  auto pos = [](double v) { return std::isfinite(v) && v > 0; };
  if (!pos(opt_.rate_hz)) throw std::invalid_argument("device_bridge: --rate-hz must be a positive rate");
  if (!pos(opt_.max_force_n)) throw std::invalid_argument("device_bridge: --max-force-n must be positive and finite");
  if (!pos(opt_.feedback_timeout_s)) throw std::invalid_argument("device_bridge: the feedback timeout must be positive");
  if (!pos(opt_.feedback_ramp_down_s) || !pos(opt_.feedback_ramp_up_s))
    throw std::invalid_argument("device_bridge: the feedback ramps must be positive");
  if (!(std::isfinite(opt_.max_force_rate_n_per_s) && opt_.max_force_rate_n_per_s >= 0))
    throw std::invalid_argument("device_bridge: --max-force-rate-n-per-s must be >= 0 (0: the clamp within 5 ms)");
  if (!(std::isfinite(opt_.mirror_rate_hz) && opt_.mirror_rate_hz >= 0))
    throw std::invalid_argument("device_bridge: --mirror-rate-hz must be >= 0");
  if (opt_.device < 0) throw std::invalid_argument("device_bridge: --device must be >= 0");
  device_ = device::make_device(opt_.kind, device_config(opt_, &bus_));
  if (!device_) throw std::runtime_error("device_bridge: unknown device kind '" + opt_.kind + "'");
  const device::Status s = device_->open();
  if (!s.ok()) throw std::runtime_error(std::string("device_bridge: open failed: ") + s.reason);
  // A device that reports its own maximum lowers the force limit to it (never raises it).
  desc_ = device_->describe();
  const device::DeviceDescription& d = desc_;
  if (std::isfinite(d.max_force_n) && d.max_force_n > 0 && d.max_force_n < opt_.max_force_n) {
    spdlog::info("device_bridge {}: {} reports a max force of {} N: forces clamped there (--max-force-n {} N)",
                 opt_.device, d.model.empty() ? opt_.kind : d.model, d.max_force_n, opt_.max_force_n);
    opt_.max_force_n = d.max_force_n;
  }
  renderer_ = feedback_renderer(opt_);
  render_torque_ = d.torque && std::isfinite(d.max_torque_nm) && d.max_torque_nm > 0;
  if (render_torque_) {
    DeviceBridgeOptions t = opt_;
    t.max_force_n = d.max_torque_nm;
    t.max_force_rate_n_per_s = opt_.max_force_rate_n_per_s > 0 ? opt_.max_force_rate_n_per_s * d.max_torque_nm / opt_.max_force_n : 0;
    torque_renderer_ = feedback_renderer(t);
  }
  for (auto& t : sent_s_) t.store(-1);
  ch_state_ = bus::channel::device_state(opt_.device, opt_.channel_suffix);
  ch_feedback_ = bus::channel::feedback(opt_.device, opt_.channel_suffix);
  ch_stats_ = bus::channel::stats(device::bridge_stats_name(opt_.device), opt_.channel_suffix);
  if (opt_.shm) {
    shm_state_ = std::make_unique<bus::ShmWriter>(ch_state_);
    // Never a FEEDBACK older than the feedback timeout, nor one of a dead or earlier coupler.
    shm_feedback_ = std::make_unique<bus::ShmReader>(ch_feedback_, opt_.feedback_timeout_s);
  } else {
    subs_(bus_.subscribe<lcmt_feedback>(ch_feedback_, [this](const lcmt_feedback& m, const std::string&) {
      const double t = now_s();
      if (!from_followed_coupler(m, t)) return;
      fb_box_.write(m);
      on_feedback(m, t);
    }));
  }
  spdlog::info("device_bridge {}: '{}' at {} Hz over {}", opt_.device, opt_.kind, opt_.rate_hz,
               opt_.shm ? "shared memory" : bus_.url());
}

DeviceBridge::~DeviceBridge() { shut_device(false); }

void DeviceBridge::shut_device(bool ramp) noexcept {
  if (!device_ || shut_) return;
  shut_ = true;
  const double period = 1.0 / opt_.rate_hz;
  // Down to zero at the rate limit (at most the ramp-down time), then zero, force output off, closed.
  for (int k = 0; ramp && k < 1000 && (renderer_.rendered().norm() > 0 || torque_renderer_.rendered().norm() > 0); ++k) {
    renderer_.ramp_down();
    torque_renderer_.ramp_down();
    if (!device_->write(renderer_.rendered(), torque_renderer_.rendered()).ok()) break;
    std::this_thread::sleep_for(std::chrono::duration<double>(period));
  }
  device_->write(Vec3::Zero(), Vec3::Zero());
  device_->enable_force(false);
  force_enabled_ = false;
  device_->close();
}

// One writer per device FEEDBACK channel: follow one coupler instance; another is taken only after the
// followed one was silent for feedback_timeout_s (by then the device renders zero anyway): a restart.
bool DeviceBridge::from_followed_coupler(const lcmt_feedback& m, double t) {
  const bus::Origin o = coupler_lock_.check(m.instance_id, t, bus::message_age_s(m.utime));
  if (!bus::accepted(o)) {
    refused_.fetch_add(1, std::memory_order_relaxed);
    if (o == bus::Origin::kTooOld)
      too_old_.fetch_add(1, std::memory_order_relaxed);
    else if (o != bus::Origin::kPrevious)
      refused_id_.store(m.instance_id, std::memory_order_relaxed);
    return false;
  }
  if (o == bus::Origin::kTakeover) takeovers_.fetch_add(1, std::memory_order_relaxed);
  followed_id_.store(m.instance_id, std::memory_order_relaxed);
  return true;
}

void DeviceBridge::poll_shm_feedback() {
  if (shm_feedback_->read_msg(fb_scratch_) != bus::ShmRead::kNew) return;
  const double t = now_s();
  if (!from_followed_coupler(fb_scratch_, t)) return;
  fb_shm_ = fb_scratch_;
  on_feedback(fb_shm_, t);
}

// Once-only warnings, from the loop's 1 Hz tick.
void DeviceBridge::report_problems() {
  if (!warned_refused_ && refused_id_.load() != 0) {
    warned_refused_ = true;
    spdlog::warn("device_bridge {}: refusing FEEDBACK from coupler instance {:016x}: this device follows coupler "
                 "instance {:016x}, which is live. Two couplers are driving device {}; stop one of them.",
                 opt_.device, static_cast<uint64_t>(refused_id_.load()), static_cast<uint64_t>(followed_id_.load()),
                 opt_.device);
  }
  if (!warned_too_old_ && too_old_.load() > 0) {
    warned_too_old_ = true;
    spdlog::warn("device_bridge {}: refused {} FEEDBACK message(s) of a new coupler instance stamped more than {} s "
                 "away from this host's clock: a replayed recording, or hosts whose clocks differ (synchronise them)",
                 opt_.device, too_old_.load(), bus::OriginLock::kDefaultMaxStartAgeS);
  }
  if (takeovers_.load() != reported_takeovers_) {
    reported_takeovers_ = takeovers_.load();
    spdlog::info("device_bridge {}: now following coupler instance {:016x} (the previous one went silent)",
                 opt_.device, static_cast<uint64_t>(followed_id_.load()));
  }
}

void DeviceBridge::on_feedback(const lcmt_feedback& m, double t) {
  feedbacks_.fetch_add(1, std::memory_order_relaxed);
  if (std::isfinite(m.force_n[0]) && std::isfinite(m.force_n[1]) && std::isfinite(m.force_n[2]))
    valid_feedback_.store(true, std::memory_order_release);
  feedback_time_s_.store(t, std::memory_order_release);
  if (m.echo_device_seq > last_echo_.load(std::memory_order_relaxed)) {
    last_echo_.store(m.echo_device_seq, std::memory_order_relaxed);
    const double sent = sent_s_[static_cast<size_t>(m.echo_device_seq % kRing)].load(std::memory_order_acquire);
    if (sent >= 0) hist_.add(1e6 * (t - sent));
  }
}

double DeviceBridge::latency_percentile_us(double q) const { return hist_.percentile(q); }

void DeviceBridge::publish_stats() { bus_.publish(ch_stats_, stats_message()); }

const lcmt_process_stats& DeviceBridge::stats_message() {
  lcmt_process_stats& m = stats_msg_;
  if (m.process_name.empty()) {   // names and the opened device's limits once: the loop then only counts
    m.process_name = device::bridge_stats_name(opt_.device);
    m.process_id = opt_.device;
    m.snapshot_age_ms = -1;
    m.extra_names = {"max_force_n"};
    m.extra_values = {opt_.max_force_n};
    device::put_reported_limits(desc_, m);
  }
  bus::stamp(m, instance_id_);
  m.seq = ++stats_seq_;
  m.messages_in = feedbacks_.load();
  m.messages_out = readings_.load();
  m.rejected_messages = refused_.load();
  return m;
}
uint64_t DeviceBridge::latency_samples() const { return hist_.count(); }

int DeviceBridge::run(const std::atomic<bool>& stop) {
  try {
    const int rc = loop(stop);
    shut_device(rc == kExitStopped);
    return rc;
  } catch (...) {
    shut_device(false);   // an exception in the bridge's own path: zero, off, closed, then the error
    throw;
  }
}

int DeviceBridge::loop(const std::atomic<bool>& stop) {
  // FTZ/DAZ in the device loop, as in the coupler's: no subnormal operand costs an assist.
  const ScopedFlushDenormals ftz;
  ftz_daz_.store(ScopedFlushDenormals::active(), std::memory_order_relaxed);
  const double period = 1.0 / opt_.rate_hz;
  const double t0 = now_s();
  double next = t0, next_mirror = t0, next_report = t0 + 1.0;
  device::DeviceReading r;
  lcmt_device_state msg{};
  bool mirror_due = false;
  publish_stats();   // at once: a coupler may be waiting for the device's limits before it starts
  while (!stop.load(std::memory_order_relaxed)) {
    const double t = now_s();
    r.grab_body = 0;   // a device that names no body or counts no presses leaves these at 0
    r.grab_seq = 0;
    const device::Status rs = device_->read(t - t0, r);
    if (rs.code == device::StatusCode::kError) {
      fault_ = std::string("device read failed: ") + rs.reason;
      return kExitDeviceFault;
    }
    if (rs.ok()) {
      buttons_.apply(r);   // grab press count and clutch, the same for every kind
      device::to_lcmt(r, opt_.device, bus::now_utime(), msg);
      msg.instance_id = instance_id_;
      sent_s_[static_cast<size_t>(r.seq % kRing)].store(now_s(), std::memory_order_release);
      if (shm_state_) {
        shm_state_->write_msg(msg);
        shm_states_[static_cast<size_t>(msg.seq % kStateRing)] = msg;
        mirror_due = opt_.mirror_rate_hz > 0 && t >= next_mirror;   // published after the answer (below)
      } else {
        bus_.publish(ch_state_, msg);
      }
      readings_.fetch_add(1, std::memory_order_relaxed);
    }
    // Apply the latest feedback: clamped, NaN -> 0, times the device's watchdog gain (older than the timeout:
    // ramp to zero; fresh again: ramp back in), and no change faster than the rate limit. It used to cut to
    // zero at the timeout and jump back to the full force with the next FEEDBACK: a step at the hand.
    if (shm_feedback_) {
      poll_shm_feedback();
      fb_ = fb_shm_;
    } else if (fb_box_.update()) {
      fb_ = fb_box_.front();
    }
    // Force output comes on with the first valid FEEDBACK: nothing is rendered before the coupler speaks.
    if (!force_enabled_ && valid_feedback_.load(std::memory_order_acquire)) {
      const device::Status es = device_->enable_force(true);
      if (!es.ok()) {
        fault_ = std::string("enabling force output failed: ") + es.reason;
        return kExitDeviceFault;
      }
      force_enabled_ = true;
    }
    const double t_fb = feedback_time_s_.load(std::memory_order_acquire);
    const double now = now_s();
    const double age = t_fb < 0 ? std::numeric_limits<double>::infinity() : now - t_fb;
    // While the clutch is held the proxy stands still and the hand moves freely: no force (ramped out
    // and back in at the rate limit).
    const bool render = force_enabled_ && !buttons_.clutched();
    const Vec3 f = renderer_.render(now, age, render ? Vec3(fb_.force_n[0], fb_.force_n[1], fb_.force_n[2]) : Vec3::Zero());
    const Vec3 tau = render_torque_ ? torque_renderer_.render(now, age, render ? Vec3(fb_.torque_nm[0], fb_.torque_nm[1],
                                                                                     fb_.torque_nm[2])
                                                                              : Vec3::Zero())
                                    : Vec3::Zero();
    const device::Status ws = device_->write(f, tau);
    if (ws.code == device::StatusCode::kError) {
      fault_ = std::string("device write failed: ") + ws.reason;
      return kExitDeviceFault;
    }
    max_force_step_n_.store(renderer_.max_step_seen(), std::memory_order_relaxed);
    last_force_n_.store(f.norm(), std::memory_order_relaxed);
    if (f.norm() > max_force_n_.load(std::memory_order_relaxed)) max_force_n_.store(f.norm());
    next += period;
    if (now_s() > next + 0.01) next = now_s();
    if (t >= next_report) {
      report_problems();
      publish_stats();
      next_report = t + 1.0;
    }
    if (opt_.busy_poll && shm_feedback_) {
      // Until the answer to this tick's pose arrives: no spinning for the rest of the period, which on a
      // 2-core host would starve the coupler (and under SCHED_FIFO meet the kernel's RT throttling).
      while (now_s() < next && !stop.load(std::memory_order_relaxed) &&
             last_echo_.load(std::memory_order_relaxed) < r.seq)
        poll_shm_feedback();
    }
    if (mirror_due) {
      // Mirror pairs the coupler actually used: the newest FEEDBACK with the device state it answers,
      // so every mirrored FEEDBACK can be replayed (replay_coupling) whatever the mirror rate. After the
      // answer to this tick's pose: two udpm sends between a pose and its answer were the shm link's p99.
      const lcmt_device_state& used = shm_states_[static_cast<size_t>(fb_shm_.echo_device_seq % kStateRing)];
      if (fb_shm_.seq > mirrored_feedback_seq_ && fb_shm_.echo_device_seq > 0 && used.seq == fb_shm_.echo_device_seq) {
        bus_.publish(ch_state_, used);
        bus_.publish(ch_feedback_, fb_shm_);
        mirrored_feedback_seq_ = fb_shm_.seq;
      } else {
        bus_.publish(ch_state_, msg);
      }
      next_mirror = t + 1.0 / opt_.mirror_rate_hz;
      mirror_due = false;
    }
    bus::sleep_until_or_stop(kEpoch + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(next)),
                             stop);
  }
  return kExitStopped;
}

}  // namespace haptree
