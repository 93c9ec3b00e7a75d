// Embedded integration: sim_server + coupler + device_bridge classes in threads over one memq:// Bus.
#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <mutex>
#include <random>
#include <thread>
#include <vector>

#include "coupler/coupler.hpp"
#include "device_bridge/device_bridge.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/dca.hpp"
#include "haptree/fp_env.hpp"
#include "haptree/safety.hpp"
#include "haptree/scenes.hpp"
#include "sim_server/sim_server.hpp"
#include "tests/integration/log_recorder.hpp"

namespace haptree {
namespace {

using namespace std::chrono_literals;

struct FeedbackLog {
  std::mutex mu;
  std::vector<lcmt_feedback> msgs;
};

struct Session {
  explicit Session(int users, double hold_s = 3.0, double stale_after_s = 0.05) : bus("memq://") {
    so.scene = "protein_like";
    so.n = 32;
    so.rate_hz = 1000;
    so.users = users;
    server = std::make_unique<SimServer>(bus, so);
    const Model& m = server->model();
    Data d0(m);
    State s0(m);
    forward_kinematics(m, d0, s0.q);
    for (int u = 0; u < users; ++u) {
      const int b = (m.nbodies - 1) - u * (m.nbodies - 1) / (users + 1);
      bodies.push_back(b);
      CouplerOptions co;
      co.user = u;
      co.device = u;
      co.rate_hz = 4000;
      co.busy_wait = false;
      co.grab_body = b;
      co.offset = d0.r[b] - co.position_scale * Vec3(0, 0, 0.01);
      co.stale_after_s = stale_after_s;
      copts.push_back(co);
      couplers.push_back(std::make_unique<Coupler>(bus, co));
      DeviceBridgeOptions bo;
      bo.device = u;
      bo.options = {{"approach_s", "0.1"}, {"settle_s", "0.05"}, {"pull_s", "0.4"}, {"hold_s", std::to_string(hold_s)},
                    {"pull_direction", u % 2 ? "0,1,0" : "1,0,0"}};
      bo.feedback_timeout_s = 0.05;
      bridges.push_back(std::make_unique<DeviceBridge>(bus, bo));
      bus.subscribe<lcmt_feedback>(bus::channel::feedback(u), [this, u](const lcmt_feedback& f, const std::string&) {
        std::lock_guard<std::mutex> lock(logs[u].mu);
        logs[u].msgs.push_back(f);
      });
    }
  }
  void start() {
    handler = std::make_unique<bus::HandlerThread>(bus, 5);
    server_thread = std::thread([this] { server->run(stop_server); });
    for (auto& c : couplers) threads.emplace_back([this, p = c.get()] { p->run(stop); });
    for (auto& b : bridges) threads.emplace_back([this, p = b.get()] { p->run(stop); });
  }
  void stop_all() {
    stop_server = true;
    stop = true;
    if (server_thread.joinable()) server_thread.join();
    for (auto& t : threads) t.join();
    threads.clear();
    if (handler) handler->stop();
  }
  ~Session() { stop_all(); }
  double max_force(int u) {
    std::lock_guard<std::mutex> lock(logs[u].mu);
    double m = 0;
    for (const auto& f : logs[u].msgs) m = std::max(m, Vec3(f.force_n[0], f.force_n[1], f.force_n[2]).norm());
    return m;
  }

