// Runs a function in a forked child inside a private network namespace (unshare(CLONE_NEWNET)), so LCM
// udpm traffic cannot leave the machine: only the namespace's own loopback exists there.
// Needs root (CAP_SYS_ADMIN); without it the caller gets a clear failure, not a skip.
#pragma once

#include <sched.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <string>

// In the child: on a failed check, write the reason (printf-style) to fd and return 1 from fn.
#define CHILD_CHECK(cond, fd, ...) \
  do {                             \
    if (!(cond)) {                 \
      dprintf(fd, __VA_ARGS__);    \
      return 1;                    \
    }                              \
  } while (0)

namespace haptree::testing {

struct NetnsResult {
  int exit_code = -1;  // the function's return value; 97 = namespace set-up failed
  std::string output;  // what the child wrote to the pipe (reasons, numbers)
};

// Set-up commands for loopback multicast inside the namespace (same as tests/run_in_netns.sh would do).
inline const char* kNetnsMulticastSetup =
    "ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo";

// fn(out_fd) runs in the child after unshare and `setup` (a shell command, may be empty); it writes any
// message to out_fd and returns the exit code.
inline NetnsResult run_in_private_netns(const std::string& setup, const std::function<int(int)>& fn) {
  NetnsResult res;
  int fds[2];
  if (::pipe(fds) != 0) {
    res.output = std::string("pipe failed: ") + std::strerror(errno);
    return res;
  }
  std::fflush(nullptr);
  const pid_t pid = ::fork();
  if (pid < 0) {
    res.output = std::string("fork failed: ") + std::strerror(errno);
    return res;
  }
  if (pid == 0) {
    ::close(fds[0]);
    int code = 97;
    if (::unshare(CLONE_NEWNET) != 0) {
      dprintf(fds[1],
              "unshare(CLONE_NEWNET) failed: %s. The udpm tests need a private network namespace so no "
              "traffic leaves the machine: run them as root (CI does), or exclude them with `ctest -LE netns`.",
              std::strerror(errno));
    } else if (!setup.empty() && std::system((setup + " 2>&1").c_str()) != 0) {
      dprintf(fds[1], "network namespace set-up failed: `%s` (is iproute2 installed?)", setup.c_str());
    } else {
      code = fn(fds[1]);
    }
    ::close(fds[1]);
    ::_exit(code);
  }
  ::close(fds[1]);
  char buf[4096];
  for (ssize_t n; (n = ::read(fds[0], buf, sizeof buf)) > 0;) res.output.append(buf, static_cast<size_t>(n));
  ::close(fds[0]);
  int status = 0;
  ::waitpid(pid, &status, 0);
  res.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
  return res;
}

}  // namespace haptree::testing
