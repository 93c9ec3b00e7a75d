// The real executables refuse out-of-range option values in plain words (they used
// to accept them: `coupler --rate-hz 0` spun at 100 % CPU and ignored SIGTERM), and SIGTERM stops every
// loop — the coupler's busy-wait pacing included — within a fraction of a second. memq:// keeps each
// process to itself: an accepted bad value would make it run, not fail on the network.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "tests/integration/spawn.hpp"

namespace haptree {
namespace {

using Clock = std::chrono::steady_clock;

// Waits up to timeout_s for p; returns its exit code (128 + signal if killed), or -1 after SIGKILLing a
// process that did not exit in time.
int wait_for(pid_t p, double timeout_s, double* waited_s = nullptr) {
  const auto t0 = Clock::now();
  int st = 0;
  while (::waitpid(p, &st, WNOHANG) == 0) {
    if (std::chrono::duration<double>(Clock::now() - t0).count() > timeout_s) {
      ::kill(p, SIGKILL);
      ::waitpid(p, &st, 0);
      return -1;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  if (waited_s) *waited_s = std::chrono::duration<double>(Clock::now() - t0).count();
  return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
}

std::string slurp(const std::string& path) {
  std::ifstream f(path);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

struct Case {
  std::vector<std::string> args;
  std::string option;   // must be named in the error
};

TEST(Options, OutOfRangeValuesAreRefusedInPlainWords) {
  const std::string memq = "memq://";
  const std::vector<Case> cases = {
      {{HAPTREE_COUPLER, "--coupler-rate-hz", "0"}, "--coupler-rate-hz"},
      {{HAPTREE_COUPLER, "--coupler-rate-hz", "-5"}, "--coupler-rate-hz"},
      {{HAPTREE_COUPLER, "--coupler-rate-hz", "nan"}, "--coupler-rate-hz"},
      {{HAPTREE_COUPLER, "--max-force-n", "-1"}, "--max-force-n"},
      {{HAPTREE_COUPLER, "--stiffness", "nan"}, "--stiffness"},
      {{HAPTREE_COUPLER, "--stale-after-s", "0"}, "--stale-after-s"},
      {{HAPTREE_COUPLER, "--user-force-rate-hz", "inf"}, "--user-force-rate-hz"},
      {{HAPTREE_COUPLER, "--force-scale", "0"}, "--force-scale"},
      {{HAPTREE_COUPLER, "--model-fingerprint", "not-hex"}, "--model-fingerprint"},
      {{HAPTREE_DEVICE_BRIDGE, "--device-rate-hz", "0"}, "--device-rate-hz"},
      {{HAPTREE_DEVICE_BRIDGE, "--max-force-n", "nan"}, "--max-force-n"},
      {{HAPTREE_SIM_SERVER, "--dt", "0"}, "--dt"},
      {{HAPTREE_SIM_SERVER, "--dt", "-0.001"}, "--dt"},
      {{HAPTREE_SIM_SERVER, "--dt", "nan"}, "--dt"},
      {{HAPTREE_SIM_SERVER, "--users", "-3"}, "--users"},
      {{HAPTREE_SIM_SERVER, "--budget-dofs", "-1"}, "--budget-dofs"},
      {{HAPTREE_SIM_SERVER, "--n", "0"}, "--n"},
      {{HAPTREE_SIM_SERVER, "--sim-rate-hz", "-1"}, "--sim-rate-hz"},
      {{HAPTREE_SIM_SERVER, "--max-user-force", "0"}, "--max-user-force"},
      {{HAPTREE_IMD_BRIDGE, "--scene", "ala20", "--imd-port", "70000"}, "--imd-port"},
      {{HAPTREE_VIEWER, "--viewer-port", "-1"}, "--viewer-port"},
      {{HAPTREE_RUN, "--dt", "0"}, "--dt"},
      {{HAPTREE_RUN, "--coupler-rate-hz", "0"}, "--coupler-rate-hz"},
      {{HAPTREE_RUN, "--sim-rate-hz", "nan"}, "--sim-rate-hz"},
  };
  const std::string dir = ::testing::TempDir();
  int i = 0;
  for (const auto& c : cases) {
    std::vector<std::string> args = c.args;
    if (args[0] != HAPTREE_RUN) args.insert(args.end(), {"--lcm-url", memq});
    const std::string log = dir + "options_case_" + std::to_string(i++) + ".log";
    const pid_t p = testing::spawn_logged(args, log);
    ASSERT_GT(p, 0);
    const int rc = wait_for(p, 5.0);
    const std::string out = slurp(log);
    std::string cmd;
    for (const auto& a : c.args) cmd += a + " ";
    EXPECT_NE(rc, -1) << cmd << ": still running after 5 s (the value was accepted)";
    EXPECT_NE(rc, 0) << cmd << ": exit 0";
    EXPECT_NE(out.find(c.option), std::string::npos) << cmd << ": the error does not name " << c.option << ":\n" << out;
  }
}

// SIGTERM ends each process within 0.5 s, at a loop rate of 1 Hz (one period = 1 s): every sleep and
// busy wait checks the stop flag. The coupler busy-waits by default.
TEST(Options, SigtermStopsEveryLoopPromptly) {
  const std::string dir = ::testing::TempDir();
  const std::vector<std::vector<std::string>> procs = {
      // --clamp-gains: at 1 Hz the default stiffness exceeds the passivity bound 2b/T (device_info.hpp)
      {HAPTREE_COUPLER, "--lcm-url", "memq://", "--coupler-rate-hz", "1", "--clamp-gains"},
      {HAPTREE_COUPLER, "--lcm-url", "memq://", "--coupler-rate-hz", "1", "--sleep", "--clamp-gains"},
      {HAPTREE_DEVICE_BRIDGE, "--lcm-url", "memq://", "--device-rate-hz", "1"},
      {HAPTREE_SIM_SERVER, "--lcm-url", "memq://", "--scene", "chain", "--n", "8", "--sim-rate-hz", "1"},
  };
  int i = 0;
  for (const auto& args : procs) {
    const std::string log = dir + "sigterm_case_" + std::to_string(i++) + ".log";
    const pid_t p = testing::spawn_logged(args, log);
    ASSERT_GT(p, 0);
    std::this_thread::sleep_for(std::chrono::milliseconds(1300));   // mid-period of the 1 Hz loop
    ASSERT_EQ(::kill(p, SIGTERM), 0);
    double waited = -1;
    const int rc = wait_for(p, 3.0, &waited);
    std::printf("%s: exit %d %.0f ms after SIGTERM\n", args[0].c_str(), rc, 1e3 * waited);
    EXPECT_EQ(rc, 0) << args[0] << " (log " << log << ")";
    EXPECT_LT(waited, 0.5) << args[0];
  }
}

}  // namespace
}  // namespace haptree
