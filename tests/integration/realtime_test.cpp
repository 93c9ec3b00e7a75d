// sim_server reports its real-time factor and says when it cannot keep its rate.
// A rate of 1 MHz cannot be kept by any machine for protein_like (857 DOF: one step is far above 1 µs), so
// the stats must show rate_fraction < 0.9 and real_time_factor = steps/s × dt.
#include <gtest/gtest.h>

#include <atomic>
#include <mutex>
#include <thread>
#include <vector>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/lcmt_process_stats.hpp"
#include "sim_server/sim_server.hpp"

namespace haptree {
namespace {

double extra(const lcmt_process_stats& m, const std::string& name) {
  for (int i = 0; i < m.n_extra; ++i)
    if (m.extra_names[static_cast<size_t>(i)] == name) return m.extra_values[static_cast<size_t>(i)];
  ADD_FAILURE() << "no extra '" << name << "' in sim_server's stats";
  return -1;
}

TEST(RealTime, StatsCarryTheRealTimeFactorAndTheShareOfTheRequestedRate) {
  bus::Bus bus("memq://");
  std::mutex mu;
  std::vector<lcmt_process_stats> got;
  bus.subscribe<lcmt_process_stats>(bus::channel::stats("sim_server"), [&](const lcmt_process_stats& m, const std::string&) {
    std::lock_guard<std::mutex> l(mu);
    got.push_back(m);
  });
  bus::HandlerThread handler(bus, 5);
  SimServerOptions o;
  o.scene = "protein_like";
  o.rate_hz = 1e6;
  o.dt = 1e-3;
  SimServer server(bus, o);
  std::atomic<bool> stop{false};
  std::thread t([&] { server.run(stop); });
  for (int i = 0; i < 100; ++i) {   // up to 10 s for 3 stats messages
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    std::lock_guard<std::mutex> l(mu);
    if (got.size() >= 3) break;
  }
  stop = true;
  t.join();
  handler.stop();
  std::lock_guard<std::mutex> l(mu);
  ASSERT_GE(got.size(), 3u);
  const lcmt_process_stats& m = got.back();
  EXPECT_GT(m.loop_rate_hz, 0);
  EXPECT_NEAR(extra(m, "real_time_factor"), m.loop_rate_hz * o.dt, 1e-12 * m.loop_rate_hz);
  EXPECT_NEAR(extra(m, "rate_fraction"), m.loop_rate_hz / o.rate_hz, 1e-15);
  EXPECT_LT(extra(m, "rate_fraction"), 0.9);
  EXPECT_GT(extra(m, "max_step_ms"), 0);
}

}  // namespace
}  // namespace haptree
