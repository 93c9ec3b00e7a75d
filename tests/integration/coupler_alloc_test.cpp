// The coupler's loop thread allocates nothing once it runs (STYLE: no allocation in the coupling loop),
// across its 1 s stats ticks too: the stats message, the settings message and the toggling of the
// second-writer check (an LCM subscribe) belong to the housekeeping thread. The loop thread is watched by
// the operator new counter (tests/support/count_allocations.hpp); the bus handler and housekeeping
// threads may allocate. The coupler grabs and computes with snapshots all along, over LCM (memq) and
// over shared memory.
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <memory>
#include <string>
#include <thread>
#include <unistd.h>

#include "coupler/coupler.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/dca.hpp"
#include "haptree/device/device.hpp"
#include "haptree/lcmt_process_stats.hpp"
#include "haptree/scenes.hpp"
#include "tests/support/count_allocations.hpp"

namespace haptree {
namespace {

using namespace std::chrono_literals;

constexpr int kBody = 8;   // the chain's last body: the snapshots' grab

// Snapshots of one grab of body kBody, versions 1, 2, ... (the failsafe test's FakeServer).
struct Snapshots {
  explicit Snapshots(bus::Bus& b) : bus(b) {
    SceneOptions so;
    so.n = 8;
    so.gravity = Vec3::Zero();
    model = make_chain(so);
    Data d(*model);
    State st(*model);
    forward_dynamics(*model, d, st);
    make_coupling_snapshot(*model, d, {make_grab(d, kBody, Vec3::Zero())}, {Vec6::Zero()}, 0, 0.0, snap);
    snap.model_fingerprint = model->fingerprint;
  }
  void send(int64_t version, const std::string& suffix) {
    snap.version = version;
    bus::to_lcmt(snap, msg);
    bus::stamp(msg, 5005);
    bus.publish(bus::channel::coeffs(0, suffix), msg);
  }
  bus::Bus& bus;
  std::shared_ptr<const Model> model;
  CouplingSnapshot snap;
  lcmt_coupling_snapshot msg;
};

lcmt_device_state grab_pose(int64_t seq) {
  lcmt_device_state m{};
  bus::stamp(m, 6006);
  m.seq = seq;
  m.orientation[0] = 1;
  m.position_m[0] = 1e-3 * static_cast<double>(seq % 20);   // a small motion: a nonzero spring force
  m.buttons = device::kButtonGrab;
  m.grab_seq = 1;
  return m;
}

void run_and_count(bool shm) {
  bus::Bus bus("memq://");
  CouplerOptions co;
  co.grab_body = kBody;
  co.rate_hz = 2000;
  co.busy_wait = false;   // 2 shared cores: sleep pacing
  co.shm = shm;
  co.channel_suffix = "_alloc" + std::to_string(::getpid());   // shm segments private to this run
  std::unique_ptr<bus::ShmWriter> shm_pose;
  if (shm) shm_pose = std::make_unique<bus::ShmWriter>(bus::channel::device_state(0, co.channel_suffix));
  Coupler coupler(bus, co);
  std::atomic<int> stats{0};
  bus.subscribe<lcmt_process_stats>(bus::channel::stats("coupler_0", co.channel_suffix),
                                    [&](const lcmt_process_stats&, const std::string&) { ++stats; });
  bus::HandlerThread handler(bus, 2);
  Snapshots snaps(bus);
  std::atomic<bool> stop{false}, quit{false};
  std::thread feeder([&] {   // the server and the device: snapshots at 200 Hz, poses at 1 kHz
    for (int64_t seq = 1; !quit; ++seq) {
      const lcmt_device_state p = grab_pose(seq);
      if (shm_pose) shm_pose->write_msg(p);
      else bus.publish(bus::channel::device_state(0, co.channel_suffix), p);
      if (seq % 5 == 0) snaps.send(seq / 5, co.channel_suffix);
      std::this_thread::sleep_for(1ms);
    }
  });
  std::thread loop([&] {
    testing::watch_this_thread();
    coupler.run(stop);
  });
  // Waits for n stats messages; a bound far above n seconds only so that a hung coupler fails.
  auto wait_stats = [&](int n) {
    for (int i = 0; i < 4000 && stats.load() < n; ++i) std::this_thread::sleep_for(5ms);
    return stats.load() >= n;
  };
  // After the first tick the loop is warm (per-thread publish buffers grown, the grab made, snapshots in use).
  const bool warm = wait_stats(1);
  const long before = testing::watched_allocation_count();
  const int64_t feedbacks_before = coupler.counters().grab_feedbacks.load();
  const bool ticked = wait_stats(4);   // three more ticks: three stats messages, three writer-check windows
  const long after = testing::watched_allocation_count();
  const int64_t feedbacks_after = coupler.counters().grab_feedbacks.load();
  stop = true;
  loop.join();
  quit = true;
  feeder.join();
  handler.stop();
  const auto& c = coupler.counters();
  std::printf("%s: loop-thread allocations %ld over ticks 1-4 (%ld before), %lld grab feedbacks, %lld snapshots, "
              "version in use %lld\n", shm ? "shm" : "lcm", after - before, before,
              static_cast<long long>(feedbacks_after - feedbacks_before),
              static_cast<long long>(c.snapshots_accepted.load()), static_cast<long long>(c.version_in_use.load()));
  ASSERT_TRUE(warm && ticked) << "stats messages: " << stats.load();
  EXPECT_EQ(after - before, 0) << "the coupler's loop thread allocated";
  EXPECT_GT(feedbacks_after - feedbacks_before, 1000) << "the loop did not grab";
  EXPECT_GT(c.snapshots_accepted.load(), 100);
  EXPECT_GT(c.version_in_use.load(), 0);
  EXPECT_LT(c.grab_watchdog_zeros.load(), c.grab_feedbacks.load()) << "the loop never computed with a snapshot";
}

TEST(CouplerLoop, AllocatesNothingAcrossStatsTicksOverLcm) { run_and_count(false); }
TEST(CouplerLoop, AllocatesNothingAcrossStatsTicksOverShm) { run_and_count(true); }

}  // namespace
}  // namespace haptree
