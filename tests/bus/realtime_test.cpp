// Tests for haptree/bus/realtime.hpp: option parsing, what is applied when permitted, and the refusals in
// words. Every apply runs in a forked child (SCHED_FIFO, mlockall and affinity must not leak into the test
// process); the child does no work under SCHED_FIFO and is bounded by alarm(), so it cannot hog a CPU.
#include "haptree/bus/realtime.hpp"

#include <gtest/gtest.h>
#include <pthread.h>
#include <sched.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstring>
#include <fstream>
#include <functional>
#include <string>
#include <thread>

#include "haptree/bus/realtime_cli.hpp"

namespace haptree::bus {
namespace {

// Runs fn in a child process and returns the text it wrote (fn's return value).
std::string in_child(const std::function<std::string()>& fn) {
  int fd[2];
  if (pipe(fd) != 0) return "pipe failed";
  const pid_t pid = fork();
  if (pid == 0) {
    close(fd[0]);
    alarm(10);   // bound: the child never outlives 10 s
    const std::string s = fn();
    ssize_t off = 0;
    while (off < static_cast<ssize_t>(s.size())) {
      const ssize_t n = write(fd[1], s.data() + off, s.size() - off);
      if (n <= 0) break;
      off += n;
    }
    _exit(0);
  }
  close(fd[1]);
  std::string out;
  char buf[512];
  ssize_t n;
  while ((n = read(fd[0], buf, sizeof buf)) > 0) out.append(buf, static_cast<size_t>(n));
  close(fd[0]);
  int status = 0;
  waitpid(pid, &status, 0);
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) out += "|child died";
  return out;
}

std::string join(const RealtimeReport& r) {
  std::string s;
  for (const auto& a : r.applied) s += "A:" + a + "\n";
  for (const auto& a : r.refused) s += "R:" + a + "\n";
  return s;
}

// CAP_SYS_NICE (bit 23) in the effective set, or an RLIMIT_RTPRIO that allows prio: SCHED_FIFO permitted.
bool fifo_permitted(int prio) {
  std::ifstream f("/proc/self/status");
  std::string line;
  while (std::getline(f, line))
    if (line.rfind("CapEff:", 0) == 0 && (std::stoull(line.substr(7), nullptr, 16) >> 23) & 1) return true;
  rlimit l{};
  return getrlimit(RLIMIT_RTPRIO, &l) == 0 && (l.rlim_cur == RLIM_INFINITY || l.rlim_cur >= static_cast<rlim_t>(prio));
}

// Drops to an unprivileged user (if root) with RLIMIT_RTPRIO and RLIMIT_MEMLOCK at 0: both must be refused.
bool drop_privileges() {
  rlimit zero{0, 0};
  if (setrlimit(RLIMIT_RTPRIO, &zero) != 0 || setrlimit(RLIMIT_MEMLOCK, &zero) != 0) return false;
  if (geteuid() == 0 && (setgid(65534) != 0 || setuid(65534) != 0)) return false;
  return true;
}

TEST(RealtimeCpuList, Parses) {
  std::string err;
  EXPECT_EQ(parse_cpu_list("1", &err), (std::vector<int>{1}));
  EXPECT_EQ(parse_cpu_list("0,1", &err), (std::vector<int>{0, 1}));
  EXPECT_EQ(parse_cpu_list("2-4,0,3", &err), (std::vector<int>{0, 2, 3, 4}));
  for (const char* bad : {"", "a", "1,", "3-1", "-1", "1-", "0,,1", "99999"}) {
    err.clear();
    EXPECT_TRUE(parse_cpu_list(bad, &err).empty()) << bad;
    EXPECT_NE(err.find("expected CPU ids"), std::string::npos) << bad << ": " << err;
  }
}

TEST(RealtimeCli, ParsesAndRejects) {
  {
    CLI::App app;
    RealtimeOptions o;
    add_realtime_options(app, o, "poll");
    EXPECT_NO_THROW(app.parse(std::vector<std::string>{"1", "--cpu-affinity", "--busy-poll", "--mlockall",
                                                       "80", "--sched-fifo", "1000", "--timer-slack-ns"}));
    // CLI11 takes the vector in reverse order
    EXPECT_EQ(o.sched_fifo, 80);
    EXPECT_TRUE(o.mlockall);
    EXPECT_TRUE(o.busy_poll);
    EXPECT_EQ(o.cpus, (std::vector<int>{1}));
    EXPECT_EQ(o.timer_slack_ns, 1000);
    EXPECT_TRUE(o.any());
  }
  {
    CLI::App app;
    RealtimeOptions o;
    add_realtime_options(app, o);
    EXPECT_FALSE(o.any());   // defaults: nothing real-time
    EXPECT_THROW(app.parse(std::vector<std::string>{"0", "--sched-fifo"}), CLI::ValidationError);
  }
  for (const char* bad : {"99", "0"}) {
    CLI::App app;
    RealtimeOptions o;
    add_realtime_options(app, o);
    EXPECT_THROW(app.parse(std::vector<std::string>{bad, "--sched-fifo"}), CLI::ValidationError) << bad;
  }
  {
    CLI::App app;
    RealtimeOptions o;
    add_realtime_options(app, o);
    EXPECT_THROW(app.parse(std::vector<std::string>{"x", "--cpu-affinity"}), CLI::ValidationError);
  }
  {
    CLI::App app;
    RealtimeOptions o;
    add_realtime_options(app, o);
    EXPECT_THROW(app.parse(std::vector<std::string>{"--busy-poll"}), CLI::ParseError);   // not offered
  }
}

TEST(RealtimeApply, NothingRequestedNothingDone) {
  const RealtimeReport r = apply_realtime(RealtimeOptions{});
  EXPECT_TRUE(r.applied.empty());
  EXPECT_TRUE(r.refused.empty());
  EXPECT_FALSE(r.fifo);
}

TEST(RealtimeApply, FifoAppliedWhenPermittedOtherwiseRefusedInWords) {
  const bool permitted = fifo_permitted(1);
  const std::string out = in_child([] {
    RealtimeOptions o;
    o.sched_fifo = 1;   // lowest priority, and the child only reads it back: nothing spins
    const RealtimeReport r = apply_realtime(o);
    int policy = -1;
    sched_param p{};
    pthread_getschedparam(pthread_self(), &policy, &p);
    return join(r) + "policy=" + std::to_string(policy) + " prio=" + std::to_string(p.sched_priority) +
           " fifo=" + std::to_string(r.fifo);
  });
  if (permitted) {
    EXPECT_NE(out.find("A:SCHED_FIFO priority 1\n"), std::string::npos) << out;
    EXPECT_NE(out.find("policy=" + std::to_string(SCHED_FIFO) + " prio=1 fifo=1"), std::string::npos) << out;
  } else {
    EXPECT_NE(out.find("R:SCHED_FIFO priority 1 refused (EPERM)"), std::string::npos) << out;
    EXPECT_NE(out.find("continuing with SCHED_OTHER"), std::string::npos) << out;
    EXPECT_NE(out.find("policy=" + std::to_string(SCHED_OTHER)), std::string::npos) << out;
  }
}

TEST(RealtimeApply, RefusalsWithoutPrivilegesAreSaidAndTheProcessContinues) {
  const std::string out = in_child([] {
    if (!drop_privileges()) return std::string("could not drop privileges");
    RealtimeOptions o;
    o.sched_fifo = 50;
    o.mlockall = true;
    const RealtimeReport r = apply_realtime(o);
    int policy = -1;
    sched_param p{};
    pthread_getschedparam(pthread_self(), &policy, &p);
    return join(r) + "policy=" + std::to_string(policy) + " fifo=" + std::to_string(r.fifo);
  });
  EXPECT_NE(out.find("R:SCHED_FIFO priority 50 refused (EPERM): run as root"), std::string::npos) << out;
  EXPECT_NE(out.find("RLIMIT_RTPRIO (ulimit -r, now 0)"), std::string::npos) << out;
  EXPECT_NE(out.find("R:mlockall refused ("), std::string::npos) << out;
  EXPECT_NE(out.find("RLIMIT_MEMLOCK (ulimit -l) is 0 bytes"), std::string::npos) << out;
  EXPECT_NE(out.find("policy=" + std::to_string(SCHED_OTHER) + " fifo=0"), std::string::npos) << out;
  EXPECT_EQ(out.find("A:"), std::string::npos) << out;
}

TEST(RealtimeApply, AffinityAppliedOrRefusedForAMissingCpu) {
  // The first CPU this process may use: pinning to it is always permitted.
  cpu_set_t set;
  CPU_ZERO(&set);
  ASSERT_EQ(sched_getaffinity(0, sizeof set, &set), 0);
  int first = -1, count = 0;
  for (int c = CPU_SETSIZE - 1; c >= 0; --c)
    if (CPU_ISSET(c, &set)) first = c, ++count;
  ASSERT_GE(first, 0);
  const std::string ok = in_child([first] {
    RealtimeOptions o;
    o.cpus = {first};
    const RealtimeReport r = apply_realtime(o);
    cpu_set_t now;
    CPU_ZERO(&now);
    sched_getaffinity(0, sizeof now, &now);
    return join(r) + "count=" + std::to_string(CPU_COUNT(&now)) + " has=" + std::to_string(CPU_ISSET(first, &now) != 0);
  });
  EXPECT_NE(ok.find("A:CPU affinity " + std::to_string(first) + "\n"), std::string::npos) << ok;
  EXPECT_NE(ok.find("count=1 has=1"), std::string::npos) << ok;

  const std::string bad = in_child([first] {
    RealtimeOptions o;
    o.cpus = {first, 4000};   // no such CPU here (CPU_SETSIZE is 1024)
    const RealtimeReport r = apply_realtime(o);
    cpu_set_t now;
    CPU_ZERO(&now);
    sched_getaffinity(0, sizeof now, &now);
    return join(r) + "count=" + std::to_string(CPU_COUNT(&now));
  });
  EXPECT_NE(bad.find("R:CPU affinity " + std::to_string(first) + ",4000 refused: CPU 4000 does not exist or is not "
                     "allowed to this process (allowed: " + allowed_cpus_text() + ")"), std::string::npos) << bad;
  EXPECT_NE(bad.find("count=" + std::to_string(count)), std::string::npos) << bad;   // unchanged
}

TEST(RealtimeApply, MlockallAndTimerSlackWhenPermitted) {
  const bool root = geteuid() == 0;
  const std::string out = in_child([] {
    RealtimeOptions o;
    o.mlockall = true;
    o.timer_slack_ns = 1000;
    const RealtimeReport r = apply_realtime(o);
    std::ifstream f("/proc/self/status");
    std::string line, locked;
    while (std::getline(f, line))
      if (line.rfind("VmLck:", 0) == 0) locked = line;
    return join(r) + "slack=" + std::to_string(prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0)) + " " + locked;
  });
  EXPECT_NE(out.find("A:timer slack 1000 ns"), std::string::npos) << out;
  EXPECT_NE(out.find("slack=1000"), std::string::npos) << out;
  if (root) {
    EXPECT_NE(out.find("A:mlockall"), std::string::npos) << out;
    EXPECT_EQ(out.find("VmLck:\t       0 kB"), std::string::npos) << out;   // something is locked
  } else {
    EXPECT_TRUE(out.find("A:mlockall") != std::string::npos || out.find("R:mlockall refused") != std::string::npos)
        << out;
  }
}

