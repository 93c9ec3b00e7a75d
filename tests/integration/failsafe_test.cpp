// Fail-safe behaviour of the bus/safety layer under stale, duplicate, foreign and implausible messages, on one memq://
// Bus with hand-made messages where a fault has to be injected precisely: the server's watchdog on user
// forces, its clamps and stats, the coupler's instance-id restart rule, its refusal of foreign/duplicate/
// implausible producers and absurd device positions, and one writer per device FEEDBACK channel.
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <mutex>
#include <thread>
#include <vector>

#include "coupler/coupler.hpp"
#include "device_bridge/device_bridge.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/dca.hpp"
#include "haptree/fp_env.hpp"
#include "haptree/lcmt_process_stats.hpp"
#include "haptree/lcmt_scene_state.hpp"
#include "haptree/scenes.hpp"
#include "sim_server/sim_server.hpp"

namespace haptree {
namespace {

using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;

lcmt_user_force user_force(int64_t instance, int64_t seq, int body, double fx) {
  lcmt_user_force m{};
  bus::stamp(m, instance);
  m.seq = seq;
  m.user_id = 0;
  m.grab_body = body;
  m.force[3] = fx;
  m.snapshot_version = -1;
  m.active = true;
  return m;
}

SimServerOptions small_server() {
  SimServerOptions so;
  so.scene = "chain";
  so.n = 8;
  so.rate_hz = 1000;
  so.gravity = Vec3::Zero();
  so.display_rate_hz = 0;
  return so;
}

// Defect 2: one USER_FORCE and nothing else must not pull forever. The server's watchdog ramps it to zero
// (a ramp, not a step) once no USER_FORCE arrived for user_force_stale_s, and counts one trip.
TEST(Failsafe, ServerRampsAStaleUserForceToZero) {
  bus::Bus bus("memq://");
  SimServerOptions so = small_server();
  SimServer server(bus, so);
  bus::HandlerThread handler(bus, 2);
  std::atomic<bool> stop{false};
  std::thread t([&] { server.run(stop); });
  // A coupler that is not grabbing sends inactive USER_FORCE at 1 kHz (the server's watchdog is fresh),
  // then one active message, then dies.
  int64_t seq = 0;
  for (int i = 0; i < 200; ++i) {
    lcmt_user_force idle = user_force(42, ++seq, 0, 0.0);
    idle.active = false;
    bus.publish(bus::channel::user_force(0), idle);
    std::this_thread::sleep_for(1ms);
  }
  const double f0 = 5.0;   // below the scene-side limit (12): not clamped
  bus.publish(bus::channel::user_force(0), user_force(42, ++seq, 8, f0));
  const auto t_pub = Clock::now();
  std::vector<std::pair<double, double>> samples;   // (ms since the message, applied |f|)
  while (Clock::now() - t_pub < 400ms) {
    samples.push_back({std::chrono::duration<double, std::milli>(Clock::now() - t_pub).count(),
                       server.applied_user_force_norm(0)});
    std::this_thread::sleep_for(200us);
  }
  stop = true;
  t.join();
  handler.stop();
  double t_full = -1, t_zero = -1;
  int64_t partial = 0;
  for (const auto& [ms, f] : samples) {
    if (f == f0 && t_full < 0) t_full = ms;
    if (t_full >= 0 && f > 0 && f < f0) ++partial;
    if (t_full >= 0 && f == 0 && t_zero < 0) t_zero = ms;
  }
  std::printf("user force %.1f applied from %.1f ms, exactly zero from %.1f ms after the only message "
              "(stale %.0f ms + ramp %.0f ms), %lld samples on the ramp; watchdog events %lld\n",
              f0, t_full, t_zero, 1e3 * so.user_force_stale_s, 1e3 * so.user_force_ramp_s,
              static_cast<long long>(partial), static_cast<long long>(server.counters().watchdog_events.load()));
  ASSERT_GE(t_full, 0) << "the user force was never applied";
  ASSERT_GE(t_zero, 0) << "the user force was still applied 400 ms after the only USER_FORCE";
  // Not before the stale time (the last sample at full force is after it), and a ramp in between.
  EXPECT_GE(t_zero, 1e3 * so.user_force_stale_s);
  EXPECT_GT(partial, 0) << "the force dropped in one step instead of a ramp";
  EXPECT_EQ(server.applied_user_force(0), Vec6::Zero());
  EXPECT_EQ(server.counters().watchdog_events.load(), 1);
}

// Defects 5 (server side) and 6: non-finite and absurd user forces are zeroed / clamped and counted,
// older and foreign messages are refused and counted, and every counter of the stats message is set
// to exactly what happened (they used to carry stack and heap addresses).
TEST(Failsafe, ServerClampsUserForcesAndItsStatsCarryEveryCounter) {
  bus::Bus bus("memq://");
  SimServerOptions so = small_server();
  SimServer server(bus, so);
  std::mutex mu;
  std::vector<lcmt_process_stats> stats;
  bus.subscribe<lcmt_process_stats>(bus::channel::stats("sim_server"), [&](const lcmt_process_stats& m, const std::string&) {
    std::lock_guard<std::mutex> l(mu);
    stats.push_back(m);
  });
  bus::HandlerThread handler(bus, 2);
  std::atomic<bool> stop{false};
  std::thread t([&] { server.run(stop); });
  std::atomic<double> max_applied{0};
  std::atomic<bool> sampling{true};
  std::thread sampler([&] {
    while (sampling) {
      const double f = server.applied_user_force_norm(0);
      if (!(f <= max_applied)) max_applied = f;   // NaN stays visible
      std::this_thread::sleep_for(100us);
    }
  });
  const double nan = std::numeric_limits<double>::quiet_NaN();
  auto send = [&](const lcmt_user_force& m) {
    bus.publish(bus::channel::user_force(0), m);
    std::this_thread::sleep_for(20ms);   // > one step: the server takes each one
  };
  // a coupler that is not grabbing yet: inactive USER_FORCE at 1 kHz for 200 ms (the watchdog gain is 1)
  for (int i = 0; i < 200; ++i) {
    lcmt_user_force idle = user_force(42, 1 + i, 0, 0.0);
    idle.active = false;
    bus.publish(bus::channel::user_force(0), idle);
    std::this_thread::sleep_for(1ms);
  }
  send(user_force(42, 201, 8, 5.0));     // accepted
  send(user_force(42, 202, 8, nan));     // accepted, zeroed: nonfinite_events
  send(user_force(42, 203, 8, 1e300));   // accepted, clamped to max_user_force: clamp_events
  send(user_force(42, 202, 8, 5.0));     // older seq of the same coupler: stale_events
  send(user_force(99, 10, 8, 5.0));    // a second coupler while 42 is live: rejected_messages
  std::this_thread::sleep_for(1300ms);  // the first stats message is published 1 s after start
  stop = true;
  t.join();
  sampling = false;
  sampler.join();
  handler.stop();
  std::lock_guard<std::mutex> l(mu);
  ASSERT_FALSE(stats.empty());
  const lcmt_process_stats& s = stats.back();
  std::printf("stats: in %lld out %lld rejected %lld stale %lld watchdog %lld clamp %lld nonfinite %lld, rate %.0f "
              "Hz, step %.3f/%.3f ms; max applied |f| %.3g (limit %.3g)\n",
              static_cast<long long>(s.messages_in), static_cast<long long>(s.messages_out),
              static_cast<long long>(s.rejected_messages), static_cast<long long>(s.stale_events),
              static_cast<long long>(s.watchdog_events), static_cast<long long>(s.clamp_events),
              static_cast<long long>(s.nonfinite_events), s.loop_rate_hz, 1e-3 * s.latency_p50_us,
              1e-3 * s.latency_p99_us, max_applied.load(), so.max_user_force);
  EXPECT_EQ(s.process_name, "sim_server");
  EXPECT_EQ(s.instance_id, server.instance_id());
  EXPECT_NE(s.instance_id, 0);
  EXPECT_EQ(s.messages_in, 203);
  EXPECT_EQ(s.stale_events, 1);
  EXPECT_EQ(s.rejected_messages, 1);
  EXPECT_EQ(s.nonfinite_events, 1);
  EXPECT_EQ(s.clamp_events, 1);
  EXPECT_EQ(s.watchdog_events, 1);   // the last accepted force went stale once
  EXPECT_GE(s.messages_out, 0);
  EXPECT_LE(s.messages_out, server.steps_done());
  EXPECT_GT(s.loop_rate_hz, 0);
  EXPECT_LE(s.loop_rate_hz, 2 * so.rate_hz);
  EXPECT_GE(s.latency_p99_us, s.latency_p50_us);
  EXPECT_EQ(s.snapshot_age_ms, -1);
  EXPECT_EQ(s.n_extra, static_cast<int32_t>(s.extra_names.size()));
  // the clamped 1e300 was applied at the limit (not zeroed by an overflowing norm), never above it
  EXPECT_NEAR(max_applied.load(), so.max_user_force, 1e-9 * so.max_user_force);
  EXPECT_EQ(server.resets(), 0);
}

// A model, a coupling snapshot of its last body, and a sender of snapshots with any origin.
struct FakeServer {
  explicit FakeServer(bus::Bus& b) : bus(b) {
    SceneOptions so;
    so.n = 8;
    so.gravity = Vec3::Zero();
    model = make_chain(so);
    Data d(*model);
    State st(*model);
    forward_dynamics(*model, d, st);
    make_coupling_snapshot(*model, d, {make_grab(d, 8, Vec3::Zero())}, {Vec6::Zero()}, 0, 0.0, snap);
  }
  void send(int64_t instance, int64_t version, uint64_t fp = 0) {
    snap.model_fingerprint = fp ? fp : model->fingerprint;
    snap.version = version;
    lcmt_coupling_snapshot m;
    bus::to_lcmt(snap, m);
    bus::stamp(m, instance);
    bus.publish(bus::channel::coeffs(0), m);
  }
  bus::Bus& bus;
  std::shared_ptr<const Model> model;
  CouplingSnapshot snap;
};

// Defect 3 (and the version checks of defect 4): a late, reordered snapshot of the live server is not
// a restart, however long the stream was quiet; a new server instance after the silence is; a second
// instance while one is live, and a version jump no server can make, are refused.
TEST(Failsafe, CouplerTellsARestartFromReorderingByInstanceId) {
  bus::Bus bus("memq://");
  CouplerOptions co;
  co.stale_after_s = 0.005;   // the old default: tight, so the reordered snapshot arrives "after silence"
  Coupler coupler(bus, co);
  bus::HandlerThread handler(bus, 2);
  FakeServer srv(bus);
  const auto& c = coupler.counters();
  auto settle = [] { std::this_thread::sleep_for(30ms); };   // > stale_after_s
  for (int v = 10; v <= 12; ++v) srv.send(1001, v);
  settle();
  srv.send(1001, 5);   // a reordered datagram of the same server, after 30 ms of silence
  settle();
  EXPECT_EQ(c.restarts.load(), 0) << "a reordered snapshot was taken for a server restart";
  EXPECT_EQ(c.stale_rejected.load(), 1);
  EXPECT_EQ(c.snapshots_accepted.load(), 3);
  srv.send(2002, 1);   // a new server instance (its step counter starts again) after the silence
  srv.send(2002, 2);
  srv.send(1001, 13);  // the old instance again, while the new one is live: refused
  srv.send(2002, 5'000'000'000'000);   // a replayed/corrupted version far beyond what 1 ms allows
  srv.send(2002, 3);
  settle();
  handler.stop();
  std::printf("restarts %lld, accepted %lld, stale %lld, duplicate %lld, implausible %lld\n",
              static_cast<long long>(c.restarts.load()), static_cast<long long>(c.snapshots_accepted.load()),
              static_cast<long long>(c.stale_rejected.load()), static_cast<long long>(c.duplicate_rejected.load()),
              static_cast<long long>(c.implausible_rejected.load()));
  EXPECT_EQ(c.restarts.load(), 1);
  EXPECT_EQ(c.snapshots_accepted.load(), 6);   // 10, 11, 12, then 1, 2, 3 of the new server
  EXPECT_EQ(c.version_in_use.load(), -1);      // the loop never ran: nothing swapped in
  EXPECT_EQ(c.implausible_rejected.load(), 1);
  // The old instance's message is a late one of the previous server (stale), not a second live server.
  EXPECT_EQ(c.stale_rejected.load() + c.duplicate_rejected.load(), 2);
}

// Defect 4: a named model refuses a foreign server that starts first; a second live server instance
// is refused.
TEST(Failsafe, CouplerWithExpectedFingerprintRefusesAForeignServerThatStartsFirst) {
  bus::Bus bus("memq://");
  FakeServer srv(bus);
  CouplerOptions co;
  co.stale_after_s = 0.05;
  co.model_fingerprint = srv.model->fingerprint;
  Coupler coupler(bus, co);
  bus::HandlerThread handler(bus, 2);
  const auto& c = coupler.counters();
  for (int v = 1; v <= 5; ++v) srv.send(3003, v, srv.model->fingerprint ^ 0x5a5a);   // foreign model, first
  std::this_thread::sleep_for(20ms);
  for (int v = 1; v <= 5; ++v) srv.send(4004, v);                                    // the expected model
  for (int v = 100; v <= 102; ++v) srv.send(5005, v);   // another live instance of the same model
  std::this_thread::sleep_for(20ms);
  handler.stop();
  EXPECT_EQ(c.foreign_rejected.load(), 5);
  EXPECT_EQ(c.snapshots_accepted.load(), 5);
  EXPECT_EQ(c.duplicate_rejected.load(), 3);
  EXPECT_EQ(c.restarts.load(), 0);
}

// A fake device: DEVICE_STATE at ~1 kHz from one instance, position and buttons settable.
struct FakeDevice {
  FakeDevice(bus::Bus& b, int64_t inst) : bus(b), instance(inst) {}
  void start() {
    th = std::thread([this] {
      while (!stop) {
        publish_one(instance, position.load(), 1);
        std::this_thread::sleep_for(1ms);
      }
    });
  }
  void halt() {
    stop = true;
    if (th.joinable()) th.join();
  }
  ~FakeDevice() { halt(); }
  void publish_one(int64_t inst, double x, int32_t buttons) {
    lcmt_device_state m{};
    bus::stamp(m, inst);
    m.seq = ++seq;
    m.device_id = 0;
    m.position_m[0] = x;
    m.position_m[2] = 0.0;
    m.orientation[0] = 1;
    m.buttons = buttons;
    bus.publish(bus::channel::device_state(0), m);
  }
  bus::Bus& bus;
  int64_t instance;
  std::atomic<double> position{0.0};
  std::atomic<int64_t> seq{0};
  std::atomic<bool> stop{false};
  std::thread th;
};

struct CouplerRig {
  explicit CouplerRig(double stale_after_s = 0.05) : bus("memq://"), srv(bus) {
    co.stale_after_s = stale_after_s;
    co.grab_body = 8;
    co.busy_wait = false;
    co.rate_hz = 4000;
    co.offset = srv.snap.grabs[0].point;   // device origin maps onto the grab point: zero spring force
    coupler = std::make_unique<Coupler>(bus, co);
    bus.subscribe<lcmt_user_force>(bus::channel::user_force(0), [this](const lcmt_user_force& m, const std::string&) {
      std::lock_guard<std::mutex> l(mu);
      forces.push_back(m);
    });
  }
  void start() {
    handler = std::make_unique<bus::HandlerThread>(bus, 2);
    snap_thread = std::thread([this] {
      for (int64_t v = 1; !stop; ++v) {
        if (serving) srv.send(7007, v);
        std::this_thread::sleep_for(1ms);
      }
    });
    loop = std::thread([this] { coupler->run(stop); });
  }
  void finish() {
    stop = true;
    if (loop.joinable()) loop.join();
    if (snap_thread.joinable()) snap_thread.join();
    if (handler) handler->stop();
  }
  ~CouplerRig() { finish(); }
  bus::Bus bus;
  FakeServer srv;
  CouplerOptions co;
  std::unique_ptr<Coupler> coupler;
  std::mutex mu;
  std::vector<lcmt_user_force> forces;
  std::unique_ptr<bus::HandlerThread> handler;
  std::atomic<bool> stop{false}, serving{true};   // serving: the fake server sends snapshots (it holds a grab)
  std::thread snap_thread, loop;
};

// Defect found by the chaos soak (docs/chaos.md, "grab on a stale snapshot"): after a release the server
// sends no snapshots, so the coupler still holds the last one of the old grab. A new grab of the same body
// elsewhere used it with the old grab point: a spring force at once (here the 3 N clamp) instead of zero,
// a step of up to the clamp in FEEDBACK until the watchdog took it away 5 ms later. Now a grab waits for a
// snapshot newer than the one in hand at its edge; until then its force is zero.
TEST(Failsafe, ANewGrabDoesNotUseTheSnapshotOfTheOldOne) {
  CouplerRig rig;
  std::mutex fb_mu;
  std::vector<lcmt_feedback> fbs;
  rig.bus.subscribe<lcmt_feedback>(bus::channel::feedback(0), [&](const lcmt_feedback& m, const std::string&) {
    std::lock_guard<std::mutex> l(fb_mu);
    fbs.push_back(m);
  });
  FakeDevice dev(rig.bus, 8008);
  std::atomic<double> x{0.0};
  std::atomic<int32_t> buttons{1};
  std::atomic<bool> dev_stop{false};
  std::thread dev_thread([&] {
    while (!dev_stop) {
      dev.publish_one(8008, x.load(), buttons.load());
      std::this_thread::sleep_for(1ms);
    }
  });
  rig.start();
  std::this_thread::sleep_for(300ms);   // grabbed at the snapshot's grab point: zero force, ramped in
  buttons = 0;                          // release: the server stops sending snapshots
  std::this_thread::sleep_for(50ms);
  rig.serving = false;
  std::this_thread::sleep_for(50ms);
  x = 0.05;                             // 0.5 scene units away: k_s 20 x 0.5 x 0.5 N/unit = 5 N > clamp 3 N
  std::this_thread::sleep_for(20ms);
  size_t at_press = 0;
  {
    std::lock_guard<std::mutex> l(fb_mu);
    at_press = fbs.size();
  }
  buttons = 1;                          // a new grab of body 8 (--grab-body) at the new device point
  std::this_thread::sleep_for(100ms);   // no snapshot for it yet: its force must stay zero
  dev_stop = true;
  dev_thread.join();
  rig.finish();
  double fmax = 0;
  int64_t with_version = 0, after = 0;
  {
    std::lock_guard<std::mutex> l(fb_mu);
    for (size_t i = at_press; i < fbs.size(); ++i, ++after) {
      fmax = std::max(fmax, Vec3(fbs[i].force_n[0], fbs[i].force_n[1], fbs[i].force_n[2]).norm());
      with_version += fbs[i].snapshot_version >= 0;
    }
  }
  std::printf("after the new grab: %lld FEEDBACK, %lld naming a snapshot, max |f| %.3g N\n",
              static_cast<long long>(after), static_cast<long long>(with_version), fmax);
  EXPECT_GT(after, 0);
  EXPECT_EQ(with_version, 0) << "the new grab used the old grab's snapshot";
  EXPECT_EQ(fmax, 0.0);   // exactly: no snapshot, no force
}

// Defect 5 (coupler side): a device position of 1e300 (or NaN) is refused rather than turned into a
// 2e302 user force, and a large but plausible displacement gives at most the scene-side limit
// 2 x max_force_n / force_scale.
TEST(Failsafe, CouplerRefusesAbsurdDevicePositionsAndClampsTheUserForce) {
  CouplerRig rig;
  FakeDevice dev(rig.bus, 8008);
  rig.start();
  dev.start();
  std::this_thread::sleep_for(300ms);   // grabbed, watchdog ramped in
  dev.position = 0.5;                    // 5 scene m from the grab point: k_s x 5 = 100 > limit 12
  std::this_thread::sleep_for(100ms);
  dev.halt();
  dev.publish_one(8008, 1e300, 1);       // a glitch
  std::this_thread::sleep_for(5ms);
  dev.publish_one(8008, std::numeric_limits<double>::quiet_NaN(), 1);
  std::this_thread::sleep_for(50ms);
  rig.finish();
  const double limit = user_force_limit(rig.co);
  double fmax = 0;
  bool finite = true;
  {
    std::lock_guard<std::mutex> l(rig.mu);
    for (const auto& m : rig.forces) {
      const Vec3 f(m.force[3], m.force[4], m.force[5]);
      finite &= f.allFinite();
      if (f.allFinite()) fmax = std::max(fmax, f.norm());
    }
  }
  const auto& c = rig.coupler->counters();
  std::printf("user force: max %.6g scene units (limit %.6g = 2 x %.1f N / %.2f N per unit), pose_rejected %lld, "
              "clamps %lld\n",
              fmax, limit, rig.co.max_force_n, rig.co.force_scale, static_cast<long long>(c.pose_rejected.load()),
              static_cast<long long>(c.user_force_clamps.load()));
  EXPECT_TRUE(finite);
  EXPECT_LE(fmax, limit * (1 + 1e-12));
  EXPECT_GE(fmax, limit * (1 - 1e-9)) << "the plausible large pull must reach the clamp";
  EXPECT_GE(c.user_force_clamps.load(), 1);
  EXPECT_EQ(c.pose_rejected.load(), 2);
}

// Defect 4: a DEVICE_STATE with the button up from another instance, while the device is live, does
// not release the grab; a new device instance after the old one went silent is followed (restart).
TEST(Failsafe, StrayDeviceStateCannotReleaseTheGrabButADeviceRestartWorks) {
  CouplerRig rig;
  FakeDevice dev(rig.bus, 8008);
  rig.start();
  dev.start();
  std::this_thread::sleep_for(200ms);
  dev.publish_one(6666, 0.0, 0);   // stray: button up, newer seq, another instance
  std::this_thread::sleep_for(30ms);
  dev.halt();
  std::this_thread::sleep_for(120ms);   // > stale_after_s: the device is silent
  FakeDevice dev2(rig.bus, 9009);       // the device_bridge restarted
  dev2.start();
  std::this_thread::sleep_for(200ms);
  dev2.halt();
  rig.finish();
  const auto& c = rig.coupler->counters();
  int64_t released_after_grab = 0, active = 0;
  bool grabbed = false;
  {
    std::lock_guard<std::mutex> l(rig.mu);
    for (const auto& m : rig.forces) {
      if (m.active) grabbed = true, ++active;
      else if (grabbed) ++released_after_grab;
    }
  }
  std::printf("USER_FORCE: %lld active, %lld released after the grab; pose_rejected %lld, device_restarts %lld\n",
              static_cast<long long>(active), static_cast<long long>(released_after_grab),
              static_cast<long long>(c.pose_rejected.load()), static_cast<long long>(c.device_restarts.load()));
  EXPECT_TRUE(grabbed);
  EXPECT_EQ(released_after_grab, 0) << "a stray DEVICE_STATE released the user's grab";
  EXPECT_EQ(c.pose_rejected.load(), 1);
  EXPECT_EQ(c.device_restarts.load(), 1);
}

// Defect 4: two couplers writing one device's FEEDBACK. The device_bridge follows the first one and
// refuses the other (it used to render both, alternating); when the followed one goes silent for the
// feedback timeout, the other is taken over (a coupler restart).
TEST(Failsafe, DeviceBridgeFollowsOneCouplerPerFeedbackChannel) {
  bus::Bus bus("memq://");
  DeviceBridgeOptions bo;
  bo.kind = "scripted";
  bo.feedback_timeout_s = 0.05;
  bo.max_force_n = 3.0;
  DeviceBridge bridge(bus, bo);
  bus::HandlerThread handler(bus, 2);
  std::atomic<bool> stop{false};
  std::thread loop([&] { bridge.run(stop); });
  auto writer = [&](int64_t inst, double fx, std::atomic<bool>& quit) {
    int64_t seq = 0;
    while (!quit) {
      lcmt_feedback f{};
      bus::stamp(f, inst);
      f.seq = ++seq;
      f.force_n[0] = fx;
      bus.publish(bus::channel::feedback(0), f);
      std::this_thread::sleep_for(500us);
    }
  };
  std::atomic<bool> quit_a{false}, quit_b{false};
  std::thread a([&] { writer(111, 1.0, quit_a); });
  std::this_thread::sleep_for(50ms);
  std::thread b([&] { writer(222, 2.0, quit_b); });
  std::this_thread::sleep_for(300ms);
  const double max_while_both = bridge.max_force_seen_n();
  const int64_t refused = bridge.feedback_refused();
  quit_a = true;
  a.join();
  std::this_thread::sleep_for(300ms);   // > feedback_timeout_s: the second coupler takes over
  const double max_after = bridge.max_force_seen_n();
  quit_b = true;
  b.join();
  stop = true;
  loop.join();
  handler.stop();
  std::printf("device: max |f| %.3f N while two couplers wrote (refused %lld), %.3f N after the first stopped "
              "(takeovers %lld)\n",
              max_while_both, static_cast<long long>(refused), max_after,
              static_cast<long long>(bridge.coupler_takeovers()));
  EXPECT_EQ(max_while_both, 1.0) << "the device rendered the second coupler's force";
  EXPECT_GT(refused, 100);
  EXPECT_EQ(max_after, 2.0);
  EXPECT_EQ(bridge.coupler_takeovers(), 1);
}

// Over LCM: two couplers on one device's FEEDBACK channel. Over shm the coupler reads its
// segment's writer; over LCM it watches the channel: another live instance's FEEDBACK is counted (and warned
// about once from the stats tick), its own echoes and replays of old messages are not.
TEST(Failsafe, CouplerOverLcmNoticesASecondCouplerOnItsDevice) {
  bus::Bus bus("memq://");
  CouplerOptions co;
  co.grab_body = 1;
  Coupler coupler(bus, co);
  bus::HandlerThread handler(bus, 2);
  auto publish = [&](int64_t inst, int64_t utime) {
    lcmt_feedback f{};
    bus::stamp(f, inst, utime);
    f.seq = 1;
    bus.publish(bus::channel::feedback(0), f);
  };
  for (int i = 0; i < 20; ++i) publish(coupler.instance_id(), bus::now_utime());            // its own
  for (int i = 0; i < 20; ++i) publish(333, bus::now_utime() - 3600LL * 1000000);           // a replay
  std::this_thread::sleep_for(100ms);
  const int64_t before = coupler.counters().other_feedback_writer.load();
  for (int i = 0; i < 5; ++i) publish(333, bus::now_utime());                               // a second coupler
  std::this_thread::sleep_for(100ms);
  const int64_t after = coupler.counters().other_feedback_writer.load();
  handler.stop();
  EXPECT_EQ(before, 0);
  EXPECT_EQ(after, 5);
}

}  // namespace
}  // namespace haptree

