#include "haptree/bus/realtime.hpp"

#include <pthread.h>
#include <sched.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <sys/resource.h>

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <set>
#include <sstream>

namespace haptree::bus {
namespace {

std::string errno_name(int e) {
  switch (e) {
    case EPERM: return "EPERM";
    case EINVAL: return "EINVAL";
    case ENOMEM: return "ENOMEM";
    case EAGAIN: return "EAGAIN";
    case ESRCH: return "ESRCH";
    default: return "errno " + std::to_string(e);
  }
}

std::string rlimit_text(int resource) {
  rlimit l{};
  if (getrlimit(resource, &l) != 0) return "unknown";
  if (l.rlim_cur == RLIM_INFINITY) return "unlimited";
  return std::to_string(static_cast<unsigned long long>(l.rlim_cur));
}

std::string cpus_text(const std::vector<int>& cpus) {
  std::string s;
  for (size_t i = 0; i < cpus.size(); ++i) {
    size_t j = i;
    while (j + 1 < cpus.size() && cpus[j + 1] == cpus[j] + 1) ++j;
    if (!s.empty()) s += ",";
    s += std::to_string(cpus[i]);
    if (j > i) s += "-" + std::to_string(cpus[j]);
    i = j;
  }
  return s;
}

std::vector<int> allowed_cpus() {
  std::vector<int> v;
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof(set), &set) != 0) return v;
  for (int c = 0; c < CPU_SETSIZE; ++c)
    if (CPU_ISSET(c, &set)) v.push_back(c);
  return v;
}

void apply_fifo(const RealtimeOptions& o, RealtimeReport& r) {
  const int lo = sched_get_priority_min(SCHED_FIFO), hi = sched_get_priority_max(SCHED_FIFO);
  const std::string what = "SCHED_FIFO priority " + std::to_string(o.sched_fifo);
  if (o.sched_fifo < lo || o.sched_fifo > hi) {
    r.refused.push_back(what + " refused: the priority must be in " + std::to_string(lo) + ".." + std::to_string(hi) +
                        "; continuing with SCHED_OTHER");
    return;
  }
  sched_param p{};
  p.sched_priority = o.sched_fifo;
  const int e = pthread_setschedparam(pthread_self(), SCHED_FIFO, &p);
  if (e != 0) {
    std::string why = e == EPERM ? ": run as root, give the binary CAP_SYS_NICE (setcap cap_sys_nice+ep) or raise "
                                   "RLIMIT_RTPRIO (ulimit -r, now " + rlimit_text(RLIMIT_RTPRIO) + ")"
                                 : std::string(": ") + std::strerror(e);
    r.refused.push_back(what + " refused (" + errno_name(e) + ")" + why + "; continuing with SCHED_OTHER");
    return;
  }
  r.fifo = true;
  r.fifo_priority = o.sched_fifo;
  r.applied.push_back(what);
  const double share = rt_throttle_fraction();
  if (o.busy_poll && share > 0 && share < 1)
    r.notes.push_back("a thread that spins under SCHED_FIFO is throttled by the kernel after " +
                      std::to_string(static_cast<int>(share * 100 + 0.5)) +
                      " % of each RT period (sched_rt_runtime_us): expect stalls of tens of ms once a second");
}

void apply_mlockall(RealtimeReport& r) {
  if (mlockall(MCL_CURRENT | MCL_FUTURE) == 0) {
    r.applied.push_back("mlockall (current and future pages locked)");
    return;
  }
  const int e = errno;
  std::string why;
  if (e == ENOMEM || e == EPERM)
    why = ": RLIMIT_MEMLOCK (ulimit -l) is " + rlimit_text(RLIMIT_MEMLOCK) +
          " bytes, below what the process maps; run as root (CAP_IPC_LOCK) or raise it";
  else
    why = std::string(": ") + std::strerror(e);
  r.refused.push_back("mlockall refused (" + errno_name(e) + ")" + why +
                      "; continuing with pageable memory (a page fault can stall the loop)");
}

