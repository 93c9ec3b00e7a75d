// IMD across processes: sim_server and imd_bridge as real executables on LCM tcpq:// through a
// 127.0.0.1 hub (no root, no network), and haptree_run --imd-port (the ImdServer inside the launcher).
#include <gtest/gtest.h>

#include <signal.h>
#include <sys/wait.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <string>
#include <thread>

#include "haptree/spatial.hpp"
#include "tests/imd/imd_receiver.hpp"
#include "tests/integration/spawn.hpp"
#include "launcher/tcpq_hub.hpp"

namespace haptree {
namespace {

using namespace std::chrono_literals;

int free_port() {
  const int s = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ::bind(s, reinterpret_cast<sockaddr*>(&a), sizeof a);
  socklen_t len = sizeof a;
  ::getsockname(s, reinterpret_cast<sockaddr*>(&a), &len);
  ::close(s);
  return ntohs(a.sin_port);
}

std::string tail(const std::string& path) {
  std::ifstream in(path);
  std::string all((std::istreambuf_iterator<char>(in)), {});
  return all.size() > 3000 ? all.substr(all.size() - 3000) : all;
}

// Connects once the server listens (it loads the molecule first).
std::unique_ptr<Receiver> connect_when_up(int port, double timeout_s = 20) {
  const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
  while (Clock::now() < end) {
    auto r = std::make_unique<Receiver>(port);
    if (r->fd >= 0) return r;
    std::this_thread::sleep_for(50ms);
  }
  return nullptr;
}

int stop_and_wait(pid_t pid) {
  ::kill(pid, SIGTERM);
  int status = 0;
  for (int i = 0; i < 500; ++i) {
    if (::waitpid(pid, &status, WNOHANG) == pid) return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
    std::this_thread::sleep_for(10ms);
  }
  ::kill(pid, SIGKILL);
  ::waitpid(pid, &status, 0);
  return -1;
}

TEST(ImdProcesses, ImdBridgeBesideSimServerServesAndPulls) {
  launcher::TcpqHub hub(0);
  const std::string url = hub.url();
  const int port = free_port();
  const std::string dir = ::testing::TempDir();
  const std::string sim_log = dir + "imd_proc_sim.log", imd_log = dir + "imd_proc_bridge.log";
  // The IMD pull is user 0 here (no haptic user): sim_server listens to users 0..--users-1.
  const pid_t sim = testing::spawn_logged({HAPTREE_SIM_SERVER, "--lcm-url", url, "--scene", "ala20", "--dt", "0.0005",
                                           "--rate-hz", "2000", "--display-rate-hz", "100", "--users", "1",
                                           "--max-user-force", "5000"},
                                          sim_log);
  const pid_t imd = testing::spawn_logged({HAPTREE_IMD_BRIDGE, "--lcm-url", url, "--scene", "ala20", "--port",
                                           std::to_string(port), "--user-id", "0", "--imd-version", "3"},
                                          imd_log);
  ASSERT_GT(sim, 0);
  ASSERT_GT(imd, 0);
  {
    auto r = connect_when_up(port);
    ASSERT_TRUE(r) << tail(imd_log);
    ASSERT_EQ(r->handshake(), 3);
    int32_t type, n;
    uint8_t flags[7];
    ASSERT_TRUE(r->header(type, n) && r->read_exact(flags, 7));
    ASSERT_TRUE(r->send_simple(3));
    Frame f0, f;
    ASSERT_TRUE(read_frame(*r, f0, true, 10)) << tail(imd_log) << tail(sim_log);
    const int a = static_cast<int>(f0.x.size() / 3) - 3;
    const Vec3 dir = Vec3(1, 1, 0).normalized();
    const float kj = 25.0f;   // kJ/(mol Å) (IMDv3's unit) = 250 kJ/(mol nm)
    ASSERT_TRUE(r->send_forces({a}, {kj * float(dir.x()), kj * float(dir.y()), 0.f}));
    // Pull for 1 ps of session time, however fast the loaded machine steps (deadline 60 s).
    const auto deadline = Clock::now() + 60s;
    do {
      ASSERT_TRUE(read_frame(*r, f, true, 5));
      ASSERT_LT(Clock::now(), deadline) << "session time " << f.time - f0.time << " ps";
    } while (f.time < f0.time + 1.0);
    const Vec3 dx(f.x[3 * a] - f0.x[3 * a], f.x[3 * a + 1] - f0.x[3 * a + 1], f.x[3 * a + 2] - f0.x[3 * a + 2]);
    std::printf("across processes: pulled atom moved %+.3f A along the force in 1 ps\n", dx.dot(dir));
    // Unpulled, this atom drifts ~1.2 Å along dir in 1 ps (ImdSession test); the pull gives ~10 Å.
    EXPECT_GT(dx.dot(dir), 3.0);
    ASSERT_TRUE(r->send_simple(0));
    EXPECT_TRUE(r->closed_by_peer());
  }
  EXPECT_EQ(stop_and_wait(imd), 0) << tail(imd_log);
  EXPECT_EQ(stop_and_wait(sim), 0) << tail(sim_log);
  hub.stop();
}

TEST(ImdProcesses, HaptreeRunImdPortServesTheEmbeddedSession) {
  const int port = free_port();
  const std::string log = ::testing::TempDir() + "imd_haptree_run.log";
  const pid_t run = testing::spawn_logged({HAPTREE_RUN, "--viewer-port", "0", "--scene", "ala20", "--dt", "0.0005", "--position-scale", "1",
                                           "--stiffness", "200", "--duration-s", "4", "--imd-port",
                                           std::to_string(port), "--imd-version", "3"},
                                          log);
  ASSERT_GT(run, 0);
  {
    auto r = connect_when_up(port);
    ASSERT_TRUE(r) << tail(log);
    ASSERT_EQ(r->handshake(), 3);
    int32_t type, n;
    uint8_t flags[7];
    ASSERT_TRUE(r->header(type, n) && r->read_exact(flags, 7));
    EXPECT_EQ(type, 10);
    ASSERT_TRUE(r->send_simple(3));
    Frame f;
    int64_t last = -1;
    for (int i = 0; i < 5; ++i) {
      ASSERT_TRUE(read_frame(*r, f, true, 5)) << tail(log);
      EXPECT_GT(f.step, last);
      last = f.step;
    }
    EXPECT_EQ(f.x.size(), 3u * 212u);
  }
  int status = 0;
  ASSERT_EQ(::waitpid(run, &status, 0), run);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << tail(log);
  // With --processes it says where the IMD server runs instead (exit 2).
  const pid_t bad = testing::spawn_logged({HAPTREE_RUN, "--processes", "--imd-port", std::to_string(port)}, log);
  ASSERT_EQ(::waitpid(bad, &status, 0), bad);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 2);
  EXPECT_NE(tail(log).find("imd_bridge"), std::string::npos) << tail(log);
}

}  // namespace
}  // namespace haptree
