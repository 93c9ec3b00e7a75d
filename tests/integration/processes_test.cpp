// The three real executables as separate processes over LCM udpm, inside a private network namespace
// (so no datagram can leave the machine), and the coupler <-> device link over shared memory.
#include <gtest/gtest.h>
#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "tests/bus/netns.hpp"
#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"
#include "tests/integration/spawn.hpp"

extern char** environ;

namespace haptree {
namespace {

constexpr const char* kUrl = "udpm://239.255.76.67:7667?ttl=0";

pid_t spawn(const std::vector<std::string>& args, const std::string& log) {
  return testing::spawn_logged(args, log);
}


// Runs sim_server, coupler and device_bridge; listens to FEEDBACK on LCM (the shm link is mirrored).
int run_three(int out_fd, bool shm) {
  int body = 0;
  const auto off = testing::grab_offset_args(&body);
  const std::string dir = ::testing::TempDir();
  // Only the device_bridge mirrors the shm link (the coupler has no --mirror-rate-hz).
  std::vector<std::string> link = shm ? std::vector<std::string>{"--shm"} : std::vector<std::string>{};
  std::vector<std::string> dev_link = shm ? std::vector<std::string>{"--shm", "--mirror-rate-hz", "500"}
                                          : std::vector<std::string>{};
  std::vector<std::string> sim = {HAPTREE_SIM_SERVER, "--lcm-url", kUrl, "--scene", "protein_like", "--n", "32",
                                  "--rate-hz", "1000"};
  std::vector<std::string> cpl = {HAPTREE_COUPLER, "--lcm-url", kUrl, "--grab-body", std::to_string(body),
                                  "--rate-hz", "5000", "--sleep", "--stale-after-s", "0.05"};
  cpl.insert(cpl.end(), off.begin(), off.end());
  cpl.insert(cpl.end(), link.begin(), link.end());
  std::vector<std::string> dev = {HAPTREE_DEVICE_BRIDGE, "--lcm-url", kUrl, "--device-option", "approach_s=0.2",
                                  "--device-option", "hold_s=3"};
  dev.insert(dev.end(), dev_link.begin(), dev_link.end());
  bus::Bus bus(kUrl);
  std::atomic<int64_t> n{0}, nonfinite{0};
  std::atomic<double> fmax{0};
  bus.subscribe<lcmt_feedback>(bus::channel::feedback(0), [&](const lcmt_feedback& f, const std::string&) {
    const double x = std::sqrt(f.force_n[0] * f.force_n[0] + f.force_n[1] * f.force_n[1] + f.force_n[2] * f.force_n[2]);
    if (!std::isfinite(x)) ++nonfinite;
    if (x > fmax) fmax = x;
    ++n;
  });
  bus::HandlerThread handler(bus, 5);
  const pid_t p1 = spawn(sim, dir + "sim_server.log");
  const pid_t p2 = spawn(cpl, dir + "coupler.log");
  const pid_t p3 = spawn(dev, dir + "device_bridge.log");
  if (p1 < 0 || p2 < 0 || p3 < 0) {
    dprintf(out_fd, "spawn failed");
    return 3;
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(2500));
  int bad_exit = 0;
  std::string exits;
  for (pid_t p : {p3, p2, p1}) {
    ::kill(p, SIGTERM);
    int st = 0;
    ::waitpid(p, &st, 0);
    exits += " " + std::to_string(WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st));
    if (!WIFEXITED(st) || WEXITSTATUS(st) != 0) ++bad_exit;
  }
  dprintf(out_fd, "exit codes (bridge, coupler, server):%s; ", exits.c_str());
  handler.stop();
  dprintf(out_fd, "%s: %lld feedback messages seen on LCM, max |f| %.4f N, %lld non-finite, %d bad exits",
          shm ? "shm" : "udpm", static_cast<long long>(n.load()), fmax.load(), static_cast<long long>(nonfinite.load()),
          bad_exit);
  return (n > 100 && fmax > 0.01 && nonfinite == 0 && bad_exit == 0) ? 0 : 1;
}

TEST(Processes, ThreeProcessesOverUdpmInPrivateNetns) {
  const auto r = testing::run_in_private_netns(testing::kNetnsMulticastSetup, [](int fd) { return run_three(fd, false); });
  std::printf("%s\n", r.output.c_str());
  EXPECT_EQ(r.exit_code, 0) << r.output;
}

TEST(Processes, CouplerDeviceOverSharedMemoryServerOverUdpm) {
  const auto r = testing::run_in_private_netns(testing::kNetnsMulticastSetup, [](int fd) { return run_three(fd, true); });
  std::printf("%s\n", r.output.c_str());
  EXPECT_EQ(r.exit_code, 0) << r.output;
}

}  // namespace
}  // namespace haptree