void apply_affinity(const RealtimeOptions& o, RealtimeReport& r) {
  const std::vector<int> allowed = allowed_cpus();
  std::vector<int> bad;
  for (int c : o.cpus)
    if (c < 0 || c >= CPU_SETSIZE || !std::binary_search(allowed.begin(), allowed.end(), c)) bad.push_back(c);
  const std::string what = "CPU affinity " + cpus_text(o.cpus);
  if (!bad.empty()) {
    r.refused.push_back(what + " refused: CPU " + cpus_text(bad) + " does not exist or is not allowed to this process "
                        "(allowed: " + cpus_text(allowed) + "); continuing on CPUs " + cpus_text(allowed));
    return;
  }
  cpu_set_t set;
  CPU_ZERO(&set);
  for (int c : o.cpus) CPU_SET(c, &set);
  const int e = pthread_setaffinity_np(pthread_self(), sizeof(set), &set);
  if (e != 0) {
    r.refused.push_back(what + " refused (" + errno_name(e) + "): " + std::strerror(e) + "; continuing on CPUs " +
                        cpus_text(allowed));
    return;
  }
  r.applied.push_back(what);
}

void apply_timer_slack(const RealtimeOptions& o, RealtimeReport& r) {
  const long ns = std::max(1L, o.timer_slack_ns);   // 0 would mean "back to the default"
  if (prctl(PR_SET_TIMERSLACK, static_cast<unsigned long>(ns), 0, 0, 0) != 0) {
    const int e = errno;
    r.refused.push_back("timer slack " + std::to_string(ns) + " ns refused (" + errno_name(e) +
                        "); continuing with the default slack (sleeps may end up to 50 us late)");
    return;
  }
  r.applied.push_back("timer slack " + std::to_string(ns) + " ns");
}

}  // namespace

RealtimeReport apply_realtime(const RealtimeOptions& o) {
  RealtimeReport r;
  if (o.mlockall) apply_mlockall(r);   // first: the pages the other steps touch are locked too
  if (!o.cpus.empty()) apply_affinity(o, r);
  if (o.timer_slack_ns >= 0) apply_timer_slack(o, r);
  if (o.sched_fifo != 0) apply_fifo(o, r);
  return r;
}

void log_realtime_report(const RealtimeReport& r, const std::string& process) {
  for (const auto& s : r.applied) spdlog::info("{}: real-time: {}", process, s);
  for (const auto& s : r.refused) spdlog::warn("{}: real-time: {}", process, s);
  for (const auto& s : r.notes) spdlog::info("{}: real-time: note: {}", process, s);
}

std::string set_io_thread_priority(std::thread::native_handle_type thread, const RealtimeReport& r, bool above_loop) {
  if (!r.fifo) return "";
  sched_param p{};
  p.sched_priority = std::clamp(r.fifo_priority + (above_loop ? 1 : -1), sched_get_priority_min(SCHED_FIFO),
                                sched_get_priority_max(SCHED_FIFO));
  const int e = pthread_setschedparam(thread, SCHED_FIFO, &p);
  if (e == 0) return "";
  return "I/O thread SCHED_FIFO priority " + std::to_string(p.sched_priority) + " refused (" + errno_name(e) +
         "); it keeps the loop's priority";
}

std::vector<int> parse_cpu_list(const std::string& text, std::string* error) {
  std::set<int> cpus;
  std::stringstream ss(text);
  std::string item;
  auto fail = [&](const std::string& why) {
    if (error) *error = "'" + text + "': " + why + " (expected CPU ids such as 1, 0,1 or 0-1)";
    return std::vector<int>{};
  };
  if (text.empty()) return fail("empty CPU list");
  auto number = [](const std::string& s, int* out) {
    if (s.empty() || s.size() > 6 || s.find_first_not_of("0123456789") != std::string::npos) return false;
    *out = std::stoi(s);
    return true;
  };
  while (std::getline(ss, item, ',')) {
    const auto dash = item.find('-');
    int a = 0, b = 0;
    if (dash == std::string::npos) {
      if (!number(item, &a)) return fail("'" + item + "' is not a CPU id");
      b = a;
    } else if (!number(item.substr(0, dash), &a) || !number(item.substr(dash + 1), &b) || b < a) {
      return fail("'" + item + "' is not a CPU range");
    }
    if (b > 4095) return fail("CPU " + std::to_string(b) + " is beyond 4095");
    for (int c = a; c <= b; ++c) cpus.insert(c);
  }
  if (cpus.empty() || text.back() == ',') return fail("empty item");
  return {cpus.begin(), cpus.end()};
}

std::string allowed_cpus_text() { return cpus_text(allowed_cpus()); }

double rt_throttle_fraction() {
  long runtime = 0, period = 0;
  std::ifstream a("/proc/sys/kernel/sched_rt_runtime_us"), b("/proc/sys/kernel/sched_rt_period_us");
  if (!(a >> runtime) || !(b >> period) || runtime < 0 || period <= 0) return -1;
  return static_cast<double>(runtime) / static_cast<double>(period);
}

}  // namespace haptree::bus
