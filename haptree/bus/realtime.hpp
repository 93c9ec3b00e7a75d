// Real-time options of the processes: SCHED_FIFO, mlockall, CPU affinity, timer slack.
// apply_realtime() applies what the system permits and says, in plain words, what it refused and why;
// it never fails the process (a refused option means "continue as an ordinary process").
//   RealtimeOptions rt; add_realtime_options(app, rt);            // realtime_cli.hpp
//   CLI11_PARSE(...); log_realtime_report(apply_realtime(rt), "coupler");   // before any thread starts
// Call it before the process creates its threads: Linux applies policy and affinity per thread, and a new
// thread inherits its creator's. An I/O thread that blocks (the LCM handler) then gets a priority next to
// the loop's with set_io_thread_priority().
#pragma once

#include <string>
#include <thread>
#include <vector>

namespace haptree::bus {

struct RealtimeOptions {
  int sched_fifo = 0;          // SCHED_FIFO priority 1..98; 0: stay SCHED_OTHER
  bool mlockall = false;       // lock current and future pages (no page fault in the loop)
  std::vector<int> cpus;       // CPU affinity; empty: any CPU
  long timer_slack_ns = -1;    // prctl(PR_SET_TIMERSLACK); -1: leave the kernel's (50 µs for SCHED_OTHER)
  bool busy_poll = false;      // process-specific: poll the device link between ticks instead of sleeping
  bool any() const { return sched_fifo > 0 || mlockall || !cpus.empty() || timer_slack_ns >= 0; }
};

struct RealtimeReport {
  std::vector<std::string> applied;   // e.g. "SCHED_FIFO priority 80"
  std::vector<std::string> refused;   // e.g. "SCHED_FIFO priority 80 refused (EPERM): ...; continuing with SCHED_OTHER"
  std::vector<std::string> notes;     // advice that is not a refusal (spinning under SCHED_FIFO, RT throttling)
  bool fifo = false;                  // SCHED_FIFO is in force for the calling thread
  int fifo_priority = 0;
};

// Applies o to the calling thread (and, through inheritance, to the threads it creates later).
RealtimeReport apply_realtime(const RealtimeOptions& o);

// Logs the report at info (applied, notes) and warn (refused) level, prefixed with the process name.
void log_realtime_report(const RealtimeReport& r, const std::string& process);

// Gives a blocking I/O thread SCHED_FIFO next to the loop's priority (when the loop got SCHED_FIFO):
//  above_loop: priority + 1, it preempts a spinning loop on its CPU when a message arrives (the thread
//    carries what the loop needs: poses and feedback over udpm, snapshots);
//  otherwise priority - 1, it never delays the loop (with every udpm datagram of the group waking each
//    process's handler, a handler above the loop stalled the shm pose-to-force path).
// Returns "" or a refusal in plain words.
std::string set_io_thread_priority(std::thread::native_handle_type thread, const RealtimeReport& r, bool above_loop);

// "0", "0,1", "2-3", "0,2-3" -> sorted unique CPU ids. On a syntax error returns {} and sets *error.
std::vector<int> parse_cpu_list(const std::string& text, std::string* error);

// CPUs this process may run on (sched_getaffinity), as "0-1".
std::string allowed_cpus_text();

// The kernel's RT throttling: sched_rt_runtime_us / sched_rt_period_us (-1 if unreadable or unlimited).
double rt_throttle_fraction();

}  // namespace haptree::bus
