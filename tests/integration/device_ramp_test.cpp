// The device side never steps the force (docs/network_faults.md): when FEEDBACK stops (a stalled coupler, a broken
// link between coupler and device) the device_bridge used to cut the force to zero after its 10 ms
// feedback timeout and jump straight back to the full force with the next FEEDBACK — a jerk of the whole
// force in one tick, at the hand. Now it ramps like the coupler's watchdog and bounds every per-tick change
// by --max-force-rate-n-per-s (default: the clamp within 5 ms).
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <thread>

#include "device_bridge/device_bridge.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/wire.hpp"

namespace haptree {
namespace {

using namespace std::chrono_literals;

TEST(DeviceRamp, FeedbackGapRampsDownAndBackWithoutAStep) {
  bus::Bus bus("memq://");
  DeviceBridgeOptions bo;
  bo.kind = "scripted";
  bo.max_force_n = 3.0;
  bo.rate_hz = 1000;   // feedback_timeout_s stays at its default 10 ms
  DeviceBridge bridge(bus, bo);
  bus::HandlerThread handler(bus, 2);
  std::atomic<bool> stop{false}, pause{false}, quit{false};
  std::thread loop([&] { bridge.run(stop); });
  std::thread coupler([&] {   // a coupler at 2 kHz that stalls while `pause` is set
    int64_t seq = 0;
    while (!quit) {
      if (!pause) {
        lcmt_feedback f{};
        bus::stamp(f, 4242);
        f.seq = ++seq;
        f.force_n[0] = 2.0;
        bus.publish(bus::channel::feedback(0), f);
      }
      std::this_thread::sleep_for(500us);
    }
  });
  // The full force once the feedback flows (a loaded machine may stall the 2 kHz thread past the
  // timeout for a moment: wait for the force rather than sample it once).
  auto settled = [&] {
    for (auto end = std::chrono::steady_clock::now() + 5s; std::chrono::steady_clock::now() < end;) {
      if (bridge.last_force_n() == 2.0) return 2.0;
      std::this_thread::sleep_for(1ms);
    }
    return bridge.last_force_n();
  };
  std::this_thread::sleep_for(100ms);
  const double before = settled();
  pause = true;
  double min_in_gap = 1e9;   // sampled all through a 150 ms gap (> timeout + ramp): it must reach zero
  for (auto end = std::chrono::steady_clock::now() + 150ms; std::chrono::steady_clock::now() < end;) {
    min_in_gap = std::min(min_in_gap, bridge.last_force_n());
    std::this_thread::sleep_for(200us);
  }
  pause = false;
  const double after = settled();
  quit = true;
  coupler.join();
  stop = true;
  loop.join();
  handler.stop();
  // A full-clamp change takes at least 5 ms: at 1 kHz at most 3 N × 1 ms / 5 ms = 0.6 N per tick.
  const double limit = bo.max_force_n / 0.005 / bo.rate_hz;
  std::printf("device: %.3f N before the gap, min %.3f N in it, %.3f N after; max step %.4f N/tick (limit %.3f)\n",
              before, min_in_gap, after, bridge.max_force_step_n(), limit);
  EXPECT_EQ(before, 2.0);
  EXPECT_EQ(min_in_gap, 0.0);
  EXPECT_EQ(after, 2.0);
  EXPECT_EQ(bridge.max_force_seen_n(), 2.0);
  EXPECT_LE(bridge.max_force_step_n(), limit * (1 + 1e-12));
  EXPECT_GT(bridge.max_force_step_n(), 0.0);
}

}  // namespace
}  // namespace haptree
