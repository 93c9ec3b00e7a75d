#include "sim_server/sim_server.hpp"

#include <spdlog/spdlog.h>

#include <chrono>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <thread>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/latest_value.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/dca.hpp"
#include "haptree/io/urdf.hpp"
#include "haptree/lcmt_process_stats.hpp"
#include "haptree/lcmt_scene_state.hpp"
#include "haptree/molecule/scene.hpp"
#include "haptree/molecule/trajectory.hpp"
#include "haptree/scenes.hpp"

namespace haptree {
namespace molecule_fwd {
struct Holder {
  mol::MolecularScene scene;
};
}  // namespace molecule_fwd

using Clock = std::chrono::steady_clock;

struct SimServer::UserSlot {
  int user = 0;
  bus::LatestValue<lcmt_user_force> box;
  lcmt_user_force latest{};
  bool grabbing = false;
  int body = -1;
  Vec3 local_point = Vec3::Zero();
  Vec6 f_u = Vec6::Zero();     // applied force at the grab point (world axes, scene units)
  Grab grab;
  CouplingSnapshot snapshot;
  lcmt_coupling_snapshot msg;
  std::string channel;
};

static bool is_procedural(const std::string& s) {
  return s == "chain" || s == "binary_tree" || s == "random_tree" || s == "star" || s == "protein_like";
}

SimServer::SimServer(bus::Bus& bus, const SimServerOptions& options) : bus_(bus), opt_(options) {
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
    bus_.subscribe_latest<lcmt_user_force>(bus::channel::user_force(u, opt_.channel_suffix), slot->box);
    users_.push_back(std::move(slot));
  }
  forward_kinematics(*model_, *data_, state_->q);
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

void SimServer::step_once() {
  const Model& m = *model_;
  Data& d = *data_;
  State& st = *state_;
  // 1. Latest user forces; a new grab fixes the material point in the body frame.
  bool any_grab = false, grab_changed = false;
  for (auto& u : users_) {
    if (u->box.update()) u->latest = u->box.front();
    const lcmt_user_force& msg = u->latest;
    const bool want = msg.active && msg.grab_body >= 1 && msg.grab_body < m.nbodies;
    if (want != u->grabbing || (want && msg.grab_body != u->body)) grab_changed = true;
    if (want && (!u->grabbing || msg.grab_body != u->body)) {
      u->body = msg.grab_body;
      const Vec3 p(msg.grab_point[0], msg.grab_point[1], msg.grab_point[2]);
      u->local_point = d.R[u->body].transpose() * (p - d.r[u->body]);
    }
    u->grabbing = want;
    if (want) {
      for (int i = 0; i < 6; ++i) u->f_u[i] = msg.force[i];
      if (!u->f_u.allFinite()) u->f_u.setZero();
      any_grab = true;
    } else {
      u->f_u.setZero();
    }
  }
  // 2. Selection: our own, every reselect_every steps, then the grabbed leaves' root paths are forced
  //    active (set_active_region), so each grabbed body is a leaf of the active tree.
  const bool reselect = grab_changed || ad_->steps_since_selection >= std::max(1, opt_.reselect_every);
  if (reselect) {
    if (molecule_) molecule_->scene.force_field->clear_rigid_regions();
    select_active_region(m, d, st, *ad_, adaptive_);
    if (any_grab) {
      active_mask_ = ad_->active;
      for (auto& u : users_) {
        if (!u->grabbing) continue;
        for (int node = m.tree.up[m.tree.leaf_of_body[u->body]]; node >= 0; node = m.tree.up[node])
          active_mask_[node] = 1;
      }
      set_active_region(m, d, st, *ad_, active_mask_);
    }
    if (molecule_) molecule_->scene.force_field->set_rigid_regions(ad_->frontier_of_body);
  }
  // 3. External forces: force field (molecules), then user forces moved to the body origin.
  update_all_body_poses(m, d, *ad_);
  if (molecule_) {
    molecule_->scene.compute(d, st.f_ext);
  } else {
    for (auto& f : st.f_ext) f.setZero();
  }
  for (auto& u : users_) {
    if (!u->grabbing) continue;
    u->grab = make_grab(d, u->body, u->local_point);
    const Vec3 arm = u->grab.point - d.r[u->body];
    Vec6 f0 = u->f_u;
    f0.head<3>() += arm.cross(u->f_u.tail<3>());   // = grab_force_at_body_origin for the same pose
    st.f_ext[u->body] += f0;
  }
  // 4. Step; adaptive_step must not reselect on its own (we did above).
  AdaptiveOptions step_opt = adaptive_;
  step_opt.reselect_every = std::numeric_limits<int>::max();
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
  const double rate = st.qd.size() ? st.qd.cwiseAbs().maxCoeff() : 0.0;
  const bool healthy = st.q.allFinite() && std::isfinite(rate) && rate <= opt_.max_joint_rate;
  if (healthy) {
    if (++steps_since_checkpoint_ >= opt_.checkpoint_every) {
      checkpoint_->q = st.q;
      checkpoint_->t = st.t;
      steps_since_checkpoint_ = 0;
    }
    return false;
  }
  const int64_t n = resets_.fetch_add(1, std::memory_order_relaxed) + 1;
  if (n == 1 || n % 100 == 0)
    spdlog::warn("sim_server: state diverged at t = {:.4g} (max |q̇| {:.3g} > {:.3g} or non-finite); "
                 "restored the checkpoint of t = {:.4g} at rest (reset #{}). Lower --dt or the coupling "
                 "stiffness/damping, or add --budget-dofs headroom.",
                 st.t, rate, opt_.max_joint_rate, checkpoint_->t, n);
  const double t = st.t;
  st.q = checkpoint_->q;
  st.qd.setZero();
  st.t = t;
  forward_kinematics(*model_, *data_, st.q);
  ad_->steps_since_selection = 1 << 30;   // reselect (and rebuild the frontier caches) next step
  steps_since_checkpoint_ = 0;
  ++version_;
  return true;
}

void SimServer::publish_snapshots() {
  const Model& m = *model_;
  Data& d = *data_;
  update_all_body_poses(m, d, *ad_);
  for (auto& u : users_) {
    if (!u->grabbing) continue;
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
    bus::stamp(u->msg);
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

void SimServer::publish_scene_state(double step_ms) {
  const Model& m = *model_;
  const Data& d = *data_;
  lcmt_scene_state s;
  bus::stamp(s);
  s.version = version_;
  s.sim_time = state_->t;
  s.nbodies = m.nbodies;
  s.body_position.resize(m.nbodies);
  s.body_orientation.resize(m.nbodies);
  for (int k = 0; k < m.nbodies; ++k) {
    s.body_position[k] = {d.r[k].x(), d.r[k].y(), d.r[k].z()};
    const Quat q(d.R[k]);
    s.body_orientation[k] = {q.w(), q.x(), q.y(), q.z()};
  }
  s.active_dofs = ad_->report.active_dofs;
  s.neglected_metric = ad_->report.neglected_metric;
  s.step_ms = step_ms;
  bus_.publish(bus::channel::scene_state(opt_.channel_suffix), s);
}

void SimServer::publish_stats(double rate_hz) {
  lcmt_process_stats s;
  bus::stamp(s);
  static int64_t seq = 0;
  s.seq = ++seq;
  s.process_name = "sim_server";
  s.loop_rate_hz = rate_hz;
  s.latency_p50_us = step_ms_.load() * 1e3;
  s.latency_p99_us = s.latency_p50_us;
  s.snapshot_age_ms = -1;
  s.messages_out = snapshots_.load();
  s.rejected_messages = bus_.rejected_total();
  s.n_extra = 3;
  s.extra_names = {"active_dofs", "snapshot_bytes", "resets"};
  s.extra_values = {static_cast<double>(active_dofs_.load()), static_cast<double>(snapshot_bytes_.load()),
                    static_cast<double>(resets_.load())};
  bus_.publish(bus::channel::stats("sim_server", opt_.channel_suffix), s);
}

int SimServer::run(const std::atomic<bool>& stop) {
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
    const auto b = Clock::now();
    const double ms = std::chrono::duration<double, std::milli>(b - a).count();
    step_ms_.store(ms, std::memory_order_relaxed);
    steps_.fetch_add(1, std::memory_order_relaxed);
    if (opt_.display_rate_hz > 0 && b >= next_display) {
      publish_scene_state(ms);
      next_display = b + std::chrono::duration_cast<Clock::duration>(
                             std::chrono::duration<double>(1.0 / opt_.display_rate_hz));
    }
    if (b >= next_stats) {
      publish_stats(static_cast<double>(steps_.load() - steps_at_stats));
      steps_at_stats = steps_.load();
      next_stats += std::chrono::seconds(1);
    }
    if (period.count() > 0) {
      next_step += std::chrono::duration_cast<Clock::duration>(period);
      std::this_thread::sleep_until(next_step);
    } else {
      std::this_thread::yield();
    }
  }
  return 0;
}

}  // namespace haptree
