#include "sim_server/sim_server.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <thread>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/pacing.hpp"
#include "haptree/bus/latest_value.hpp"
#include "haptree/bus/origin.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/dca.hpp"
#include "haptree/fp_env.hpp"
#include "haptree/io/urdf.hpp"
#include "haptree/lcmt_process_stats.hpp"
#include "haptree/lcmt_scene_state.hpp"
#include "haptree/molecule/scene.hpp"
#include "haptree/safety.hpp"
#include "haptree/molecule/trajectory.hpp"
#include "haptree/scenes.hpp"

namespace haptree {
namespace molecule_fwd {
struct Holder {
  mol::MolecularScene scene;
};
}  // namespace molecule_fwd

using Clock = std::chrono::steady_clock;
static const Clock::time_point kEpoch = Clock::now();
static double since_epoch() { return std::chrono::duration<double>(Clock::now() - kEpoch).count(); }

struct SimServer::UserSlot {
  int user = 0;
  bus::LatestValue<lcmt_user_force> box;
  lcmt_user_force latest{};
  // handler thread: which coupler this user's forces come from, and its newest seq
  bus::OriginLock origin;
  int64_t newest_seq = 0;
  std::atomic<bool> warned_foreign{false}, warned_old{false};
  // stepping thread: arrival time of the newest message, its force after the sanity checks, watchdog
  double last_in_s = -1;
  double max_gap_s = 0;
  Vec6 f_msg = Vec6::Zero();
  Watchdog watchdog;
  std::atomic<double> applied_norm{0};
  bool grabbing = false;
  int body = -1;
  Vec3 local_point = Vec3::Zero();
  Vec3 grab_point_msg = Vec3::Zero();   // grab point of the current grab, as the coupler sent it
  Vec6 f_u = Vec6::Zero();     // applied force at the grab point (world axes, scene units)
  Grab grab;
  CouplingSnapshot snapshot;
  lcmt_coupling_snapshot msg;
  std::string channel;
};

static bool is_procedural(const std::string& s) {
  return s == "chain" || s == "binary_tree" || s == "random_tree" || s == "star" || s == "protein_like";
}

static void check_options(const SimServerOptions& o) {
  auto fail = [](const std::string& what) { throw std::invalid_argument("sim_server: " + what); };
  auto pos = [](double v) { return std::isfinite(v) && v > 0; };
  if (!pos(o.dt)) fail("--dt must be a positive finite time step, got " + std::to_string(o.dt));
  if (!(std::isfinite(o.rate_hz) && o.rate_hz >= 0)) fail("--sim-rate-hz must be >= 0 (0 = free-running)");
  if (!(std::isfinite(o.display_rate_hz) && o.display_rate_hz >= 0)) fail("--display-rate-hz must be >= 0");
  if (o.users < 1) fail("--users must be at least 1, got " + std::to_string(o.users));
  if (o.n < 1) fail("--n must be at least 1, got " + std::to_string(o.n));
  if (o.budget_dofs < 1) fail("--budget-dofs must be at least 1, got " + std::to_string(o.budget_dofs));
  if (!(std::isfinite(o.epsilon) && o.epsilon >= 0)) fail("--epsilon must be >= 0");
  if (o.reselect_every < 1) fail("--reselect-every must be at least 1");
  if (o.steps < 0) fail("--steps must be >= 0");
  if (!pos(o.max_joint_rate)) fail("--max-joint-rate must be positive");
  if (o.checkpoint_every < 1) fail("--checkpoint-every must be at least 1");
  if (!pos(o.user_force_stale_s) || !(std::isfinite(o.user_force_ramp_s) && o.user_force_ramp_s >= 0))
    fail("--user-force-stale-s must be positive and the ramp >= 0");
  if (!pos(o.max_user_force)) fail("--max-user-force must be positive");
}

SimServer::SimServer(bus::Bus& bus, const SimServerOptions& options)
    : bus_(bus), opt_(options), instance_id_(bus::new_instance_id()) {
  check_options(opt_);
  const bool default_gravity = !opt_.gravity.allFinite();
  if (!opt_.urdf.empty()) {
    io::UrdfOptions uo;
    if (!default_gravity) uo.gravity = opt_.gravity;
    model_ = io::load_urdf(opt_.urdf, uo);
  } else if (is_procedural(opt_.scene)) {
    SceneOptions so;
    so.n = opt_.n;
    if (opt_.scene == "random_tree") so.seed = 1;
    so.gravity = !default_gravity ? opt_.gravity
                 : opt_.scene == "protein_like" ? Vec3::Zero()
                                                : Vec3(0, 0, -9.81);
    model_ = make_scene(opt_.scene, so);
  } else {
    molecule_ = std::make_unique<molecule_fwd::Holder>(molecule_fwd::Holder{mol::load_molecular_scene(opt_.scene)});
    model_ = molecule_->scene.model;
    for (const auto& m : molecule_->scene.messages) spdlog::info("molecule: {}", m);
  }
  data_ = std::make_unique<Data>(*model_);
  state_ = std::make_unique<State>(*model_);
  ad_ = std::make_unique<AdaptiveData>(*model_);
  if (opt_.epsilon > 0) {
    adaptive_.mode = AdaptiveOptions::Mode::kThreshold;
    adaptive_.epsilon = opt_.epsilon;
  } else {
    adaptive_.mode = AdaptiveOptions::Mode::kBudget;
    adaptive_.budget = opt_.budget_dofs;
  }
  adaptive_.reselect_every = opt_.reselect_every;
  for (int u = 0; u < opt_.users; ++u) {
    auto slot = std::make_unique<UserSlot>();
    slot->user = u;
    slot->channel = bus::channel::coeffs(u, opt_.channel_suffix);
    slot->origin = bus::OriginLock(opt_.user_force_stale_s);
    slot->watchdog = Watchdog(WatchdogParams{opt_.user_force_stale_s, opt_.user_force_ramp_s, 0.1});
    // Handler thread: one coupler per user (a second live one is refused), reordered messages dropped.
    subs_(bus_.subscribe<lcmt_user_force>(
        bus::channel::user_force(u, opt_.channel_suffix), [this, slot = slot.get()](const lcmt_user_force& m, const std::string&) {
          const bus::Origin o = slot->origin.check(m.instance_id, since_epoch(), bus::message_age_s(m.utime));
          if (!bus::accepted(o)) {
            c_.foreign_rejected.fetch_add(1, std::memory_order_relaxed);
            if (o == bus::Origin::kTooOld && !slot->warned_old.exchange(true))
              spdlog::warn("sim_server: refusing USER_FORCE for user {} from a new coupler instance {:016x} stamped "
                           "{:.3f} s away from this host's clock: a replayed recording, or hosts whose clocks differ "
                           "by more than {} s (synchronise them)", slot->user, static_cast<uint64_t>(m.instance_id),
                           bus::message_age_s(m.utime), bus::OriginLock::kDefaultMaxStartAgeS);
            if (o != bus::Origin::kPrevious && o != bus::Origin::kTooOld && !slot->warned_foreign.exchange(true))
              spdlog::warn("sim_server: refusing USER_FORCE for user {} from coupler instance {:016x}: coupler "
                           "instance {:016x} is live on that channel. Run one coupler per user (--user).",
                           slot->user, static_cast<uint64_t>(m.instance_id), static_cast<uint64_t>(slot->origin.locked()));
            return;
          }
          if (o == bus::Origin::kTakeover) {
            spdlog::info("sim_server: user {}: new coupler instance {:016x}", slot->user,
                         static_cast<uint64_t>(m.instance_id));
            slot->newest_seq = 0;
          } else if (m.seq <= slot->newest_seq) {
            c_.stale_rejected.fetch_add(1, std::memory_order_relaxed);
            return;
          }
          slot->newest_seq = m.seq;
          slot->box.write(m);
          c_.user_forces_in.fetch_add(1, std::memory_order_relaxed);
        }));
    users_.push_back(std::move(slot));
  }
  forward_kinematics(*model_, *data_, state_->q);
  if (!molecule_) start_background_selection(*model_, *ad_);   // allocated now, not in a step
  checkpoint_ = std::make_unique<State>(*state_);
  if (!opt_.trajectory.empty()) {   // trajectory: atoms of a molecule, else one pseudo-atom per body
    mol::TrajectoryOptions to;
    to.path = opt_.trajectory;
    to.every_steps = opt_.trajectory_every_steps;
    to.every_time = opt_.trajectory_every_time;
    to.dt = opt_.dt;
    trajectory_ = molecule_ ? std::make_unique<mol::TrajectoryRecorder>(to, &molecule_->scene.structure,
                                                                        molecule_->scene.natoms())
                            : std::make_unique<mol::TrajectoryRecorder>(to, nullptr, model_->nbodies - 1);
    spdlog::info("sim_server: trajectory to {} every {}", to.path,
                 to.every_time > 0 ? fmt::format("{:g} time units", to.every_time)
                                   : fmt::format("{} steps", to.every_steps));
  }
  spdlog::info("sim_server: scene '{}' with {} bodies, {} DOF, fingerprint {:016x}, dt {}",
               opt_.urdf.empty() ? opt_.scene : opt_.urdf, model_->nbodies - 1, model_->nv, model_->fingerprint,
               opt_.dt);
}

SimServer::~SimServer() = default;

Vec6 SimServer::applied_user_force(int u) const { return users_.at(static_cast<size_t>(u))->f_u; }
double SimServer::applied_user_force_norm(int u) const {
  return users_.at(static_cast<size_t>(u))->applied_norm.load(std::memory_order_relaxed);
}

// Takes the newest USER_FORCE of one user: sanity check and clamp once per message (non-finite -> zero,
// above max_user_force -> scaled down, both counted), then the watchdog gain on its age.
void SimServer::take_user_force(UserSlot& u, double now) {
  if (u.box.update()) {
    u.latest = u.box.front();
    if (u.last_in_s >= 0) {
      u.max_gap_s = std::max(u.max_gap_s, now - u.last_in_s);
      if (now - u.last_in_s > c_.user_force_gap_max_s.load(std::memory_order_relaxed))
        c_.user_force_gap_max_s.store(now - u.last_in_s, std::memory_order_relaxed);
    }
    u.last_in_s = now;
    Vec6 f;
    for (int i = 0; i < 6; ++i) f[i] = u.latest.force[i];
    if (!f.allFinite()) {
      f.setZero();
      c_.nonfinite_events.fetch_add(1, std::memory_order_relaxed);
    } else if (f.head<3>().norm() > opt_.max_user_force || f.tail<3>().norm() > opt_.max_user_force) {
      bool clamped = false;
      f.head<3>() = clamp_norm(f.head<3>(), opt_.max_user_force, &clamped);
      f.tail<3>() = clamp_norm(f.tail<3>(), opt_.max_user_force, &clamped);
      if (c_.clamp_events.fetch_add(1, std::memory_order_relaxed) == 0)
        spdlog::warn("sim_server: user {} sent a force of {:.3g} scene units, above --max-user-force {}: clamped "
                     "(counted in clamp_events; the coupler should already clamp to 2 x max_force_n / force_scale)",
                     u.user, Vec3(u.latest.force[3], u.latest.force[4], u.latest.force[5]).norm(),
                     opt_.max_user_force);
    }
    u.f_msg = f;
  }
  const int64_t trips = u.watchdog.trips();
  const double age = u.last_in_s >= 0 ? now - u.last_in_s : std::numeric_limits<double>::infinity();
  u.watchdog.update(now, age);
  if (u.watchdog.trips() != trips) c_.watchdog_events.fetch_add(1, std::memory_order_relaxed);
}

void SimServer::step_once() {
  const Model& m = *model_;
  Data& d = *data_;
  State& st = *state_;
  // 1. Latest user forces; a new grab fixes the material point in the body frame.
  bool grab_changed = false;
  const double now = since_epoch();
  for (auto& u : users_) {
    take_user_force(*u, now);
    const lcmt_user_force& msg = u->latest;
    const bool want = msg.active && msg.grab_body >= 1 && msg.grab_body < m.nbodies;
    // The coupler keeps grab_point fixed for one grab: another point is another grab, even on the same
    // body with the release in between coalesced away by the mailbox.
    const Vec3 gp(msg.grab_point[0], msg.grab_point[1], msg.grab_point[2]);
    const bool new_point = want && u->grabbing && gp != u->grab_point_msg;
    if (want != u->grabbing || (want && msg.grab_body != u->body) || new_point) grab_changed = true;
    if (want && (!u->grabbing || msg.grab_body != u->body || new_point)) {
      u->grab_point_msg = gp;
      u->body = msg.grab_body;
      const Vec3 p(msg.grab_point[0], msg.grab_point[1], msg.grab_point[2]);
      Mat3 Rb;
      Vec3 rb;
      body_pose(d, *ad_, u->body, Rb, rb);   // the body may sit inside a rigid region: O(1)
      u->local_point = Rb.transpose() * (p - rb);
    }
    u->grabbing = want;
    if (want) {
      // A stale user's force ramps to zero (the grab is kept, so the coupler resumes where it was).
      u->f_u = u->watchdog.gain() * u->f_msg;
    } else {
      u->f_u.setZero();
    }
    u->applied_norm.store(u->f_u.tail<3>().norm(), std::memory_order_relaxed);
  }
  // 2. Selection. Every grabbed body's root path stays active (AdaptiveData::keep_active_bodies),
  //    so each grabbed body is a leaf of the active tree and its snapshot is O(log n). Robot scenes:
  //    a new grab makes a selection due, which runs in the background like the periodic ones
  //    (adaptive_step), off the step; until the region that holds the body's path is in force the
  //    grab has no force and no snapshot (the coupler's force is zero until its first snapshot).
  //    A reset that could not be undone within the region in force selects at once, in the step.
  //    Molecules select here, on a new grab and every reselect_every steps: the force field's rigid
  //    regions follow each selection.
  keep_.clear();
  for (auto& u : users_)
    if (u->grabbing && std::find(keep_.begin(), keep_.end(), u->body) == keep_.end()) keep_.push_back(u->body);
  if (ad_->keep_active_bodies != keep_) ad_->keep_active_bodies = keep_;
  const bool periodic = ad_->steps_since_selection >= std::max(1, opt_.reselect_every);
  if (resync_ || (molecule_ && (grab_changed || periodic))) {
    if (molecule_) molecule_->scene.force_field->clear_rigid_regions();
    select_active_region(m, d, st, *ad_, adaptive_);
    resync_ = false;
    if (molecule_) molecule_->scene.force_field->set_rigid_regions(ad_->frontier_of_body);
  }
  // 3. External forces: force field (molecules, every body), then user forces moved to the body
  //    origin. Robot scenes touch only the grabbed bodies (the hybrid pass reads the list).
  if (molecule_) {
    update_all_body_poses(m, d, *ad_);
    molecule_->scene.compute(d, st.f_ext);
  } else {
    for (int k : loaded_) st.f_ext[k].setZero();
    loaded_.clear();
  }
  for (auto& u : users_) {
    if (!u->grabbing || !body_in_active_tree(m, *ad_, u->body)) continue;   // the body's pose is current
    u->grab = make_grab(d, u->body, u->local_point);
    const Vec3 arm = u->grab.point - d.r[u->body];
    Vec6 f0 = u->f_u;
    f0.head<3>() += arm.cross(u->f_u.tail<3>());   // = grab_force_at_body_origin for the same pose
    st.f_ext[u->body] += f0;
    if (!molecule_ && std::find(loaded_.begin(), loaded_.end(), u->body) == loaded_.end())
      loaded_.push_back(u->body);
  }
  if (!molecule_) {
    ad_->scan_forces = false;
    if (ad_->loaded_bodies != loaded_) ad_->loaded_bodies = loaded_;
  }
  // 4. Step (robot scenes: with the background reselection every reselect_every steps).
  AdaptiveOptions step_opt = adaptive_;
  if (molecule_) {
    step_opt.reselect_every = std::numeric_limits<int>::max();
    step_opt.background_selection = false;
  }
  const AdaptiveReport& rep = adaptive_step(m, d, st, *ad_, step_opt, opt_.dt);
  active_dofs_.store(rep.active_dofs, std::memory_order_relaxed);
  just_reset_ = guard_state();
  if (!just_reset_) ++version_;
}

// Explicit integration of a floppy body can diverge (a whipping light link, a too-stiff user
// spring): rather than publish coefficients of a NaN body, go back to the last healthy checkpoint,
// at rest, and reselect. Copies are into preallocated vectors; logging only on the rare reset.
bool SimServer::guard_state() {
  State& st = *state_;
  // Only the active joints moved in this step (the others keep q, and q̇ = 0): O(|active|).
  const Model& m = *model_;
  double rate = 0;
  bool finite = true;
  for (int J : ad_->active_joints) {
    const int a = m.q_adr[J], n = joint_nq(m.joint_type[J]);
    finite = finite && st.q.segment(a, n).allFinite();
    if (m.v_num[J] > 0) rate = std::max(rate, st.qd.segment(m.v_adr[J], m.v_num[J]).cwiseAbs().maxCoeff());
  }
  const bool healthy = finite && std::isfinite(rate) && rate <= opt_.max_joint_rate;
  if (healthy) {
    // A checkpoint every checkpoint_every steps and, for robot scenes, at every new region (a memcpy
    // of q): a reset then needs to restore only the joints of the region in force.
    if (++steps_since_checkpoint_ >= opt_.checkpoint_every ||
        (!molecule_ && ad_->report.selections != checkpoint_selections_)) {
      checkpoint_->q = st.q;
      checkpoint_->t = st.t;
      checkpoint_selections_ = ad_->report.selections;
      steps_since_checkpoint_ = 0;
    }
    return false;
  }
  const int64_t n = resets_.fetch_add(1, std::memory_order_relaxed) + 1;
  // Robot scenes, without a pass over the whole tree (O(|active|); the next selection runs in the
  // background; the frontier caches still hold because no inactive joint moved):
  //  - the region in force is the checkpoint's: only its active joints have moved since (inactive
  //    joints have q̇ = 0), so restoring them restores the whole checkpoint;
  //  - the region was installed by this very step (a checkpoint follows every new region's first
  //    healthy step), for the configuration at the step's start: that configuration, at rest, by
  //    integrating the active joints back over dt (the lock into a new region is what can diverge).
  // Otherwise (molecules, a non-finite state) every joint from the checkpoint and a selection in the step.
  const bool region_only = !molecule_ && checkpoint_selections_ == ad_->report.selections;
  const bool step_back = !molecule_ && !region_only && finite && std::isfinite(rate);
  if (n == 1 || n % 100 == 0)
    spdlog::warn("sim_server: state diverged at t = {:.4g} (max |q̇| {:.3g} > {:.3g} or non-finite); "
                 "restored {} at rest ({}; reset #{}). Lower --dt or the coupling stiffness/damping, or add "
                 "--budget-dofs headroom.",
                 st.t, rate, opt_.max_joint_rate,
                 step_back ? fmt::format("the state of t = {:.4g}", st.t - opt_.dt)
                           : fmt::format("the checkpoint of t = {:.4g}", checkpoint_->t),
                 region_only || step_back ? "the active region's joints" : "every joint, then a selection in the step",
                 n);
  steps_since_checkpoint_ = 0;
  ++version_;
  if (region_only || step_back) {
    local_resets_.fetch_add(1, std::memory_order_relaxed);
    for (int J : ad_->active_joints) {
      const int a = m.q_adr[J], nq = joint_nq(m.joint_type[J]);
      if (region_only) st.q.segment(a, nq) = checkpoint_->q.segment(a, nq);
      else integrate_joint(m, J, st.q, st.qd, -opt_.dt);
      if (m.v_num[J] > 0) st.qd.segment(m.v_adr[J], m.v_num[J]).setZero();
    }
    request_reselection(*ad_);
    return true;
  }
  const double t = st.t;
  st.q = checkpoint_->q;
  st.qd.setZero();
  st.t = t;
  forward_kinematics(*model_, *data_, st.q);
  ad_->steps_since_selection = 1 << 30;
  resync_ = true;   // reselect (and rebuild the frontier caches) in the next step, synchronously
  return true;
}

void SimServer::publish_snapshots() {
  const Model& m = *model_;
  Data& d = *data_;
  // No pose update: a grabbed body is a leaf of the active tree, so its pose and its handles'
  // offsets are the step's own (reduced kinematics), and the snapshot reads only its root path.
  for (auto& u : users_) {
    if (!u->grabbing || !body_in_active_tree(m, *ad_, u->body)) continue;   // its region is not in force yet
    // The coefficients in Data are those of the pass just done (poses at the start of the step).
    std::vector<Grab>& grabs = u->snapshot.grabs;
    grabs.assign(1, make_grab(d, u->body, u->local_point));
    static thread_local std::vector<Vec6> fu(1);
    fu[0] = u->f_u;
    try {
      make_coupling_snapshot(m, d, grabs, fu, version_, state_->t, u->snapshot);
    } catch (const std::exception& e) {
      if (snapshot_errors_++ == 0) spdlog::error("sim_server: no snapshot for user {}: {}", u->user, e.what());
      continue;
    }
    bus::to_lcmt(u->snapshot, u->msg);
    bus::stamp(u->msg, instance_id_);
    u->msg.user_id = u->user;
    const int bytes = u->msg.getEncodedSize();
    snapshot_bytes_.store(static_cast<size_t>(bytes), std::memory_order_relaxed);
    if (bytes > 65000) {
      spdlog::warn("snapshot for user {} is {} bytes (> one datagram)", u->user, bytes);
    }
    bus_.publish(u->channel, u->msg);
    snapshots_.fetch_add(1, std::memory_order_relaxed);
  }
}

void SimServer::record_trajectory() {
  if (!trajectory_->due(version_, state_->t)) return;
  update_all_body_poses(*model_, *data_, *ad_);
  if (molecule_) {
    molecule_->scene.atom_positions(*data_, trajectory_x_);
  } else {
    trajectory_x_.resize(static_cast<size_t>(model_->nbodies - 1));
    for (int k = 1; k < model_->nbodies; ++k) trajectory_x_[k - 1] = data_->r[k];
  }
  try {
    trajectory_->write(trajectory_x_, version_, state_->t);
  } catch (const std::exception& e) {
    spdlog::error("sim_server: trajectory stopped after {} frames: {}", trajectory_->frames(), e.what());
    trajectory_.reset();
  }
}

// The scene state at the display rate, in chunks spread over the next steps (each chunk's poses
// from its own step, O(chunk) each, from the frontier caches): no step pays for every body.
void SimServer::publish_scene_state(double step_ms) {
  // The header is the state's at its start: every chunk of one state carries the same version, time and
  // active count, so a reader can tell the chunks of one state from the next one's.
  lcmt_scene_state& s = scene_msg_;
  s.version = version_;
  s.sim_time = state_->t;
  s.active_dofs = ad_->report.active_dofs;
  s.neglected_metric = ad_->report.neglected_metric;
  s.step_ms = step_ms;
  s.total_bodies = model_->nbodies;
  scene_chunk_ = 0;
  publish_scene_chunks();
}

void SimServer::publish_scene_chunks() {
  if (scene_chunk_ < 0) return;
  const Model& m = *model_;
  const Data& d = *data_;
  // 56 bytes of pose + 1 of active flag per body: chunks of <= 1000 bodies stay within one 64 KB datagram.
  constexpr int kChunk = 1000;
  const int chunks = (m.nbodies + kChunk - 1) / kChunk;
  // Enough per step to finish well within one display period at the step rate.
  const double steps_per_frame =
      (opt_.rate_hz > 0 ? opt_.rate_hz : 1000.0) / std::max(1e-3, opt_.display_rate_hz);
  const int per_step = std::max(1, static_cast<int>(std::ceil(2.0 * chunks / std::max(1.0, steps_per_frame))));
  lcmt_scene_state& s = scene_msg_;
  bus::stamp(s, instance_id_);
  for (int c = 0; c < per_step && scene_chunk_ < chunks; ++c, ++scene_chunk_) {
    const int first = scene_chunk_ * kChunk;
    const int n = std::min(kChunk, m.nbodies - first);
    s.first_body = first;
    s.nbodies = n;
    s.body_position.resize(n);
    s.body_orientation.resize(n);
    s.body_active.resize(n);
    for (int i = 0; i < n; ++i) {
      const int k = first + i;
      Mat3 R;
      Vec3 r;
      body_pose(d, *ad_, k, R, r);
      s.body_position[i] = {r.x(), r.y(), r.z()};
      const Quat q(R);
      s.body_orientation[i] = {q.w(), q.x(), q.y(), q.z()};
      const int node = k > 0 ? m.tree.owner_of_joint[k] : -1;
      s.body_active[i] = node >= 0 && ad_->active[node] ? 1 : 0;
    }
    bus_.publish(bus::channel::scene_state(opt_.channel_suffix), s);
  }
  if (scene_chunk_ >= chunks) scene_chunk_ = -1;
}

// Every field set: counters from SimServerCounters, latencies from the last step
// and the slowest step of the period.
// Once per stats window: the real-time factor, and one plain-words warning when the requested rate is not
// kept for two windows in a row (the first window, with the start-up, does not count).
void SimServer::check_rate(double steps_per_s, double mean_step_ms, double max_step_ms) {
  last_real_time_factor_ = steps_per_s * opt_.dt;
  last_rate_fraction_ = opt_.rate_hz > 0 ? steps_per_s / opt_.rate_hz : 0.0;
  last_max_step_ms_ = max_step_ms;
  if (opt_.rate_hz <= 0 || warned_rate_) return;
  slow_windows_ = last_rate_fraction_ < 0.9 ? slow_windows_ + 1 : 0;
  if (slow_windows_ < 2) return;
  warned_rate_ = true;
  const bool molecule = molecule_ != nullptr;
  spdlog::warn("sim_server: cannot keep the requested --sim-rate-hz {:.0f}: {:.0f} steps/s in the last second ({:.0f} % "
               "of it); steps took {:.2f} ms on average and up to {:.1f} ms, so simulated time runs at {:.3g} {} "
               "instead of {:.3g}. The haptic loop is unaffected, but the body responds more slowly. Lower "
               "--budget-dofs, use a smaller model, or ask for a lower --sim-rate-hz. (Said once.)",
               opt_.rate_hz, steps_per_s, 100 * last_rate_fraction_, mean_step_ms, max_step_ms,
               last_real_time_factor_, molecule ? "ps of simulated time per second" : "x real time",
               opt_.rate_hz * opt_.dt);
}

void SimServer::publish_stats(double rate_hz) {
  lcmt_process_stats s{};
  bus::stamp(s, instance_id_);
  s.seq = ++stats_seq_;
  s.process_name = "sim_server";
  s.process_id = 0;
  s.loop_rate_hz = rate_hz;
  s.latency_p50_us = step_ms_.load() * 1e3;
  s.latency_p99_us = std::max(max_step_ms_ * 1e3, s.latency_p50_us);
  s.snapshot_age_ms = -1;
  s.messages_in = c_.user_forces_in.load();
  s.messages_out = snapshots_.load();
  s.rejected_messages = bus_.rejected_total() + c_.foreign_rejected.load();
  s.stale_events = c_.stale_rejected.load();
  s.watchdog_events = c_.watchdog_events.load();
  s.clamp_events = c_.clamp_events.load();
  s.nonfinite_events = c_.nonfinite_events.load();
  double gap = 0;
  for (auto& u : users_) gap = std::max(gap, u->max_gap_s), u->max_gap_s = 0;
  // real_time_factor: simulated time per wall-clock second (s/s; ps/s for molecules); rate_fraction: steps/s
  // over the requested --sim-rate-hz (0 if free-running); max_step_ms: the longest step of the last second.
  s.n_extra = 7;
  s.extra_names = {"active_dofs", "snapshot_bytes", "resets", "user_force_gap_max_ms", "real_time_factor",
                   "rate_fraction", "max_step_ms"};
  s.extra_values = {static_cast<double>(active_dofs_.load()), static_cast<double>(snapshot_bytes_.load()),
                    static_cast<double>(resets_.load()), 1e3 * gap, last_real_time_factor_, last_rate_fraction_,
                    last_max_step_ms_};
  bus_.publish(bus::channel::stats("sim_server", opt_.channel_suffix), s);
  max_step_ms_ = 0;
}

int SimServer::run(const std::atomic<bool>& stop) {
  // FTZ/DAZ in the stepping thread: subnormal operands cost Intel CPUs a microcode assist
  // each; under FTZ the DCA pass makes none (snapshots are flushed as well, make_coupling_snapshot).
  const ScopedFlushDenormals ftz;
  c_.ftz_daz.store(ScopedFlushDenormals::active(), std::memory_order_relaxed);
  const auto t0 = Clock::now();
  auto next_display = t0, next_stats = t0 + std::chrono::seconds(1);
  const auto period = opt_.rate_hz > 0 ? std::chrono::duration<double>(1.0 / opt_.rate_hz)
                                       : std::chrono::duration<double>(0);
  auto next_step = t0;
  int64_t steps_at_stats = 0;
  while (!stop.load(std::memory_order_relaxed) && (opt_.steps <= 0 || steps_.load() < opt_.steps)) {
    const auto a = Clock::now();
    step_once();
    if (!just_reset_) publish_snapshots();   // after a reset the coefficients are stale
    if (trajectory_ && !just_reset_) record_trajectory();
    publish_scene_chunks();   // the rest of a scene state, a few chunks per step
    const auto b = Clock::now();
    const double ms = std::chrono::duration<double, std::milli>(b - a).count();
    step_ms_.store(ms, std::memory_order_relaxed);
    max_step_ms_ = std::max(max_step_ms_, ms);
    const int64_t index = steps_.fetch_add(1, std::memory_order_relaxed) + 1;
    if (index > 1 && ms > longest_step_ms_.load(std::memory_order_relaxed)) {
      longest_step_ms_.store(ms, std::memory_order_relaxed);
      longest_step_index_.store(index, std::memory_order_relaxed);
    }
    window_step_ms_sum_ += ms;
    window_step_ms_max_ = std::max(window_step_ms_max_, ms);
    if (opt_.display_rate_hz > 0 && b >= next_display && scene_chunk_ < 0) {
      publish_scene_state(ms);
      next_display = b + std::chrono::duration_cast<Clock::duration>(
                             std::chrono::duration<double>(1.0 / opt_.display_rate_hz));
    }
    if (b >= next_stats) {
      const int64_t window_steps = steps_.load() - steps_at_stats;
      check_rate(static_cast<double>(window_steps), window_steps ? window_step_ms_sum_ / window_steps : 0.0,
                 window_step_ms_max_);
      window_step_ms_sum_ = window_step_ms_max_ = 0;
      publish_stats(static_cast<double>(window_steps));
      steps_at_stats = steps_.load();
      next_stats += std::chrono::seconds(1);
    }
    if (period.count() > 0) {
      next_step += std::chrono::duration_cast<Clock::duration>(period);
      bus::sleep_until_or_stop(next_step, stop);
    } else {
      std::this_thread::yield();
    }
  }
  return 0;
}

}  // namespace haptree
