// Command-line options for realtime.hpp, shared by the processes. Header-only: the process links CLI11.
//   RealtimeOptions rt; add_realtime_options(app, rt, /*busy_poll=*/"help text or empty for none");
#pragma once

#include <CLI/CLI.hpp>

#include <string>

#include "haptree/bus/realtime.hpp"

namespace haptree::bus {

// busy_poll_help: the process's meaning of --busy-poll; "" = the process has no --busy-poll.
inline void add_realtime_options(CLI::App& app, RealtimeOptions& o, const std::string& busy_poll_help = "") {
  app.add_option("--sched-fifo", o.sched_fifo,
                 "run the loop as SCHED_FIFO with this priority (1-98; needs root, CAP_SYS_NICE or RLIMIT_RTPRIO); "
                 "refused: said in the log, the process continues as SCHED_OTHER")
      ->check(CLI::Range(1, 98))
      ->group("Real-time");
  app.add_flag("--mlockall", o.mlockall, "lock all pages in memory (no page fault in the loop); refused: said, continues")
      ->group("Real-time");
  app.add_option_function<std::string>(
         "--cpu-affinity",
         [&o](const std::string& s) {
           std::string err;
           o.cpus = parse_cpu_list(s, &err);
           if (o.cpus.empty()) throw CLI::ValidationError("--cpu-affinity", err);
         },
         "pin the process to these CPUs, e.g. 1 or 0,1 or 0-1 (a CPU that does not exist: said, continues on any)")
      ->type_name("CPUS")
      ->group("Real-time");
  app.add_option("--timer-slack-ns", o.timer_slack_ns,
                 "timer slack of the process's sleeps, ns (the kernel's default for SCHED_OTHER is 50000)")
      ->check(CLI::Range(1L, 100000000L))
      ->group("Real-time");
  if (!busy_poll_help.empty()) app.add_flag("--busy-poll", o.busy_poll, busy_poll_help)->group("Real-time");
}

}  // namespace haptree::bus
