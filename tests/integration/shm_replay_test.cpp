// A session whose device link runs over shared memory, recorded with the default
// mirror rate, replays with replay_coupling's defaults: the coupler's settings come from the log
// (lcmt_coupler_settings) and every mirrored FEEDBACK comes with the device state it answers, so
// > 0 compared, 0 missing, deviation <= 1e-12 N (the replay is the same computation on the same bits).
#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <signal.h>
#include <sys/wait.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "haptree/bus/bus.hpp"
#include "tests/integration/log_recorder.hpp"
#include "tests/integration/spawn.hpp"
#include "launcher/tcpq_hub.hpp"

namespace haptree {
namespace {

using namespace std::chrono_literals;

using testing::stop_and_reap;

long long number_before(const std::string& out, const std::string& word) {
  const auto k = out.find(word);
  if (k == std::string::npos) return -1;
  auto b = out.rfind(' ', k - 2);
  return std::atoll(out.c_str() + (b == std::string::npos ? 0 : b + 1));
}

TEST(ShmReplay, RecordedShmSessionReplaysWithDefaults) {
  launcher::TcpqHub hub(0);
  const std::string suffix = "_P" + std::to_string(::getpid());
  const std::string dir = ::testing::TempDir();
  const std::string path = dir + "haptree_shm_session.lcmlog";
  std::remove(path.c_str());
  const auto a = testing::shm_session_args(HAPTREE_SIM_SERVER, HAPTREE_COUPLER, HAPTREE_DEVICE_BRIDGE, hub.url(), suffix);
  {
    // The recorder: every channel of the session's bus into an LCM log, as lcm-logger would.
    bus::Bus bus(hub.url());
    testing::LcmLogRecorder log(bus, path);
    ASSERT_TRUE(log.good());
    bus::HandlerThread handler(bus, 5);
    std::this_thread::sleep_for(200ms);   // the recorder is connected before the session starts
    const pid_t p_sim = testing::spawn_logged(a.sim, dir + "shm_replay_sim.log");
    const pid_t p_cpl = testing::spawn_logged(a.coupler, dir + "shm_replay_coupler.log");
    const pid_t p_dev = testing::spawn_logged(a.device, dir + "shm_replay_bridge.log");
    ASSERT_GT(p_sim, 0);
    ASSERT_GT(p_cpl, 0);
    ASSERT_GT(p_dev, 0);
    std::this_thread::sleep_for(3s);   // approach 0.2 s, settle, pull: most of it under a nonzero force
    EXPECT_EQ(stop_and_reap(p_dev), 0);
    EXPECT_EQ(stop_and_reap(p_cpl), 0);
    EXPECT_EQ(stop_and_reap(p_sim), 0);
    handler.stop();
    log.close();
  }
  hub.stop();
  const std::string cmd = std::string(HAPTREE_REPLAY_COUPLING) + " " + path + " --channel-suffix " + suffix + " 2>&1";
  FILE* p = ::popen(cmd.c_str(), "r");
  ASSERT_NE(p, nullptr);
  std::string out;
  char buf[4096];
  for (size_t k; (k = std::fread(buf, 1, sizeof buf, p)) > 0;) out.append(buf, k);
  const int st = ::pclose(p);
  std::printf("%s\n%s", cmd.c_str(), out.c_str());
  EXPECT_TRUE(WIFEXITED(st) && WEXITSTATUS(st) == 0) << out;
  // > 0, not a rate: on a loaded machine more feedback falls in watchdog ramps (skipped, counted).
  EXPECT_GT(number_before(out, "compared"), 0) << out;
  EXPECT_EQ(number_before(out, "missing snapshot/pose"), 0) << out;
  EXPECT_NE(out.find("coupler settings from the log"), std::string::npos) << out;
}

}  // namespace
}  // namespace haptree
