// "Server host" and "workstation host" on one machine: two private network namespaces joined by a veth pair.
// sim_server runs in namespace A; coupler + device_bridge run in namespace B; they talk over LCM udpm
// multicast (ttl=1) across the veth link. Nothing leaves the machine: the namespaces, the veth pair and the
// 10.213.0.0/24 addresses exist only inside this test and are deleted at the end, even on failure.
// Needs root (ip netns); without it the test fails with a clear message (it does not skip).
#include <gtest/gtest.h>
#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"
#include "tests/integration/spawn.hpp"

extern char** environ;

namespace haptree {
namespace {

constexpr const char* kUrl = "udpm://239.255.76.67:7667?ttl=1";
constexpr double kMaxForceN = 3.0;  // --max-force-n given to coupler and device_bridge

int sh(const std::string& cmd) { return std::system((cmd + " >/dev/null 2>&1").c_str()); }

// Creates nsA/nsB + veth pair on construction, deletes them in the destructor (also on test failure).
struct TwoNamespaces {
  std::string a, b, va, vb, error;
  TwoNamespaces() {
    const std::string id = std::to_string(::getpid());
    a = "htA" + id;
    b = "htB" + id;
    va = "htva" + id;
    vb = "htvb" + id;
    const std::vector<std::string> cmds = {
        "ip netns add " + a,
        "ip netns add " + b,
        "ip link add " + va + " type veth peer name " + vb,
        "ip link set " + va + " netns " + a,
        "ip link set " + vb + " netns " + b,
        "ip netns exec " + a + " ip addr add 10.213.0.1/24 dev " + va,
        "ip netns exec " + b + " ip addr add 10.213.0.2/24 dev " + vb,
        "ip netns exec " + a + " ip link set lo up",
        "ip netns exec " + b + " ip link set lo up",
        "ip netns exec " + a + " ip link set " + va + " up multicast on",
        "ip netns exec " + b + " ip link set " + vb + " up multicast on",
        "ip netns exec " + a + " ip route add 224.0.0.0/4 dev " + va,
        "ip netns exec " + b + " ip route add 224.0.0.0/4 dev " + vb,
    };
    if (::geteuid() != 0) {
      error = "not root: this test creates two network namespaces and a veth pair (ip netns add) and needs root "
              "(CI runs it as root); exclude it with `ctest -LE netns`.";
      return;
    }
    for (const auto& c : cmds) {
      if (sh(c) != 0) {
        error = "network namespace set-up failed at `" + c + "` (needs root and iproute2; exclude with `ctest -LE netns`)";
        return;
      }
    }
  }
  ~TwoNamespaces() {
    sh("ip netns delete " + a);  // deleting a namespace destroys its veth end and so the pair
    sh("ip netns delete " + b);
    sh("ip link delete " + va);  // in case the pair was never moved
  }
};

pid_t spawn_in(const std::string& ns, std::vector<std::string> args, const std::string& log) {
  args.insert(args.begin(), {"ip", "netns", "exec", ns});  // ip execs the program: the pid is the program's
  return testing::spawn_logged(args, log, /*search_path=*/true);
}

std::string slurp(const std::string& path) {
  std::ifstream f(path);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}


TEST(TwoHosts, ServerAndWorkstationNamespacesOverVethUdpm) {
  TwoNamespaces ns;
  ASSERT_TRUE(ns.error.empty()) << ns.error;

  int body = 0;
  const auto off = testing::grab_offset_args(&body);
  const std::string dir = ::testing::TempDir();
  const std::string mf = std::to_string(kMaxForceN);
  std::vector<std::string> sim = {HAPTREE_SIM_SERVER, "--lcm-url", kUrl, "--scene", "protein_like", "--n", "32",
                                  "--rate-hz", "1000"};
  std::vector<std::string> cpl = {HAPTREE_COUPLER, "--lcm-url", kUrl, "--grab-body", std::to_string(body),
                                  "--rate-hz", "5000", "--sleep", "--stale-after-s", "0.05", "--max-force-n", mf};
  cpl.insert(cpl.end(), off.begin(), off.end());
  std::vector<std::string> dev = {HAPTREE_DEVICE_BRIDGE, "--lcm-url", kUrl, "--option", "approach_s=0.2",
                                  "--option", "hold_s=3", "--max-force-n", mf};
  const std::string dev_log = dir + "two_hosts_device_bridge.log";
  const pid_t p1 = spawn_in(ns.a, sim, dir + "two_hosts_sim_server.log");
  const pid_t p2 = spawn_in(ns.b, cpl, dir + "two_hosts_coupler.log");
  const pid_t p3 = spawn_in(ns.b, dev, dev_log);
  std::this_thread::sleep_for(std::chrono::milliseconds(3000));
  std::string exits;
  int bad_exit = 0;
  for (pid_t p : {p3, p2, p1}) {
    if (p < 0) {
      exits += " spawn-failed";
      ++bad_exit;
      continue;
    }
    ::kill(p, SIGTERM);
    int st = 0;
    ::waitpid(p, &st, 0);
    exits += " " + std::to_string(WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st));
    if (!WIFEXITED(st) || WEXITSTATUS(st) != 0) ++bad_exit;
  }
  // device_bridge's final line: "device_bridge: R readings, F feedbacks, max |f| X N, ..."
  const std::string log = slurp(dev_log);
  std::smatch m;
  long long feedbacks = -1;
  double fmax = std::nan("");
  if (std::regex_search(log, m, std::regex(R"((\d+) feedbacks, max \|f\| ([-+0-9.eEnaif]+) N)"))) {
    feedbacks = std::stoll(m[1]);
    fmax = std::strtod(m[2].str().c_str(), nullptr);
  }
  std::printf("exit codes (bridge, coupler, server):%s; device got %lld feedbacks, max |f| %.4f N (clamp %.1f N)\n",
              exits.c_str(), feedbacks, fmax, kMaxForceN);
  EXPECT_EQ(bad_exit, 0) << "exit codes (bridge, coupler, server):" << exits << "\n" << log;
  EXPECT_GT(feedbacks, 100) << log;
  EXPECT_TRUE(std::isfinite(fmax)) << log;
  EXPECT_GT(fmax, 0.01) << log;
  EXPECT_LE(fmax, kMaxForceN + 1e-9) << log;
}

}  // namespace
}  // namespace haptree
