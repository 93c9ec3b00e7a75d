#include "coupler/coupler.hpp"

#include <spdlog/spdlog.h>

#include <chrono>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <random>
#include <thread>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/delivery.hpp"
#include "haptree/bus/pacing.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/device/convert.hpp"
#include "haptree/device/device.hpp"
#include "haptree/fp_env.hpp"
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

double user_force_limit(const CouplerOptions& o) noexcept { return kUserForceMargin * o.max_force_n / o.force_scale; }

void check_coupler_options(const CouplerOptions& o) {
  auto fail = [](const std::string& what) { throw std::invalid_argument("coupler: " + what); };
  auto pos = [](double v) { return std::isfinite(v) && v > 0; };
  if (!pos(o.rate_hz)) fail("--coupler-rate-hz must be a positive rate, got " + std::to_string(o.rate_hz));
  if (!pos(o.stiffness)) fail("--stiffness must be positive and finite");
  if (!(std::isfinite(o.damping) && o.damping >= 0)) fail("--damping must be >= 0 and finite");
  if (!pos(o.position_scale)) fail("--position-scale must be positive and finite");
  if (!pos(o.force_scale)) fail("--force-scale must be positive and finite");
  if (!o.offset.allFinite()) fail("--offset must be finite");
  if (!pos(o.max_force_n)) fail("--max-force-n must be positive and finite");
  if (!pos(o.stale_after_s)) fail("--stale-after-s must be positive and finite");
  if (!pos(o.user_force_rate_hz)) fail("--user-force-rate-hz must be positive and finite");
  if (!pos(o.max_device_position_m)) fail("--max-device-position-m must be positive and finite");
  if (o.user < 0 || o.device < 0) fail("--user and --device must be >= 0");
}

CouplingStatus coupler_feedback(const CouplerOptions& o, const CouplingSnapshot& snap, const CouplingInputs& in,
                                CouplingWorkspace& ws, Vec6& f_u, Vec6& f_feed, Vec3& force_n, bool* clamped) noexcept {
  const WorkspaceMapping map = coupler_mapping(o);
  const Vec3 x_h = map.device_to_scene_point(in.position_m);
  const Vec3 xd_h = map.device_to_scene_velocity(in.velocity_mps);
  VirtualCoupling3 vc;
  vc.k_s = o.stiffness;
  vc.b_s = o.damping;
  f_u = vc.user_force(x_h, xd_h, snap.grabs[0].point, snap.grabs[0].velocity);
  // Scene-side clamp (moment part is zero: a point force at the grab point).
  bool c = false;
  f_u.tail<3>() = clamp_norm(f_u.tail<3>(), user_force_limit(o), &c);
  if (clamped) *clamped = c;
  const CouplingStatus st = coupling_forces(snap, &f_u, ws, &f_feed);
  force_n = map.scene_to_device_force(f_feed.tail<3>());
  return st;
}

void to_settings(const CouplerOptions& o, int64_t instance_id, lcmt_coupler_settings& m) {
  bus::stamp(m, instance_id);
  m.instance_id = instance_id;
  m.user_id = o.user;
  m.device_id = o.device;
  m.stiffness = o.stiffness;
  m.damping = o.damping;
  m.position_scale = o.position_scale;
  m.force_scale = o.force_scale;
  for (int i = 0; i < 3; ++i) m.offset[i] = o.offset[i];
  m.grab_body = o.grab_body;
  m.max_force_n = o.max_force_n;
  m.stale_after_s = o.stale_after_s;
  m.rate_hz = o.rate_hz;
  m.user_force_rate_hz = o.user_force_rate_hz;
  m.model_fingerprint = bus::fingerprint_to_wire(o.model_fingerprint);
  m.shm = o.shm;
}

