// Real processes on one host without any network: the device link over shared memory, the rest over
// LCM tcpq:// through a hub bound to 127.0.0.1 (launcher/tcpq_hub.hpp). No root needed.
//  * ServerKilledMidSession: SIGKILL the sim_server process while the scripted user pulls; from the
//    device side (the FEEDBACK shared-memory segment the device_bridge reads), the force must reach
//    exactly zero within 10x the coupler's watchdog time (stale_after_s + ramp_down_s) and stay zero; the
//    coupler and device_bridge must survive; a new sim_server process must bring feedback back.
//  * LauncherProcessesSmoke: `haptree_run --processes --duration-s 2` exits 0 with feedback > 0.
#include <gtest/gtest.h>
#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/shm_channel.hpp"
#include "haptree/dca.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "haptree/safety.hpp"
#include "haptree/scenes.hpp"
#include "tests/integration/spawn.hpp"
#include "launcher/tcpq_hub.hpp"

extern char** environ;

namespace haptree {
namespace {

using Clock = std::chrono::steady_clock;

pid_t spawn(const std::vector<std::string>& args, const std::string& log) {
  return testing::spawn_logged(args, log);
}

bool alive(pid_t p) {
  int st = 0;
  return ::waitpid(p, &st, WNOHANG) == 0;
}

using testing::stop_and_reap;   // SIGTERM + wait; the exit code (128 + signal if killed)

struct Sample {
  double t_s;   // since the test's t0
  double f_n;
  int32_t flags;
  int64_t version;
};

TEST(Restart, ServerKilledMidSession) {
  constexpr double kStaleAfterS = 0.05;
  const double watchdog_s = kStaleAfterS + WatchdogParams{}.ramp_down_s;   // the coupler's ramp-down
  launcher::TcpqHub hub(0);
  const std::string url = hub.url();
  const std::string suffix = "_K" + std::to_string(::getpid());
  const std::string dir = ::testing::TempDir();
  int body = 0;
  const Vec3 o = testing::grab_offset_protein32(&body);
  const std::vector<std::string> common = {"--lcm-url", url, "--channel-suffix", suffix};
  std::vector<std::string> sim = {HAPTREE_SIM_SERVER, "--scene", "protein_like", "--n", "32", "--rate-hz", "1000"};
  sim.insert(sim.end(), common.begin(), common.end());
  std::vector<std::string> cpl = {HAPTREE_COUPLER, "--grab-body", std::to_string(body), "--rate-hz", "5000",
                                  "--sleep", "--stale-after-s", std::to_string(kStaleAfterS), "--shm", "--offset",
                                  std::to_string(o.x()), std::to_string(o.y()), std::to_string(o.z())};
  cpl.insert(cpl.end(), common.begin(), common.end());
  // approach 0.2 s, settle 0.2 s, pull 1 s, then hold for the rest of the test (button down throughout)
  std::vector<std::string> dev = {HAPTREE_DEVICE_BRIDGE, "--shm", "--device-option", "approach_s=0.2", "--device-option",
                                  "hold_s=60"};
  dev.insert(dev.end(), common.begin(), common.end());

  // The device's side of the link: the latest-value FEEDBACK segment, read as the device_bridge reads it.
  bus::ShmReader feedback(bus::channel::feedback(0, suffix));
  std::vector<Sample> samples;
  samples.reserve(1 << 20);
  const auto t0 = Clock::now();
  auto now_s = [&t0] { return std::chrono::duration<double>(Clock::now() - t0).count(); };
  lcmt_feedback fb{};
  int64_t nonfinite = 0;
  auto poll_for = [&](double seconds) {
    const double end = now_s() + seconds;
    while (now_s() < end) {
      if (feedback.read_msg(fb) == bus::ShmRead::kNew) {
        const double f = std::sqrt(fb.force_n[0] * fb.force_n[0] + fb.force_n[1] * fb.force_n[1] +
                                   fb.force_n[2] * fb.force_n[2]);
        if (!std::isfinite(f)) ++nonfinite;
        samples.push_back({now_s(), f, fb.flags, fb.snapshot_version});
      }
      std::this_thread::sleep_for(std::chrono::microseconds(100));
    }
  };

  const pid_t p_sim = spawn(sim, dir + "restart_sim_server_1.log");
  const pid_t p_cpl = spawn(cpl, dir + "restart_coupler.log");
  const pid_t p_dev = spawn(dev, dir + "restart_device_bridge.log");
  ASSERT_GT(p_sim, 0);
  ASSERT_GT(p_cpl, 0);
  ASSERT_GT(p_dev, 0);

  // 1. Session under way: wait (up to 8 s) until the user has pulled with a nonzero force for 1 s.
  double first_force_t = -1;
  for (double waited = 0; waited < 8.0 && (first_force_t < 0 || now_s() - first_force_t < 1.0); waited += 0.05) {
    poll_for(0.05);
    for (size_t i = samples.size(); i-- > 0 && first_force_t < 0;)
      if (samples[i].f_n > 0.01) first_force_t = samples[i].t_s;
  }
  double fmax_before = 0;
  for (const auto& x : samples) fmax_before = std::max(fmax_before, x.f_n);
  ASSERT_GT(fmax_before, 0.01) << "no feedback force before the kill (logs in " << dir << ")";
  ASSERT_GT(samples.back().f_n, 0.0) << "force already zero before the kill";

  // 2. SIGKILL the server mid-session.
  const double t_kill = now_s();
  ASSERT_EQ(::kill(p_sim, SIGKILL), 0);
  int st = 0;
  ::waitpid(p_sim, &st, 0);
  const size_t i_kill = samples.size();
  poll_for(1.5);
  const size_t i_restart = samples.size();
  ASSERT_GT(i_restart, i_kill + 100) << "the coupler stopped publishing feedback after the kill";
  // Time of the first zero after which every feedback until the restart is exactly zero.
  size_t i_zero = i_restart;
  while (i_zero > i_kill && samples[i_zero - 1].f_n == 0.0) --i_zero;
  ASSERT_LT(i_zero, i_restart) << "force still nonzero 1.5 s after the server was killed";
  const double zero_after_s = samples[i_zero].t_s - t_kill;
  int64_t ramp_samples = 0;   // nonzero feedbacks after the kill, all with the watchdog flag set
  for (size_t i = i_kill; i < i_zero; ++i)
    if (samples[i].flags & kSafetyWatchdog) ++ramp_samples;
  const double fmax_zero_phase = [&] {
    double v = 0;
    for (size_t i = i_zero; i < i_restart; ++i) v = std::max(v, samples[i].f_n);
    return v;
  }();
  bool watchdog_flag_on_zeros = true;
  for (size_t i = i_zero; i < i_restart; ++i) watchdog_flag_on_zeros &= (samples[i].flags & kSafetyWatchdog) != 0;
  EXPECT_TRUE(alive(p_cpl)) << "coupler died after the server was killed";
  EXPECT_TRUE(alive(p_dev)) << "device_bridge died after the server was killed";

  // 3. A new server process: feedback must come back.
  const double t_restart = now_s();
  const pid_t p_sim2 = spawn(sim, dir + "restart_sim_server_2.log");
  ASSERT_GT(p_sim2, 0);
  poll_for(4.0);
  int64_t nonzero_after = 0;
  double first_back_s = -1, fmax_after = 0;
  for (size_t i = i_restart; i < samples.size(); ++i)
    if (samples[i].f_n > 0) {
      ++nonzero_after;
      fmax_after = std::max(fmax_after, samples[i].f_n);
      if (first_back_s < 0) first_back_s = samples[i].t_s - t_restart;
    }
  const bool cpl_alive = alive(p_cpl), dev_alive = alive(p_dev), sim2_alive = alive(p_sim2);
  const int rc_dev = stop_and_reap(p_dev), rc_cpl = stop_and_reap(p_cpl), rc_sim2 = stop_and_reap(p_sim2);
  hub.stop();

  std::printf("server SIGKILLed at t = %.3f s (max |f| before %.3f N): force exactly zero %.1f ms after the kill "
              "(watchdog stale_after %.0f ms + ramp %.0f ms = %.0f ms; bound 10x = %.0f ms), %lld ramp feedbacks "
              "(watchdog flag), max |f| in the zero phase %.3g N; new server: first nonzero force %.0f ms after its "
              "spawn, %lld nonzero feedbacks seen in 4 s (max %.3f N); %lld non-finite; exits bridge %d coupler %d "
              "server %d\n",
              t_kill, fmax_before, 1e3 * zero_after_s, 1e3 * kStaleAfterS, 1e3 * (watchdog_s - kStaleAfterS),
              1e3 * watchdog_s, 1e4 * watchdog_s, static_cast<long long>(ramp_samples), fmax_zero_phase,
              1e3 * first_back_s, static_cast<long long>(nonzero_after), fmax_after, static_cast<long long>(nonfinite),
              rc_dev, rc_cpl, rc_sim2);
  EXPECT_LE(zero_after_s, 10.0 * watchdog_s);
  EXPECT_EQ(fmax_zero_phase, 0.0);
  EXPECT_TRUE(watchdog_flag_on_zeros);
  EXPECT_EQ(nonfinite, 0);
  EXPECT_GT(nonzero_after, 0) << "no feedback force after the server restart (logs in " << dir << ")";
  EXPECT_TRUE(cpl_alive);
  EXPECT_TRUE(dev_alive);
  EXPECT_TRUE(sim2_alive);
  EXPECT_EQ(rc_dev, 0);
  EXPECT_EQ(rc_cpl, 0);
  EXPECT_EQ(rc_sim2, 0);
}

TEST(Restart, LauncherProcessesSmoke) {
  const std::string log_dir = ::testing::TempDir() + "haptree_run_processes_smoke";
  const std::string cmd = std::string(HAPTREE_RUN) + " --processes --duration-s 2 --scene protein_like --n 32 --viewer-port 0 " +
                          "--log-dir " + log_dir + " 2>&1";
  FILE* p = ::popen(cmd.c_str(), "r");
  ASSERT_NE(p, nullptr);
  std::string out;
  char buf[4096];
  for (size_t n; (n = std::fread(buf, 1, sizeof buf, p)) > 0;) out.append(buf, n);
  const int st = ::pclose(p);
  std::printf("%s", out.c_str());
  ASSERT_TRUE(WIFEXITED(st)) << out;
  EXPECT_EQ(WEXITSTATUS(st), 0) << out;
  long long seen = -1, applied = -1;
  double fmax = -1;
  const auto a = out.find("launcher saw ");
  ASSERT_NE(a, std::string::npos) << out;
  std::sscanf(out.c_str() + a, "launcher saw %lld feedback messages (max |f| %lf N", &seen, &fmax);
  const auto b = out.find(" feedbacks applied by the device");
  ASSERT_NE(b, std::string::npos) << out;
  const auto c = out.rfind(", ", b);
  std::sscanf(out.c_str() + c + 2, "%lld", &applied);
  EXPECT_GT(seen, 0) << out;
  EXPECT_GT(applied, 0) << out;
  EXPECT_NE(out.find("sim_server exit code 0"), std::string::npos) << out;
}

}  // namespace
}  // namespace haptree
