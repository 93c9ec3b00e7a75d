#include "coupler/coupler.hpp"

#include <spdlog/spdlog.h>

#include <chrono>
#include <limits>
#include <thread>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/device/convert.hpp"
#include "haptree/device/device.hpp"
#include "haptree/lcmt_process_stats.hpp"

namespace haptree {

using Clock = std::chrono::steady_clock;

WorkspaceMapping coupler_mapping(const CouplerOptions& o) {
  WorkspaceMapping m;
  m.position_scale = o.position_scale;
  m.force_scale = o.force_scale;
  m.offset = o.offset;
  return m;
}

CouplingStatus coupler_feedback(const CouplerOptions& o, const CouplingSnapshot& snap, const CouplingInputs& in,
                                CouplingWorkspace& ws, Vec6& f_u, Vec6& f_feed, Vec3& force_n) noexcept {
  const WorkspaceMapping map = coupler_mapping(o);
  const Vec3 x_h = map.device_to_scene_point(in.position_m);
  const Vec3 xd_h = map.device_to_scene_velocity(in.velocity_mps);
  VirtualCoupling3 vc;
  vc.k_s = o.stiffness;
  vc.b_s = o.damping;
  f_u = vc.user_force(x_h, xd_h, snap.grabs[0].point, snap.grabs[0].velocity);
  const CouplingStatus st = coupling_forces(snap, &f_u, ws, &f_feed);
  force_n = map.scene_to_device_force(f_feed.tail<3>());
  return st;
}

static WatchdogParams watchdog_params(const CouplerOptions& o) {
  WatchdogParams w;
  w.stale_after_s = o.stale_after_s;
  return w;
}

static double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }
static const Clock::time_point kEpoch = Clock::now();

Coupler::Coupler(bus::Bus& bus, const CouplerOptions& options)
    : bus_(bus),
      opt_(options),
      map_(coupler_mapping(options)),
      safety_(ForceLimits{options.max_force_n, 0.0}, watchdog_params(options)),
      ws_(options.max_nodes, options.max_slots) {
  vc_.k_s = opt_.stiffness;
  vc_.b_s = opt_.damping;
  locked_fingerprint_ = opt_.model_fingerprint;
  ch_feedback_ = bus::channel::feedback(opt_.device, opt_.channel_suffix);
  ch_user_force_ = bus::channel::user_force(opt_.user, opt_.channel_suffix);
  ch_stats_ = bus::channel::stats("coupler_" + std::to_string(opt_.user), opt_.channel_suffix);
  bus_.subscribe_raw(bus::channel::coeffs(opt_.user, opt_.channel_suffix),
                     [this](const void* d, uint32_t n, const std::string&) { on_snapshot(d, n); });
  const std::string ch_pose = bus::channel::device_state(opt_.device, opt_.channel_suffix);
  if (opt_.shm) {
    shm_pose_ = std::make_unique<bus::ShmReader>(ch_pose);
    shm_feedback_ = std::make_unique<bus::ShmWriter>(ch_feedback_);
  } else {
    bus_.subscribe<lcmt_device_state>(ch_pose, [this](const lcmt_device_state& m, const std::string&) {
      pose_box_.write(m);
      pose_recv_s_.store(since(kEpoch), std::memory_order_release);
    });
  }
  bus_.subscribe_latest<lcmt_scene_state>(bus::channel::scene_state(opt_.channel_suffix), scene_box_);
  spdlog::info(
      "coupler {}: device {}, k_s {} b_s {}, mapping: scene = {} x device_m + [{} {} {}], force_n = {} x scene "
      "force, clamp {} N, {} Hz, link {}",
      opt_.user, opt_.device, opt_.stiffness, opt_.damping, opt_.position_scale, opt_.offset.x(), opt_.offset.y(),
      opt_.offset.z(), opt_.force_scale, opt_.max_force_n, opt_.rate_hz, opt_.shm ? "shm" : bus_.url());
}

Coupler::~Coupler() = default;

int64_t Coupler::rejected_messages() const {
  return c_.foreign_rejected.load() + c_.stale_rejected.load() + c_.bad_rejected.load() + bus_.rejected_total() +
         (shm_pose_ ? shm_pose_->rejected() : 0);
}