void from_settings(const lcmt_coupler_settings& m, CouplerOptions& o) {
  o.user = m.user_id;
  o.device = m.device_id;
  o.stiffness = m.stiffness;
  o.damping = m.damping;
  o.position_scale = m.position_scale;
  o.force_scale = m.force_scale;
  o.offset = Vec3(m.offset[0], m.offset[1], m.offset[2]);
  o.grab_body = m.grab_body;
  o.max_force_n = m.max_force_n;
  o.stale_after_s = m.stale_after_s;
  o.rate_hz = m.rate_hz;
  o.user_force_rate_hz = m.user_force_rate_hz;
  o.model_fingerprint = bus::fingerprint_from_wire(m.model_fingerprint);
  o.shm = m.shm;
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
      ws_((check_coupler_options(options), options.max_nodes), options.max_slots) {
  instance_id_ = bus::new_instance_id();
  server_lock_ = bus::OriginLock(opt_.stale_after_s);
  device_lock_ = bus::OriginLock(opt_.stale_after_s);
  vc_.k_s = opt_.stiffness;
  vc_.b_s = opt_.damping;
  locked_fingerprint_ = opt_.model_fingerprint;
  ch_feedback_ = bus::channel::feedback(opt_.device, opt_.channel_suffix);
  ch_user_force_ = bus::channel::user_force(opt_.user, opt_.channel_suffix);
  ch_stats_ = bus::channel::stats("coupler_" + std::to_string(opt_.user), opt_.channel_suffix);
  subs_(bus_.subscribe_raw(bus::channel::coeffs(opt_.user, opt_.channel_suffix),
                     [this](const void* d, uint32_t n, const std::string&) { on_snapshot(d, n); }));
  const std::string ch_pose = bus::channel::device_state(opt_.device, opt_.channel_suffix);
  if (opt_.shm) {
    shm_pose_ = std::make_unique<bus::ShmReader>(ch_pose, opt_.stale_after_s);   // no pose of a dead device
    shm_feedback_ = std::make_unique<bus::ShmWriter>(ch_feedback_);
    shm_feedback_check_ = std::make_unique<bus::ShmReader>(ch_feedback_);
  } else {
    subs_(bus_.subscribe<lcmt_device_state>(ch_pose, [this](const lcmt_device_state& m, const std::string&) {
      const double t = since(kEpoch);
      if (!take_pose(m, t)) return;
      pose_box_.write(m);
      pose_recv_s_.store(t, std::memory_order_release);
    }));
    // One writer per device FEEDBACK channel over LCM too (shm: the segment check in publish_stats): a FEEDBACK
    // of another live instance is a second coupler on this device. Peeked from the header, not decoded (our
    // own come back at the loop rate; run() delivers them in a window after each stats tick only); an old
    // stamp is a replay, not a writer.
    feedback_check_ = &subs_(bus_.subscribe_raw(ch_feedback_, [this](const void* d, uint32_t n, const std::string&) {
      int64_t utime = 0, inst = 0;
      if (!bus::peek_origin<lcmt_feedback>(d, n, &utime, &inst) || inst == instance_id_ || inst == 0) return;
      if (!(std::fabs(bus::message_age_s(utime)) <= bus::OriginLock::kDefaultMaxStartAgeS)) return;
      c_.other_feedback_writer.fetch_add(1, std::memory_order_relaxed);
      refused_writer_.store(inst, std::memory_order_relaxed);
    }));
  }
  subs_(bus_.subscribe_latest<lcmt_scene_state>(bus::channel::scene_state(opt_.channel_suffix), scene_box_));
  ch_settings_ = bus::channel::coupler_settings(opt_.user, opt_.channel_suffix);
  // Stamped with the FEEDBACK's instance id: a replay takes each FEEDBACK's settings from its own coupler,
  // not from whichever settings message came last (a replayed one of another coupler, chaos_soak).
  to_settings(opt_, instance_id_, settings_msg_);
  spdlog::info(
      "coupler {}: device {}, k_s {} b_s {}, mapping: scene = {} x device_m + [{} {} {}], force_n = {} x scene "
      "force, clamp {} N, {} Hz, link {}",
      opt_.user, opt_.device, opt_.stiffness, opt_.damping, opt_.position_scale, opt_.offset.x(), opt_.offset.y(),
      opt_.offset.z(), opt_.force_scale, opt_.max_force_n, opt_.rate_hz, opt_.shm ? "shm" : bus_.url());
  spdlog::info("coupler {}: instance {:016x}; stale after {} s; user force clamped to {} scene units "
               "(2 x max_force_n / force_scale); device positions beyond {} m refused; {}",
               opt_.user, static_cast<uint64_t>(instance_id_), opt_.stale_after_s, user_force_limit(opt_),
               opt_.max_device_position_m,
               opt_.model_fingerprint ? fmt::format("expecting model fingerprint {:016x}", opt_.model_fingerprint)
                                      : std::string("no --model-fingerprint: locking onto the first model heard"));
}

// The pose path (handler thread for LCM, loop for shm): one device instance at a time (a new one only
// after the old went silent for stale_after_s: a device restart), newest seq only, and sane values. A
// refused pose is not taken: its age grows and the watchdog takes the force away. No logging here.
bool Coupler::take_pose(const lcmt_device_state& m, double now_s) {
  const bus::Origin o = device_lock_.check(m.instance_id, now_s, bus::message_age_s(m.utime));
  if (!bus::accepted(o)) {
    c_.pose_rejected.fetch_add(1, std::memory_order_relaxed);
    if (o == bus::Origin::kRefused || o == bus::Origin::kInvalid) refused_device_.fetch_add(1, std::memory_order_relaxed);
    if (o == bus::Origin::kTooOld) old_device_.fetch_add(1, std::memory_order_relaxed);
    return false;
  }
  if (o == bus::Origin::kTakeover) {
    c_.device_restarts.fetch_add(1, std::memory_order_relaxed);
    newest_pose_seq_ = -1;
  }
  if (o != bus::Origin::kSame) followed_device_.store(m.instance_id, std::memory_order_relaxed);
  if (m.seq <= newest_pose_seq_) {   // reordered: an older reading of the same device
    c_.stale_rejected.fetch_add(1, std::memory_order_relaxed);
    return false;
  }
  bool sane = true;
  for (int i = 0; i < 3; ++i) sane &= std::isfinite(m.position_m[i]) && std::isfinite(m.linear_velocity_mps[i]);
  for (int i = 0; i < 4; ++i) sane &= std::isfinite(m.orientation[i]);
  sane = sane && Vec3(m.position_m[0], m.position_m[1], m.position_m[2]).norm() <= opt_.max_device_position_m;
  if (!sane) {
    c_.pose_rejected.fetch_add(1, std::memory_order_relaxed);
    bad_pose_value_.store(true, std::memory_order_relaxed);
    return false;
  }
  newest_pose_seq_ = m.seq;
  return true;
}

// Warnings about refused inputs, once each, from the loop's stats tick (never inside the computation).
void Coupler::report_problems() {
  if (!reported_lock_ && opt_.model_fingerprint == 0 && locked_fingerprint_.load() != 0) {
    reported_lock_ = true;
    spdlog::info("coupler {}: locked onto model fingerprint {:016x}, the first one heard (name the model with "
                 "--model-fingerprint to refuse any other)", opt_.user, locked_fingerprint_.load());
  }
  if (!warned_foreign_ && c_.foreign_rejected.load(std::memory_order_acquire) > 0) {
    warned_foreign_ = true;
    spdlog::warn("coupler {}: refusing snapshots of model {:016x}: this coupler {} model {:016x}. Another scene "
                 "is served on this channel: check the sim_server's --scene/--n/--urdf and --channel-suffix.",
                 opt_.user, foreign_fp_.load(), opt_.model_fingerprint ? "expects (--model-fingerprint)" : "locked onto",
                 locked_fingerprint_.load());
  }
  if (!warned_old_snapshot_ && old_snapshots_.load(std::memory_order_acquire) > 0) {
    warned_old_snapshot_ = true;
    spdlog::warn("coupler {}: refusing snapshots of server instance {:016x} stamped {:.3f} s away from this host's "
                 "clock: a replayed recording, or hosts whose clocks differ by more than {} s (synchronise them)",
                 opt_.user, static_cast<uint64_t>(old_snapshot_instance_.load()), old_snapshot_age_s_.load(),
                 bus::OriginLock::kDefaultMaxStartAgeS);
  }
  if (!warned_duplicate_ && c_.duplicate_rejected.load(std::memory_order_acquire) > 0) {
    warned_duplicate_ = true;
    spdlog::warn("coupler {}: refusing snapshots from server instance {:016x}: server instance {:016x} is live "
                 "on the same channel (two sim_servers for one user, or a replay). Stop one of them.",
                 opt_.user, static_cast<uint64_t>(duplicate_instance_.load()),
                 static_cast<uint64_t>(duplicate_locked_.load()));
  }
  if (const int64_t r = c_.restarts.load(std::memory_order_acquire); r != reported_restarts_) {
    reported_restarts_ = r;
    spdlog::info("coupler {}: new server instance {:016x} (the previous one was silent for more than {} s), "
                 "resuming at version {}{}", opt_.user, static_cast<uint64_t>(takeover_instance_.load()),
                 opt_.stale_after_s, takeover_version_.load(), r > 1 ? fmt::format(" ({} restarts)", r) : "");
  }
  if (!warned_implausible_ && c_.implausible_rejected.load(std::memory_order_acquire) > 0) {
    warned_implausible_ = true;
    spdlog::warn("coupler {}: refusing snapshot version {} after version {} {:.3f} s earlier: no server steps that "
                 "fast (a replayed or corrupted message)", opt_.user, implausible_version_.load(),
                 implausible_after_.load(), implausible_dt_s_.load());
  }
  if (!warned_device_ && refused_device_.load() > 0) {
    warned_device_ = true;
    spdlog::warn("coupler {}: refused {} DEVICE_STATE message(s) from a device instance other than the one "
                 "this coupler follows ({:016x}) while it is live: two device_bridges on --device {}, or a stray "
                 "publisher. They cannot press or release the grab.",
                 opt_.user, refused_device_.load(), static_cast<uint64_t>(followed_device_.load()), opt_.device);
  }
  if (!warned_old_device_ && old_device_.load() > 0) {
    warned_old_device_ = true;
    spdlog::warn("coupler {}: refused {} DEVICE_STATE message(s) of a new device instance stamped more than {} s away "
                 "from this host's clock: a replayed recording, or hosts whose clocks differ (synchronise them)",
                 opt_.user, old_device_.load(), bus::OriginLock::kDefaultMaxStartAgeS);
  }
  if (!warned_bad_pose_ && bad_pose_value_.load()) {
    warned_bad_pose_ = true;
    spdlog::warn("coupler {}: refused a device position that is non-finite or farther than "
                 "--max-device-position-m {} m from the device origin (a glitch); the watchdog zeroes the force "
                 "until sane positions arrive",
                 opt_.user, opt_.max_device_position_m);
  }
  if (c_.device_restarts.load() != reported_device_restarts_) {
    reported_device_restarts_ = c_.device_restarts.load();
    spdlog::info("coupler {}: now following device instance {:016x} (the previous one went silent)", opt_.user,
                 static_cast<uint64_t>(followed_device_.load()));
  }
  if (!warned_writer_ && c_.other_feedback_writer.load() > 0) {
    warned_writer_ = true;
    spdlog::warn("coupler {}: another coupler (instance {:016x}) writes FEEDBACK for device {} too: two couplers "
                 "on one device. The device_bridge follows only one of them; stop the other.",
                 opt_.user, static_cast<uint64_t>(refused_writer_.load()), opt_.device);
  }
  if (!warned_clamp_ && c_.user_force_clamps.load() > 0) {
    warned_clamp_ = true;
    spdlog::warn("coupler {}: the user force reached the scene-side limit {} (2 x --max-force-n / --force-scale) "
                 "and was clamped (counted in clamp_events)",
                 opt_.user, user_force_limit(opt_));
  }
}

Coupler::~Coupler() = default;

int64_t Coupler::rejected_messages() const {
  return c_.foreign_rejected.load() + c_.stale_rejected.load() + c_.bad_rejected.load() + c_.duplicate_rejected.load() +
         c_.implausible_rejected.load() + c_.pose_rejected.load() + bus_.rejected_total() +
         (shm_pose_ ? shm_pose_->rejected() : 0);
}

// No server steps faster than this: a version may advance by at most kMaxStepRate x the time since the
// previous accepted snapshot (+ kVersionSlack). 1 MHz is far above any real step rate (>= 1 µs per step);
// a replayed or corrupted version such as 5e12 is far beyond it.
constexpr double kMaxStepRate = 1e6;
constexpr int64_t kVersionSlack = 1000;

// Bus handler thread: decode, check (model, server instance, version), convert into the back slot, publish
// (allocation allowed here).
void Coupler::on_snapshot(const void* data, uint32_t size) {
  if (bus::decode_checked(data, size, snap_msg_) != bus::DecodeResult::kOk) {
    c_.bad_rejected.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  const double now = since(kEpoch);
  const uint64_t fp = bus::fingerprint_from_wire(snap_msg_.model_fingerprint);
  uint64_t locked = locked_fingerprint_.load();
  if (locked == 0) {
    locked_fingerprint_ = fp;
    locked = fp;
  }
  // The handler thread never logs (it carries what the loop waits for): the first case of each refusal is
  // noted, report_problems logs it from the loop's stats tick. The handler is the only writer of the counters.
  if (fp != locked) {
    if (c_.foreign_rejected.load(std::memory_order_relaxed) == 0) foreign_fp_.store(fp, std::memory_order_relaxed);
    c_.foreign_rejected.fetch_add(1, std::memory_order_release);
    return;
  }
  // One server instance at a time: a new one only after the old stream went silent for stale_after_s (by
  // then the watchdog has taken the force away): that is a restart, whatever the versions. Older versions
  // of the same instance are reordered or duplicated datagrams: ignored, counted, no log.
  const bus::Origin o = server_lock_.check(snap_msg_.instance_id, now, bus::message_age_s(snap_msg_.utime));
  if (o == bus::Origin::kPrevious) {
    c_.stale_rejected.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  if (o == bus::Origin::kTooOld) {   // a replay: it must not pass for a restarted server (chaos_soak)
    c_.stale_rejected.fetch_add(1, std::memory_order_relaxed);
    if (old_snapshots_.load(std::memory_order_relaxed) == 0) {
      old_snapshot_instance_.store(snap_msg_.instance_id, std::memory_order_relaxed);
      old_snapshot_age_s_.store(bus::message_age_s(snap_msg_.utime), std::memory_order_relaxed);
    }
    old_snapshots_.fetch_add(1, std::memory_order_release);
    return;
  }
  if (!bus::accepted(o)) {
    if (c_.duplicate_rejected.load(std::memory_order_relaxed) == 0) {
      duplicate_instance_.store(snap_msg_.instance_id, std::memory_order_relaxed);
      duplicate_locked_.store(server_lock_.locked(), std::memory_order_relaxed);
    }
    c_.duplicate_rejected.fetch_add(1, std::memory_order_release);
    return;
  }
  if (o == bus::Origin::kTakeover) {
    takeover_instance_.store(snap_msg_.instance_id, std::memory_order_relaxed);
    takeover_version_.store(snap_msg_.version, std::memory_order_relaxed);
    newest_version_ = -1;
    c_.restarts.fetch_add(1, std::memory_order_release);
  }
  if (snap_msg_.version < 0 ||
      (newest_version_ >= 0 &&
       static_cast<double>(snap_msg_.version - newest_version_) > kVersionSlack + kMaxStepRate * (now - newest_accept_s_))) {
    if (c_.implausible_rejected.load(std::memory_order_relaxed) == 0) {
      implausible_version_.store(snap_msg_.version, std::memory_order_relaxed);
      implausible_after_.store(newest_version_, std::memory_order_relaxed);
      implausible_dt_s_.store(now - newest_accept_s_, std::memory_order_relaxed);
    }
    c_.implausible_rejected.fetch_add(1, std::memory_order_release);
    return;
  }
  if (snap_msg_.version <= newest_version_) {
    c_.stale_rejected.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  CouplingSnapshot& back = snap_box_.back();
  bus::from_lcmt(snap_msg_, back);
  back.source_instance = snap_msg_.instance_id;
  // No subnormal value reaches the loop, whoever built the snapshot (sim_server's are flushed).
  if (const std::size_t k = flush_subnormals(back.values.data(), back.values.size()))
    c_.subnormals_flushed.fetch_add(static_cast<int64_t>(k), std::memory_order_relaxed);
  if (back.grabs.size() != 1 || validate_coupling_snapshot(back) != CouplingStatus::kOk || !ws_.fits(back)) {
    c_.bad_rejected.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  newest_version_ = snap_msg_.version;
  newest_accept_s_ = now;
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
    // decode into a scratch message: a refused pose must not replace the last good one
    if (shm_pose_->read_msg(shm_pose_msg_) == bus::ShmRead::kNew && take_pose(shm_pose_msg_, now)) {
      pose_ = shm_pose_msg_;
      pose_time_s_ = now;
    }
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
      // Nearest body within the grab radius of the proxy (none farther: the press grabs nothing).
      double best = opt_.grab_radius > 0 ? opt_.grab_radius * opt_.grab_radius : std::numeric_limits<double>::infinity();
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
      grab_old_version_ = snap.version;
      grab_old_instance_ = snap.source_instance;
      send_user_force = true;
    }
  } else if (!button && grabbing_) {
    grabbing_ = false;
    send_user_force = true;
  }
  Vec3 force_n = Vec3::Zero();
  f_u_.setZero();
  f_feed_.setZero();
  int64_t version = -1, snapshot_instance = 0;
  // Arrival times are taken by the handler thread: a message that arrived after this iteration's `now`
  // was read is fresh (age 0), not negative, which the watchdog would count as stale.
  double age = pose_time_s_ >= 0 ? std::max(0.0, now - pose_time_s_) : 1e9;
  if (grabbing_) {
    // The snapshot's age counts once coefficients for this grab are in use. Before the first one arrives
    // (the server has not seen the grab yet) the force is zero anyway: that is not a stale input, and
    // counting it made every grab a watchdog trip with a 100 ms ramp-in.
    const bool for_this_grab = snap.source_instance != grab_old_instance_ || snap.version > grab_old_version_;
    if (snap.version >= 0 && for_this_grab && snap.grabs.size() == 1 && snap.grabs[0].body == body_) {
      const double snap_t = snapshot_recv_s_.load(std::memory_order_acquire);
      age = std::max(age, snap_t >= 0 ? std::max(0.0, now - snap_t) : 1e9);
      if (1e3 * age > c_.max_grab_input_age_ms.load(std::memory_order_relaxed))
        c_.max_grab_input_age_ms.store(1e3 * age, std::memory_order_relaxed);
      CouplingInputs in{x_dev, v_dev};
      bool clamped = false;
      if (coupler_feedback(opt_, snap, in, ws_, f_u_, f_feed_, force_n, &clamped) != CouplingStatus::kOk)
        force_n.setZero();
      if (clamped) c_.user_force_clamps.fetch_add(1, std::memory_order_relaxed);
      version = snap.version;
      snapshot_instance = snap.source_instance;
    }
  }
  const int64_t trips_before = safety_.watchdog().trips();
  const GuardedForce g = safety_.apply(now, age, force_n, Vec3::Zero());
  if (grabbing_ && safety_.watchdog().trips() != trips_before)
    c_.grab_watchdog_trips.fetch_add(1, std::memory_order_relaxed);
  if (grabbing_) {
    c_.grab_feedbacks.fetch_add(1, std::memory_order_relaxed);
    if ((g.flags & kSafetyWatchdog) && g.force.isZero(0)) c_.grab_watchdog_zeros.fetch_add(1, std::memory_order_relaxed);
  }
  device::FeedbackCommand cmd;
  cmd.echo_device_seq = pose_.seq;
  cmd.snapshot_version = version;
  cmd.snapshot_instance = snapshot_instance;
  cmd.echo_device_instance = pose_.instance_id;
  cmd.force_n = g.force;
  cmd.flags = g.flags;
  device::to_lcmt(cmd, opt_.device, ++feedback_seq_, bus::now_utime(), fb_);
  fb_.instance_id = instance_id_;
  if (shm_feedback_) {
    shm_feedback_->write_msg(fb_);
  } else {
    bus_.publish(ch_feedback_, fb_);
  }
  if (send_user_force) {
    bus::stamp(uf_, instance_id_);
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

bool Coupler::new_pose_waiting() const noexcept {
  if (shm_pose_) return shm_pose_->latest_index() != shm_pose_->last_index();
  return pose_recv_s_.load(std::memory_order_acquire) != pose_time_s_;
}

void Coupler::publish_stats(double period_s, int64_t iterations) {
  const double now = since(kEpoch);
  const double snap_t = snapshot_recv_s_.load();
  const double age_ms = snap_t >= 0 ? 1e3 * (now - snap_t) : -1;
  c_.rate_hz = static_cast<double>(iterations) / period_s;
  c_.p50_us = hist_.percentile(0.5);
  c_.p99_us = hist_.percentile(0.99);
  c_.snapshot_age_ms = age_ms;
  c_.grab_body = grabbing_ ? body_ : 0;
  lcmt_process_stats s{};
  bus::stamp(s, instance_id_);
  s.seq = ++stats_seq_;
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
  s.clamp_events = safety_.clamp_events() + c_.user_force_clamps.load();
  s.nonfinite_events = safety_.nonfinite_events();
  // The mapping too, so a viewer can draw the device point in the scene and a browser device can
  // invert it (scene = position_scale x device_m + offset).
  s.extra_names = {"force_n", "grab_body", "restarts", "duplicate_rejected", "pose_rejected", "position_scale",
                   "offset_x", "offset_y", "offset_z", "force_scale", "max_force_n"};
  s.extra_values = {c_.force_n.load(), static_cast<double>(grabbing_ ? body_ : 0),
                    static_cast<double>(c_.restarts.load()), static_cast<double>(c_.duplicate_rejected.load()),
                    static_cast<double>(c_.pose_rejected.load()), opt_.position_scale, opt_.offset.x(),
                    opt_.offset.y(), opt_.offset.z(), opt_.force_scale, opt_.max_force_n};
  s.n_extra = static_cast<int32_t>(s.extra_names.size());
  bus_.publish(ch_stats_, s);
  hist_.reset();
  // Another writer on our device's FEEDBACK segment? Its newest message would carry another instance id.
  if (shm_feedback_check_) {
    if (shm_feedback_check_->read_msg(fb_check_) == bus::ShmRead::kNew && fb_check_.instance_id != instance_id_) {
      c_.other_feedback_writer.fetch_add(1, std::memory_order_relaxed);
      refused_writer_.store(fb_check_.instance_id, std::memory_order_relaxed);
    }
  }
  report_problems();
}

void Coupler::publish_settings() {
  settings_msg_.utime = bus::now_utime();
  bus_.publish(ch_settings_, settings_msg_);
}

int Coupler::run(const std::atomic<bool>& stop) {
  // FTZ/DAZ in the loop: no microcode assist for a subnormal operand on any CPU, whatever
  // the snapshot holds (on_snapshot flushes them too) or the arithmetic makes.
  const ScopedFlushDenormals ftz;
  c_.ftz_daz.store(ScopedFlushDenormals::active(), std::memory_order_relaxed);
  const double period = 1.0 / opt_.rate_hz;
  double next = since(kEpoch);
  if (feedback_check_) feedback_check_until_s_ = next + kWriterCheckWindow_s;   // the first window
  double next_stats = next + 1.0, stats_start = next;
  publish_settings();
  double next_settings = next + kSettingsEvery_s;
  int64_t it_at_stats = 0, it = 0;
  while (!stop.load(std::memory_order_relaxed)) {
    const double now = since(kEpoch);
    iterate(now);
    ++it;
    c_.iterations.store(it, std::memory_order_relaxed);
    if (feedback_check_until_s_ >= 0 && now >= feedback_check_until_s_) {   // end of the writer-check window
      bus::set_delivery(bus_, *feedback_check_, false);
      feedback_check_until_s_ = -1;
    }
    if (now >= next_stats) {   // once a second, outside the computation
      publish_stats(now - stats_start, it - it_at_stats);
      if (feedback_check_) {
        bus::set_delivery(bus_, *feedback_check_, true);
        feedback_check_until_s_ = now + kWriterCheckWindow_s;
      }
      it_at_stats = it;
      stats_start = now;
      next_stats += 1.0;
      if (now >= next_settings) {   // again, for a logger that started late
        publish_settings();
        next_settings += kSettingsEvery_s;
      }
    }
    next += period;
    if (since(kEpoch) > next + 0.01) next = since(kEpoch);   // overrun: do not try to catch up
    if (opt_.busy_wait) {
      // --busy-poll: a new device pose ends the wait; that iteration takes the place of the next tick, so
      // the rate stays --coupler-rate-hz and the pose waits for no tick (lower pose-to-force latency).
      while (since(kEpoch) < next && !stop.load(std::memory_order_relaxed) && !(opt_.busy_poll && new_pose_waiting())) {
      }
    } else {
      bus::sleep_until_or_stop(kEpoch + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(next)),
                               stop);
    }
  }
  if (feedback_check_) bus::set_delivery(bus_, *feedback_check_, true);   // as constructed
  report_problems();   // what the last second refused
  return 0;
}

}  // namespace haptree