TEST(RealtimeApply, IoThreadNextToTheLoopPriority) {
  const bool permitted = fifo_permitted(11);
  const std::string out = in_child([] {
    RealtimeOptions o;
    o.sched_fifo = 10;
    const RealtimeReport r = apply_realtime(o);
    std::string s;
    for (bool above : {true, false}) {
      int fd[2];
      if (pipe(fd) != 0) return std::string("pipe failed");
      std::thread t([&] {   // blocks in read() until released: it never runs under SCHED_FIFO for long
        char c;
        (void)!read(fd[0], &c, 1);
      });
      const std::string w = set_io_thread_priority(t.native_handle(), r, above);
      int policy = -1;
      sched_param p{};
      pthread_getschedparam(t.native_handle(), &policy, &p);
      s += "[" + w + "] policy=" + std::to_string(policy) + " prio=" + std::to_string(p.sched_priority) + "\n";
      (void)!write(fd[1], "x", 1);
      t.join();
      close(fd[0]);
      close(fd[1]);
    }
    return s;
  });
  if (permitted) {
    EXPECT_EQ(out, "[] policy=" + std::to_string(SCHED_FIFO) + " prio=11\n[] policy=" + std::to_string(SCHED_FIFO) +
                       " prio=9\n");
  } else {   // the loop stayed SCHED_OTHER: the thread is left alone, nothing to say
    EXPECT_EQ(out, "[] policy=" + std::to_string(SCHED_OTHER) + " prio=0\n[] policy=" + std::to_string(SCHED_OTHER) +
                       " prio=0\n");
  }
}

TEST(RealtimeApply, BadPriorityRefusedInWords) {
  RealtimeOptions o;
  o.sched_fifo = 1000;   // the CLI refuses it; the library says why too
  const RealtimeReport r = apply_realtime(o);
  ASSERT_EQ(r.refused.size(), 1u);
  EXPECT_NE(r.refused[0].find("SCHED_FIFO priority 1000 refused: the priority must be in 1..99"), std::string::npos)
      << r.refused[0];
  EXPECT_FALSE(r.fifo);
}

}  // namespace
}  // namespace haptree::bus
