// What the device_vendor tests share: running an executable with the fakes' environment, reaping it
// within a time, reading its output and the fake vendor libraries' force log (tests/device/fakes), and
// the fail-safe checks every run against a fake must pass.
#pragma once

#include <fcntl.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "tests/integration/spawn.hpp"

extern char** environ;

namespace haptree::vendor_test {

using Env = std::map<std::string, std::string>;

inline double unix_now() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}
inline void sleep_s(double s) { std::this_thread::sleep_for(std::chrono::duration<double>(s)); }

// Spawns argv with this process's environment, less any FAKE_HAPTIC_* (each run sets its own), plus
// `env`; stdout+stderr to `log`. Returns the pid, or -1.
inline pid_t spawn(const std::vector<std::string>& args, const Env& env, const std::string& log) {
  std::vector<std::string> envs;
  for (char** e = environ; *e; ++e)
    if (std::strncmp(*e, "FAKE_HAPTIC_", 12) != 0) envs.push_back(*e);
  for (const auto& kv : env) envs.push_back(kv.first + "=" + kv.second);
  std::vector<char*> envp;
  for (const auto& e : envs) envp.push_back(const_cast<char*>(e.c_str()));
  envp.push_back(nullptr);
  return testing::spawn_logged(args, log, /*search_path=*/false, envp.data());
}

// Waits up to timeout_s; exit code, 128 + signal, or -1 (still running: killed and reaped).
inline int reap(pid_t p, double timeout_s = 10) {
  int st = 0;
  for (double t = 0; t < timeout_s; t += 0.01) {
    if (::waitpid(p, &st, WNOHANG) == p) return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
    sleep_s(0.01);
  }
  ::kill(p, SIGKILL);
  ::waitpid(p, &st, 0);
  return -1;
}

inline std::string slurp(const std::string& path) {
  std::ifstream in(path);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// A loopback TCP port nothing listens on: bound, read, closed.
inline int free_port() {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a);
  socklen_t n = sizeof a;
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &n);
  ::close(fd);
  return ntohs(a.sin_port);
}

// One line of a fake vendor library's log (tests/device/fakes/fake_common.hpp).
struct Event {
  double t = 0;        // unix time, s
  std::string what;    // open, close, enable, disable, force, force_off, error
  double v[6] = {0, 0, 0, 0, 0, 0};   // force, torque (vendor units and axes)
  bool is_force() const { return what == "force" || what == "force_off"; }
  double norm() const { return std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }
  double torque_norm() const { return std::sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5]); }
  bool finite() const {
    return std::all_of(std::begin(v), std::end(v), [](double x) { return std::isfinite(x); });
  }
};
inline std::vector<Event> read_log(const std::string& path) {
  std::vector<Event> out;
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream ls(line);
    Event e;
    ls >> e.t >> e.what;
    for (double& x : e.v)
      if (!(ls >> x)) break;
    out.push_back(e);
  }
  return out;
}

// The log once the device is closed (up to 2 s after the process that closed it was reaped: one run in
// about a dozen under heavy load read it before the last lines were there).
inline std::vector<Event> read_log_until_closed(const std::string& path) {
  auto closed = [](const std::vector<Event>& v) {
    return std::any_of(v.begin(), v.end(), [](const Event& e) { return e.what == "close"; });
  };
  std::vector<Event> ev = read_log(path);
  for (int i = 0; i < 200 && !closed(ev); ++i) {
    sleep_s(0.01);
    ev = read_log(path);
  }
  return ev;
}

// The fail-safe ending every run must have: a zero force (and torque) is the last force written, then
// force output off, then the device closed; and a nonzero force was written before (else the check
// would prove nothing).
inline void expect_zero_last_then_off_then_closed(const std::vector<Event>& ev) {
  ASSERT_FALSE(ev.empty());
  int last_force = -1, last_nonzero = -1, last_disable = -1, last_close = -1;
  for (int i = 0; i < static_cast<int>(ev.size()); ++i) {
    if (ev[i].is_force()) last_force = i;
    if (ev[i].is_force() && (ev[i].norm() > 0 || ev[i].torque_norm() > 0)) last_nonzero = i;
    if (ev[i].what == "disable") last_disable = i;
    if (ev[i].what == "close") last_close = i;
  }
  ASSERT_GE(last_nonzero, 0) << "no force was ever rendered: the ending proves nothing";
  ASSERT_GE(last_force, 0);
  EXPECT_EQ(ev[last_force].norm(), 0.0) << "the last force written is not zero";
  EXPECT_EQ(ev[last_force].torque_norm(), 0.0) << "the last torque written is not zero";
  EXPECT_GT(last_disable, last_nonzero) << "force output not turned off after the last force";
  ASSERT_GE(last_close, 0) << "the device was not closed";
  EXPECT_GT(last_close, last_disable);
  for (size_t i = last_close + 1; i < ev.size(); ++i)
    EXPECT_EQ(ev[i].what, "error") << "the device was used after it was closed";   // a vendor error read at close
}

// Every force written before force output was first enabled is zero; returns the unix time of that
// first enable (-1, with a failure, if it never came).
inline double expect_no_force_before_enable(const std::vector<Event>& ev) {
  for (const auto& e : ev) {
    if (e.what == "enable") return e.t;
    if (e.is_force()) {
      EXPECT_EQ(e.norm(), 0.0) << "force written before force output was enabled";
    }
  }
  ADD_FAILURE() << "force output never enabled";
  return -1;
}

// No force is rendered before the first FEEDBACK: every force before the first "enable" is zero, and
// that enable comes after `first_feedback_t` (unix time).
inline void expect_no_force_before_feedback(const std::vector<Event>& ev, double first_feedback_t) {
  const double t_enable = expect_no_force_before_enable(ev);
  if (t_enable > 0) {
    EXPECT_GE(t_enable, first_feedback_t) << "force output enabled before the first FEEDBACK";
  }
}

}  // namespace haptree::vendor_test
