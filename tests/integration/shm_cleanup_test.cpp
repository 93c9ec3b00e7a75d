// A dead session's FEEDBACK never reaches a new device, and segments do not outlive their writers, with the real executables (shared memory + a 127.0.0.1 tcpq hub, no root):
//  * DeadSessionsForceNeverReachesANewDevice: sim_server + coupler + device_bridge over --shm, the user
//    pulling; kill -9 the coupler and the bridge; a new device_bridge --shm without a coupler must render
//    exactly zero (before the fix it rendered the dead coupler's last FEEDBACK, ~2.5 N).
//  * Launcher*: `haptree_run --processes` must leave none of its segments in /dev/shm after a normal end,
//    Ctrl-C, a child killed by SIGKILL, and SIGKILL of the launcher itself (children die with it).
#include <gtest/gtest.h>
#include <dirent.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/shm_channel.hpp"
#include "tests/integration/spawn.hpp"
#include "launcher/tcpq_hub.hpp"

namespace haptree {
namespace {

using Clock = std::chrono::steady_clock;
using namespace std::chrono_literals;

// /dev/shm entries whose name contains `tag`.
std::vector<std::string> segments_with(const std::string& tag) {
  std::vector<std::string> out;
  if (DIR* d = ::opendir("/dev/shm")) {
    while (const dirent* e = ::readdir(d))
      if (std::string(e->d_name).find(tag) != std::string::npos) out.push_back(e->d_name);
    ::closedir(d);
  }
  return out;
}

std::string last_line_with(const std::string& path, const std::string& key) {
  std::ifstream f(path);
  std::string line, found;
  while (std::getline(f, line))
    if (line.find(key) != std::string::npos) found = line;
  return found;
}

TEST(ShmCleanup, DeadSessionsForceNeverReachesANewDevice) {
  launcher::TcpqHub hub(0);
  const std::string suffix = "_D" + std::to_string(::getpid());
  const std::string dir = ::testing::TempDir();
  const std::vector<std::string> common = {"--lcm-url", hub.url(), "--channel-suffix", suffix};
  const auto a = testing::shm_session_args(HAPTREE_SIM_SERVER, HAPTREE_COUPLER, HAPTREE_DEVICE_BRIDGE, hub.url(), suffix);
  const pid_t p_sim = testing::spawn_logged(a.sim, dir + "shm_dead_sim.log");
  const pid_t p_cpl = testing::spawn_logged(a.coupler, dir + "shm_dead_coupler.log");
  const pid_t p_dev = testing::spawn_logged(a.device, dir + "shm_dead_bridge1.log");
  ASSERT_GT(p_sim, 0);
  ASSERT_GT(p_cpl, 0);
  ASSERT_GT(p_dev, 0);
  // Wait until the coupler writes a clearly nonzero force (the scripted pull), up to 10 s.
  bus::ShmReader fb_reader(bus::channel::feedback(0, suffix));
  lcmt_feedback fb{};
  double f_before = 0;
  for (const auto until = Clock::now() + 10s; Clock::now() < until && f_before < 0.5;) {
    if (fb_reader.read_msg(fb) == bus::ShmRead::kNew)
      f_before = std::sqrt(fb.force_n[0] * fb.force_n[0] + fb.force_n[1] * fb.force_n[1] + fb.force_n[2] * fb.force_n[2]);
    std::this_thread::sleep_for(1ms);
  }
  ASSERT_GE(f_before, 0.5) << "no pull force before the kill (logs in " << dir << ")";
  ::kill(p_cpl, SIGKILL);
  ::kill(p_dev, SIGKILL);
  testing::reap(p_cpl);
  testing::reap(p_dev);
  // The dead coupler's FEEDBACK segment is still there (nobody could unlink it) ...
  EXPECT_FALSE(segments_with("HAPTREE_FEEDBACK_0" + suffix).empty());
  // ... and a new device_bridge without a coupler must render nothing of it.
  std::vector<std::string> dev2 = {HAPTREE_DEVICE_BRIDGE, "--shm", "--device-option", "hold_s=60"};
  dev2.insert(dev2.end(), common.begin(), common.end());
  const std::string log2 = dir + "shm_dead_bridge2.log";
  const pid_t p_dev2 = testing::spawn_logged(dev2, log2);
  ASSERT_GT(p_dev2, 0);
  std::this_thread::sleep_for(1500ms);
  ::kill(p_dev2, SIGTERM);
  const int rc2 = testing::reap(p_dev2);
  ::kill(p_sim, SIGTERM);
  testing::reap(p_sim);
  hub.stop();
  const std::string summary = last_line_with(log2, "device_bridge: ");
  std::printf("before the kill |f| %.3f N; new bridge: %s\n", f_before, summary.c_str());
  EXPECT_EQ(rc2, 0);
  EXPECT_NE(summary.find(" 0 feedbacks, max |f| 0.000 N"), std::string::npos) << summary;
  for (const auto& s : segments_with(suffix)) bus::ShmChannel::remove(s.substr(8, s.rfind('.') - 8));
}

// Runs `haptree_run --processes` (protein_like 32); `act` is called with the launcher's pid once its
// session's segments exist. Returns the launcher's exit code.
template <class Act>
int launcher_session(const std::string& name, double duration_s, Act act) {
  const std::string dir = ::testing::TempDir() + "haptree_run_" + name;
  const pid_t p = testing::spawn_logged({HAPTREE_RUN, "--processes", "--viewer-port", "0", "--duration-s", std::to_string(duration_s),
                                         "--scene", "protein_like", "--n", "32", "--log-dir", dir},
                                        ::testing::TempDir() + "haptree_run_" + name + ".log");
  if (p <= 0) return -1;
  const std::string tag = "_R" + std::to_string(p) + ".";
  const auto until = Clock::now() + 15s;
  while (segments_with(tag).size() < 2 && Clock::now() < until) std::this_thread::sleep_for(5ms);
  EXPECT_EQ(segments_with(tag).size(), 2u) << name << ": the session's two segments never appeared";
  act(p);
  return testing::reap(p);
}

void expect_no_segments_within(pid_t launcher, double seconds, const std::string& what) {
  const std::string tag = "_R" + std::to_string(launcher) + ".";
  const auto until = Clock::now() + std::chrono::duration<double>(seconds);
  while (!segments_with(tag).empty() && Clock::now() < until) std::this_thread::sleep_for(10ms);
  std::string left;
  for (const auto& s : segments_with(tag)) left += " /dev/shm/" + s;
  EXPECT_TRUE(left.empty()) << what << ": left" << left;
}

TEST(ShmCleanup, LauncherNormalEnd) {
  pid_t pid = 0;
  const int rc = launcher_session("normal", 2.0, [&](pid_t p) { pid = p; });
  EXPECT_EQ(rc, 0);
  expect_no_segments_within(pid, 0.0, "normal end");
}

TEST(ShmCleanup, LauncherCtrlC) {
  pid_t pid = 0;
  launcher_session("sigint", 30.0, [&](pid_t p) {
    pid = p;
    std::this_thread::sleep_for(500ms);
    ::kill(p, SIGINT);
  });
  expect_no_segments_within(pid, 0.0, "Ctrl-C");
}

TEST(ShmCleanup, LauncherChildKilled) {
  pid_t pid = 0;
  int64_t coupler = 0;
  const int rc = launcher_session("child", 30.0, [&](pid_t p) {
    pid = p;
    const std::string line = last_line_with(::testing::TempDir() + "haptree_run_child.log", "coupler_0 pid ");
    if (!line.empty()) coupler = std::atoll(line.c_str() + line.find("coupler_0 pid ") + 14);
    if (coupler > 0) ::kill(static_cast<pid_t>(coupler), SIGKILL);
  });
  ASSERT_GT(coupler, 0);
  EXPECT_EQ(rc, 1);   // a child that stopped on its own is a failed session
  expect_no_segments_within(pid, 0.0, "coupler killed");
}

TEST(ShmCleanup, LauncherKilled) {
  pid_t pid = 0;
  const int rc = launcher_session("sigkill", 30.0, [&](pid_t p) {
    pid = p;
    std::this_thread::sleep_for(500ms);
    ::kill(p, SIGKILL);
  });
  EXPECT_EQ(rc, 128 + SIGKILL);
  // The children get SIGTERM from the kernel (PR_SET_PDEATHSIG) and unlink their own segments.
  expect_no_segments_within(pid, 10.0, "launcher SIGKILLed");
}

}  // namespace
}  // namespace haptree