// Bus handler thread: decode, check, convert into the back slot, publish (allocation allowed here).
void Coupler::on_snapshot(const void* data, uint32_t size) {
  if (bus::decode_checked(data, size, snap_msg_) != bus::DecodeResult::kOk) {
    c_.bad_rejected.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  const uint64_t fp = bus::fingerprint_from_wire(snap_msg_.model_fingerprint);
  uint64_t locked = locked_fingerprint_.load();
  if (locked == 0) {
    locked_fingerprint_ = fp;
    locked = fp;
    spdlog::info("coupler {}: locked onto model fingerprint {:016x}", opt_.user, fp);
  }
  if (fp != locked) {
    c_.foreign_rejected.fetch_add(1, std::memory_order_relaxed);
    if (!warned_foreign_) spdlog::warn("coupler {}: ignoring snapshots of model {:016x} (mine: {:016x})", opt_.user, fp, locked);
    warned_foreign_ = true;
    return;
  }
  // A lower version after the stream went silent (older than the watchdog's stale time) is a restarted
  // server (its step counter starts again): accept it. Within a live stream, older versions are ignored.
  const double last_recv = snapshot_recv_s_.load(std::memory_order_acquire);
  const bool restarted = last_recv >= 0 && since(kEpoch) - last_recv > opt_.stale_after_s;
  if (restarted && snap_msg_.version <= newest_version_) {
    spdlog::info("coupler {}: snapshot stream resumed at version {} (was {}): new server", opt_.user,
                 snap_msg_.version, newest_version_);
    newest_version_ = -1;
    c_.restarts.fetch_add(1, std::memory_order_relaxed);
  }
  if (snap_msg_.version <= newest_version_) {
    c_.stale_rejected.fetch_add(1, std::memory_order_relaxed);
    if (!warned_stale_)
      spdlog::warn("coupler {}: ignoring snapshot version {} (have {}); a restarted server is accepted "
                   "once its versions pass the old ones",
                   opt_.user, snap_msg_.version, newest_version_);
    warned_stale_ = true;
    return;
  }
  CouplingSnapshot& back = snap_box_.back();
  bus::from_lcmt(snap_msg_, back);
  if (back.grabs.size() != 1 || validate_coupling_snapshot(back) != CouplingStatus::kOk || !ws_.fits(back)) {
    c_.bad_rejected.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  newest_version_ = snap_msg_.version;
  snap_box_.publish();
  snapshot_recv_s_.store(since(kEpoch), std::memory_order_release);
  c_.last_snapshot_utime.store(bus::now_utime(), std::memory_order_relaxed);
  c_.snapshots_accepted.fetch_add(1, std::memory_order_relaxed);
}

bool Coupler::iterate(double now) {
  const auto t_start = Clock::now();
  snap_box_.update();
  const CouplingSnapshot& snap = snap_box_.front();
  // device pose
  if (shm_pose_) {
    if (shm_pose_->read_msg(pose_) == bus::ShmRead::kNew) pose_time_s_ = now;
  } else if (pose_box_.update()) {
    pose_ = pose_box_.front();
    pose_time_s_ = pose_recv_s_.load(std::memory_order_acquire);
  }
  const Vec3 x_dev(pose_.position_m[0], pose_.position_m[1], pose_.position_m[2]);
  const Vec3 v_dev(pose_.linear_velocity_mps[0], pose_.linear_velocity_mps[1], pose_.linear_velocity_mps[2]);
  const bool button = pose_time_s_ >= 0 && (pose_.buttons & device::kButtonGrab) != 0;
  bool send_user_force = now >= next_user_force_s_;
  // grab logic: on the button's down edge pick a body; the grab point is the mapped device point itself
  // (a material point of that body from now on), so the spring starts at zero force.
  // A press counter that moved while the button is held is a new grab whose release never reached us
  // (latest-value mailboxes coalesce a short release): re-grab.
  const bool regrab = button && grabbing_ && pose_.grab_seq != grab_seq_;
  if (button && (!grabbing_ || regrab)) {
    const Vec3 x_h = map_.device_to_scene_point(x_dev);
    // A pointing device (the browser) names the body it picked on screen; otherwise --grab-body, or
    // the body nearest the device point.
    int body = pose_.grab_body >= 1 ? pose_.grab_body : opt_.grab_body;
    if (body < 1) {
      scene_box_.update();
      const lcmt_scene_state& s = scene_box_.front();
      double best = std::numeric_limits<double>::infinity();
      for (int i = 0; i < s.nbodies && i < static_cast<int>(s.body_position.size()); ++i) {
        const int k = s.first_body + i;   // a large scene comes in chunks: this one's bodies only
        if (k < 1) continue;
        const Vec3 r(s.body_position[i][0], s.body_position[i][1], s.body_position[i][2]);
        const double d2 = (r - x_h).squaredNorm();
        if (d2 < best) best = d2, body = k;
      }
    }
    if (body >= 1) {
      grabbing_ = true;
      grab_seq_ = pose_.grab_seq;
      body_ = body;
      grab_point_ = x_h;
      send_user_force = true;
    }
  } else if (!button && grabbing_) {
    grabbing_ = false;
    send_user_force = true;
  }
  Vec3 force_n = Vec3::Zero();
  f_u_.setZero();
  f_feed_.setZero();
  int64_t version = -1;
  double age = pose_time_s_ >= 0 ? now - pose_time_s_ : 1e9;
  if (grabbing_) {
    const double snap_t = snapshot_recv_s_.load(std::memory_order_acquire);
    age = std::max(age, snap_t >= 0 ? now - snap_t : 1e9);
    if (snap.version >= 0 && snap.grabs.size() == 1 && snap.grabs[0].body == body_) {
      CouplingInputs in{x_dev, v_dev};
      if (coupler_feedback(opt_, snap, in, ws_, f_u_, f_feed_, force_n) != CouplingStatus::kOk) force_n.setZero();
      version = snap.version;
    }
  }
  const GuardedForce g = safety_.apply(now, age, force_n, Vec3::Zero());
  device::FeedbackCommand cmd;
  cmd.echo_device_seq = pose_.seq;
  cmd.snapshot_version = version;
  cmd.force_n = g.force;
  cmd.flags = g.flags;
  device::to_lcmt(cmd, opt_.device, ++feedback_seq_, bus::now_utime(), fb_);
  if (shm_feedback_) {
    shm_feedback_->write_msg(fb_);
  } else {
    bus_.publish(ch_feedback_, fb_);
  }
  if (send_user_force) {
    bus::stamp(uf_);
    uf_.seq = ++user_seq_;
    uf_.user_id = opt_.user;
    uf_.grab_body = grabbing_ ? body_ : 0;
    for (int i = 0; i < 3; ++i) uf_.grab_point[i] = grab_point_[i];
    const double gain = safety_.watchdog().gain();
    for (int i = 0; i < 6; ++i) uf_.force[i] = grabbing_ && f_u_.allFinite() ? gain * f_u_[i] : 0.0;
    uf_.snapshot_version = version;
    uf_.active = grabbing_;
    bus_.publish(ch_user_force_, uf_);
    next_user_force_s_ = now + 1.0 / opt_.user_force_rate_hz;
  }
  c_.force_n.store(g.force.norm(), std::memory_order_relaxed);
  c_.version_in_use.store(snap.version, std::memory_order_relaxed);
  hist_.add(std::chrono::duration<double, std::micro>(Clock::now() - t_start).count());
  return true;
}

void Coupler::publish_stats(double period_s, int64_t iterations) {
  const double now = since(kEpoch);
  const double snap_t = snapshot_recv_s_.load();
  const double age_ms = snap_t >= 0 ? 1e3 * (now - snap_t) : -1;
  c_.rate_hz = static_cast<double>(iterations) / period_s;
  c_.p50_us = hist_.percentile(0.5);
  c_.p99_us = hist_.percentile(0.99);
  c_.snapshot_age_ms = age_ms;
  lcmt_process_stats s;
  bus::stamp(s);
  static std::atomic<int64_t> seq{0};
  s.seq = ++seq;
  s.process_name = "coupler";
  s.process_id = opt_.user;
  s.loop_rate_hz = c_.rate_hz;
  s.latency_p50_us = c_.p50_us;
  s.latency_p99_us = c_.p99_us;
  s.snapshot_age_ms = age_ms;
  s.messages_in = c_.snapshots_accepted.load();
  s.messages_out = feedback_seq_;
  s.rejected_messages = rejected_messages();
  s.stale_events = c_.stale_rejected.load();
  s.watchdog_events = safety_.watchdog().trips();
  s.clamp_events = safety_.clamp_events();
  s.nonfinite_events = safety_.nonfinite_events();
  // The mapping too, so a viewer can draw the device point in the scene and a browser device can
  // invert it (scene = position_scale x device_m + offset).
  s.extra_names = {"force_n", "grab_body", "position_scale", "offset_x", "offset_y", "offset_z", "force_scale",
                   "max_force_n"};
  s.extra_values = {c_.force_n.load(), static_cast<double>(grabbing_ ? body_ : 0), opt_.position_scale,
                    opt_.offset.x(), opt_.offset.y(), opt_.offset.z(), opt_.force_scale, opt_.max_force_n};
  s.n_extra = static_cast<int32_t>(s.extra_names.size());
  bus_.publish(ch_stats_, s);
  hist_.reset();
}

int Coupler::run(const std::atomic<bool>& stop) {
  const double period = 1.0 / opt_.rate_hz;
  double next = since(kEpoch);
  double next_stats = next + 1.0, stats_start = next;
  int64_t it_at_stats = 0, it = 0;
  while (!stop.load(std::memory_order_relaxed)) {
    const double now = since(kEpoch);
    iterate(now);
    ++it;
    c_.iterations.store(it, std::memory_order_relaxed);
    if (now >= next_stats) {   // once a second, outside the computation
      publish_stats(now - stats_start, it - it_at_stats);
      it_at_stats = it;
      stats_start = now;
      next_stats += 1.0;
    }
    next += period;
    if (since(kEpoch) > next + 0.01) next = since(kEpoch);   // overrun: do not try to catch up
    if (opt_.busy_wait) {
      while (since(kEpoch) < next) {
      }
    } else {
      std::this_thread::sleep_until(kEpoch + std::chrono::duration_cast<Clock::duration>(
                                                 std::chrono::duration<double>(next)));
    }
  }
  return 0;
}

}  // namespace haptree