namespace haptree {
namespace {

// The check above must not wake the handler thread for each of the coupler's own FEEDBACK
// messages. While run() loops, the channel is delivered only in a kWriterCheckWindow_s (20 ms) window after
// each stats tick: over ~2.3 s (3 windows, 60 ms) the subscription sees a few % of the coupler's own messages
// (bound 20 %: windows that a loaded machine stretches), and a second writer publishing all along is still
// seen. Before the window, every own message reached the handler (received ≈ published).
TEST(Failsafe, CouplerChecksItsFeedbackChannelForASecondWriterInWindowsOnly) {
  bus::Bus bus("memq://");
  CouplerOptions co;
  co.grab_body = 1;
  co.rate_hz = 2000;
  co.busy_wait = false;
  Coupler coupler(bus, co);
  const bus::SubscriptionBase* check = nullptr;
  for (const auto* s : bus.subscriptions())
    if (s->channel() == bus::channel::feedback(0)) check = s;
  ASSERT_NE(check, nullptr);
  bus::HandlerThread handler(bus, 2);
  std::atomic<bool> stop{false};
  std::thread loop([&] { coupler.run(stop); });
  std::thread other([&] {   // a second coupler on the same device, at 500 Hz
    for (int64_t seq = 1; !stop; ++seq) {
      lcmt_feedback f{};
      bus::stamp(f, 333);
      f.seq = seq;
      bus.publish(bus::channel::feedback(0), f);
      std::this_thread::sleep_for(2ms);
    }
  });
  std::this_thread::sleep_for(2300ms);
  stop = true;
  loop.join();
  other.join();
  handler.stop();
  const int64_t own = coupler.counters().iterations.load(), received = check->stats().received.load();
  std::printf("own FEEDBACK published %lld, delivered to the writer check %lld (with the other writer's); "
              "other-writer messages counted %lld\n", static_cast<long long>(own), static_cast<long long>(received),
              static_cast<long long>(coupler.counters().other_feedback_writer.load()));
  ASSERT_GT(own, 1000);
  EXPECT_LT(received, own / 5);
  EXPECT_GT(coupler.counters().other_feedback_writer.load(), 0);
}

// A snapshot that holds subnormal values (a producer other than sim_server, e.g. Python) has
// them set to 0 on arrival, counted; the coupler's loop computes with FTZ/DAZ on.
TEST(Failsafe, CouplerFlushesSubnormalsOfIncomingSnapshots) {
  bus::Bus bus("memq://");
  CouplerOptions co;
  co.rate_hz = 1000;
  co.busy_wait = false;
  Coupler coupler(bus, co);
  bus::HandlerThread handler(bus, 2);
  FakeServer srv(bus);
  int planted = 0;
  for (double& v : srv.snap.values)   // zeros of the blocks become the smallest subnormals, ± (7 of them)
    if (v == 0.0 && planted < 7) v = (planted++ % 2 ? -1 : 1) * std::numeric_limits<double>::denorm_min();
  ASSERT_EQ(planted, 7);
  ASSERT_EQ(count_subnormals(srv.snap.values.data(), srv.snap.values.size()), 7u);
  std::atomic<bool> stop{false};
  std::thread loop([&] { coupler.run(stop); });
  srv.send(7007, 1);
  for (int i = 0; i < 200 && coupler.counters().snapshots_accepted.load() == 0; ++i) std::this_thread::sleep_for(5ms);
  std::this_thread::sleep_for(20ms);
  stop = true;
  loop.join();
  handler.stop();
  EXPECT_EQ(coupler.counters().snapshots_accepted.load(), 1);
  EXPECT_EQ(coupler.counters().subnormals_flushed.load(), 7);
#ifdef HAPTREE_HAVE_MXCSR
  EXPECT_TRUE(coupler.counters().ftz_daz.load());
  EXPECT_FALSE(ScopedFlushDenormals::active()) << "the test thread's mode changed";
#endif
}

// A press (button 0, the coupler picking: --grab-body -1) takes the body nearest to the device point
// only within --grab-radius of it: a hardware device's stylus must be near a body to grab it.
TEST(Failsafe, GrabTakesTheNearestBodyOnlyWithinTheGrabRadius) {
  // Bodies 1 at the scene origin and 2 at x = 5; position scale 10: device x = 0.05 m is scene 0.5
  // (body 1 within a radius of 1), device x = 0.25 m is scene 2.5 (2.5 from both: nothing).
  for (const double device_x : {0.05, 0.25}) {
    bus::Bus bus("memq://");
    CouplerOptions co;
    co.busy_wait = false;
    co.rate_hz = 4000;
    co.grab_body = -1;
    co.grab_radius = 1.0;
    Coupler coupler(bus, co);
    std::mutex mu;
    int32_t last_grab_body = -1;
    bus.subscribe<lcmt_user_force>(bus::channel::user_force(0), [&](const lcmt_user_force& m, const std::string&) {
      std::lock_guard<std::mutex> l(mu);
      last_grab_body = m.grab_body;
    });
    bus::HandlerThread handler(bus, 2);
    std::atomic<bool> stop{false};
    std::thread loop([&] { coupler.run(stop); });
    lcmt_scene_state scene{};
    bus::stamp(scene, 5151);
    scene.nbodies = 2;
    scene.first_body = 1;
    scene.total_bodies = 3;
    scene.body_position = {{0, 0, 0}, {5, 0, 0}};
    scene.body_orientation = {{1, 0, 0, 0}, {1, 0, 0, 0}};
    scene.body_active = {1, 1};
    bus.publish(bus::channel::scene_state(), scene);
    FakeDevice dev(bus, 6161);
    for (int i = 0; i < 200; ++i) {   // 200 ms of poses with the grab button held
      dev.publish_one(6161, device_x, 1);
      std::this_thread::sleep_for(1ms);
    }
    stop = true;
    loop.join();
    handler.stop();
    std::lock_guard<std::mutex> l(mu);
    EXPECT_EQ(last_grab_body, device_x < 0.1 ? 1 : 0) << "device x " << device_x << " m";
  }
}

}  // namespace
}  // namespace haptree