  bus::Bus bus;
  SimServerOptions so;
  std::unique_ptr<SimServer> server;
  std::vector<int> bodies;
  std::vector<CouplerOptions> copts;
  std::vector<std::unique_ptr<Coupler>> couplers;
  std::vector<std::unique_ptr<DeviceBridge>> bridges;
  FeedbackLog logs[4];
  std::unique_ptr<bus::HandlerThread> handler;
  std::atomic<bool> stop{false}, stop_server{false};
  std::thread server_thread;
  std::vector<std::thread> threads;
};

TEST(Embedded, SingleUserPullGivesFiniteClampedNonzeroForce) {
  Session s(1);
  s.start();
  std::this_thread::sleep_for(1500ms);
  s.stop_all();
  const auto& c = s.couplers[0]->counters();
  EXPECT_GT(s.server->snapshots_published(), 50);
  EXPECT_GT(c.snapshots_accepted.load(), 50);
  EXPECT_LT(s.server->last_snapshot_bytes(), 65000u);
  std::lock_guard<std::mutex> lock(s.logs[0].mu);
  ASSERT_GT(s.logs[0].msgs.size(), 1000u);
  double fmax = 0;
  for (const auto& f : s.logs[0].msgs) {
    const Vec3 F(f.force_n[0], f.force_n[1], f.force_n[2]);
    ASSERT_TRUE(F.allFinite());
    EXPECT_LE(F.norm(), s.copts[0].max_force_n + 1e-12);
    fmax = std::max(fmax, F.norm());
  }
  EXPECT_GT(fmax, 0.01) << "pulling must produce a feedback force";
  std::printf("single user: %lld snapshots, max |f| %.4f N, %zu feedback messages\n",
              static_cast<long long>(c.snapshots_accepted.load()), fmax, s.logs[0].msgs.size());
}

// The blow-up guard: with gravity on, the 100-m protein-like tree whips its light ends and the
// explicit step diverges after a few seconds (docs/accuracy_and_stability.md). A joint-rate bound
// far below what the fall reaches trips the guard within a few hundred steps: every trip restores the
// last healthy checkpoint at rest, and stepping continues to the end of the run.
TEST(Embedded, BlowUpGuardRestoresACheckpointInsteadOfServingNaN) {
  bus::Bus bus("memq://");
  SimServerOptions so;
  so.scene = "protein_like";
  so.gravity = Vec3(0, 0, -9.81);
  so.max_joint_rate = 2.0;   // rad/s: the fall passes it within ~0.3 s
  so.checkpoint_every = 50;
  so.steps = 1500;
  so.display_rate_hz = 0;
  SimServer server(bus, so);
  std::atomic<bool> stop{false};
  server.run(stop);
  EXPECT_EQ(server.steps_done(), 1500);
  EXPECT_GT(server.resets(), 0);
  // A robot scene's reset is undone within the active region (the checkpoint's joints, or the step of a
  // region installed in the diverging step), without a selection inside the step.
  EXPECT_EQ(server.local_resets(), server.resets());
  std::printf("guard: %lld resets in 1500 steps, %lld within the active region\n",
              static_cast<long long>(server.resets()), static_cast<long long>(server.local_resets()));
}

TEST(Embedded, TwoUsersPullTwoBodies) {
  Session s(2);
  s.start();
  std::this_thread::sleep_for(1500ms);
  s.stop_all();
  EXPECT_NE(s.bodies[0], s.bodies[1]);
  for (int u = 0; u < 2; ++u) {
    EXPECT_GT(s.couplers[u]->counters().snapshots_accepted.load(), 50) << "user " << u;
    EXPECT_GT(s.max_force(u), 0.01) << "user " << u;
    EXPECT_LE(s.max_force(u), s.copts[u].max_force_n + 1e-12);
  }
}

TEST(Embedded, WatchdogZeroesForceWhenServerStopsAndRecoversWithNewServer) {
  Session s(1, 5.0, 0.005);
  s.start();
  // Wait for a pulled state with force (a 5 ms stale time on shared cores trips now and then).
  const auto until = std::chrono::steady_clock::now() + 4s;
  std::this_thread::sleep_for(700ms);
  while (s.couplers[0]->counters().force_n.load() == 0.0 && std::chrono::steady_clock::now() < until)
    std::this_thread::sleep_for(1ms);
  ASSERT_GT(s.couplers[0]->counters().force_n.load(), 0.0);
  s.stop_server = true;
  s.server_thread.join();
  const int64_t last_snapshot_utime = s.couplers[0]->counters().last_snapshot_utime.load();
  std::this_thread::sleep_for(200ms);
  {
    // Every feedback stamped more than stale (5 ms) + ramp (5 ms) + 5 ms after the last snapshot was
    // accepted is exactly zero (coupler clock). The watchdog acts on the loop's clock at the start of an
    // iteration, the stamp is taken at publish: a loop preempted in between on a loaded 2-core machine
    // stamped a force still on its ramp 1 ms late (0.51 N at 10.6 ms, falling 0.54 N/ms), so the margin
    // is a scheduling delay, not the watchdog's: 5 ms (without a watchdog the force never drops).
    std::lock_guard<std::mutex> lock(s.logs[0].mu);
    int64_t checked = 0;
    double first_zero_ms = -1;
    for (const auto& f : s.logs[0].msgs) {
      const double dt_ms = 1e-3 * static_cast<double>(f.utime - last_snapshot_utime);
      const double n = Vec3(f.force_n[0], f.force_n[1], f.force_n[2]).norm();
      if (dt_ms > 0 && n == 0 && first_zero_ms < 0) first_zero_ms = dt_ms;
      if (dt_ms > 15.0) {
        EXPECT_EQ(n, 0.0) << "at " << dt_ms << " ms after the last snapshot";
        EXPECT_TRUE(f.flags & lcmt_feedback::FLAG_WATCHDOG);
        ++checked;
      }
    }
    EXPECT_GT(checked, 100);
    std::printf("watchdog: first zero force %.2f ms after the last snapshot\n", first_zero_ms);
  }
  // A new server (version counter restarts) on the same bus: the coupler resumes.
  SimServer fresh(s.bus, s.so);
  std::atomic<bool> stop_fresh{false};
  std::thread t([&] { fresh.run(stop_fresh); });
  double f_after = 0;
  const auto until2 = std::chrono::steady_clock::now() + 3s;   // ramp-up is 100 ms
  while (f_after == 0.0 && std::chrono::steady_clock::now() < until2) {
    std::this_thread::sleep_for(1ms);
    f_after = s.couplers[0]->counters().force_n.load();
  }
  const int64_t restarts = s.couplers[0]->counters().restarts.load();
  stop_fresh = true;
  t.join();
  EXPECT_GE(restarts, 1);
  EXPECT_GT(f_after, 0.0) << "force must come back with the new server";
}

TEST(Embedded, ForeignFingerprintAndStaleVersionsIgnored) {
  bus::Bus bus("memq://");
  CouplerOptions co;
  co.stale_after_s = 10;   // no restart detection within this test
  Coupler coupler(bus, co);
  bus::HandlerThread handler(bus, 5);
  SceneOptions so;
  so.n = 8;
  auto model = make_chain(so);
  Data d(*model);
  State st(*model);
  forward_dynamics(*model, d, st);
  CouplingSnapshot snap;
  make_coupling_snapshot(*model, d, {make_grab(d, 8, Vec3::Zero())}, {Vec6::Zero()}, 10, 0.0, snap);
  auto send = [&](uint64_t fp, int64_t version) {
    snap.model_fingerprint = fp;
    snap.version = version;
    lcmt_coupling_snapshot m;
    bus::to_lcmt(snap, m);
    bus::stamp(m, 42);
    bus.publish(bus::channel::coeffs(0), m);
    std::this_thread::sleep_for(20ms);
  };
  send(model->fingerprint, 10);
  send(model->fingerprint ^ 1, 11);   // foreign
  send(model->fingerprint, 9);        // older
  send(model->fingerprint, 10);       // duplicate
  send(model->fingerprint, 12);       // newer: accepted
  handler.stop();
  const auto& c = coupler.counters();
  EXPECT_EQ(c.snapshots_accepted.load(), 2);
  EXPECT_EQ(c.foreign_rejected.load(), 1);
  EXPECT_EQ(c.stale_rejected.load(), 2);
}

TEST(Embedded, RandomBytesOnEveryChannelAreCountedNotFatal) {
  Session s(1);
  s.start();
  std::mt19937 rng(7);
  const std::vector<std::string> chans = {bus::channel::coeffs(0), bus::channel::device_state(0),
                                          bus::channel::feedback(0), bus::channel::user_force(0),
                                          bus::channel::scene_state()};
  const int per_channel = 200;
  std::vector<uint8_t> junk;
  for (int i = 0; i < per_channel; ++i) {
    for (const auto& ch : chans) {
      junk.resize(1 + rng() % 400);
      for (auto& b : junk) b = static_cast<uint8_t>(rng());
      s.bus.publish_raw(ch, junk.data(), static_cast<int>(junk.size()));
    }
    std::this_thread::sleep_for(1ms);
  }
  std::this_thread::sleep_for(300ms);
  s.stop_all();
  const int64_t rejected = s.couplers[0]->rejected_messages();
  // Each subscribed channel counts its own junk; the coupler's snapshot channel is decoded by the coupler.
  EXPECT_GE(rejected, per_channel) << "rejected " << rejected;
  EXPECT_GE(s.bus.rejected_total(), 3 * per_channel);
  EXPECT_GT(s.couplers[0]->counters().snapshots_accepted.load(), 0);
  EXPECT_TRUE(std::isfinite(s.max_force(0)));
  EXPECT_LE(s.max_force(0), s.copts[0].max_force_n + 1e-12);
}

// Subnormals, by construction on any CPU: the three hot loops (sim_server's step, the coupler, the device
// bridge) compute with flush-to-zero + denormals-are-zero, each in its own thread, and leave the mode of
// every other thread (here the test's) alone.
TEST(Embedded, HotLoopsComputeWithFlushToZeroAndDenormalsAreZero) {
#ifndef HAPTREE_HAVE_MXCSR
  GTEST_SKIP() << "no MXCSR on this CPU: ScopedFlushDenormals is a no-op";
#endif
  Session s(1);
  s.start();
  for (int i = 0; i < 400 && (s.server->steps_done() == 0 || s.couplers[0]->counters().iterations.load() == 0 ||
                              s.bridges[0]->readings() == 0); ++i)
    std::this_thread::sleep_for(5ms);
  s.stop_all();
  EXPECT_TRUE(s.server->counters().ftz_daz.load());
  EXPECT_TRUE(s.couplers[0]->counters().ftz_daz.load());
  EXPECT_TRUE(s.bridges[0]->ftz_daz());
  EXPECT_FALSE(ScopedFlushDenormals::active());
}

TEST(Embedded, RecordedSessionReplaysTo1em12) {
  const std::string path = ::testing::TempDir() + "haptree_replay_test.lcmlog";
  std::remove(path.c_str());
  {
    Session s(1);
    testing::LcmLogRecorder log(s.bus, path);
    ASSERT_TRUE(log.good());
    s.start();
    std::this_thread::sleep_for(1200ms);
    s.stop_all();
    log.close();
    const auto& co = s.copts[0];
    char cmd[1024];
    std::snprintf(cmd, sizeof cmd,
                  "%s %s --stiffness %.17g --damping %.17g --position-scale %.17g --force-scale %.17g "
                  "--offset %.17g %.17g %.17g --max-force-n %.17g --tolerance 1e-12",
                  HAPTREE_REPLAY_COUPLING, path.c_str(), co.stiffness, co.damping, co.position_scale, co.force_scale,
                  co.offset.x(), co.offset.y(), co.offset.z(), co.max_force_n);
    EXPECT_EQ(std::system(cmd), 0) << cmd;
  }
}

}  // namespace
}  // namespace haptree
