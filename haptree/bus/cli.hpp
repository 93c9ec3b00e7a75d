// Command-line options shared by the processes. Header-only: the process links CLI11.
//   BusOptions bus_opts; add_bus_options(app, bus_opts);
#pragma once

#include <CLI/CLI.hpp>

#include "haptree/bus/shm_channel.hpp"

#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdlib>
#include <string>

#include "haptree/bus/auth.hpp"

namespace haptree::bus {

struct BusOptions {
  std::string lcm_url = "udpm://239.255.76.67:7667?ttl=0";  // LCM's default; memq:// for one process
  std::string channel_suffix;                              // appended to every channel name
  bool shm = false;                                        // device <-> coupler link over shared memory
  double mirror_rate_hz = 100.0;                           // shm -> LCM mirror rate (0 = no mirror)
  std::string session_key_file;                            // keyed session (auth.hpp); "" = none
};

// A finite number in [lo, hi] (lo excluded when open_lo). CLI::Range lets NaN through (every comparison
// with NaN is false), so every floating-point option of the processes uses this instead. The message
// names the allowed range in plain words; CLI11 prefixes it with the option's name.
inline CLI::Validator finite_in(double lo, double hi, bool open_lo = false) {
  const std::string range = (open_lo ? "(" : "[") + CLI::detail::to_string(lo) + ", " + CLI::detail::to_string(hi) + "]";
  return CLI::Validator(
      [lo, hi, open_lo, range](std::string& in) -> std::string {
        char* end = nullptr;
        const double v = std::strtod(in.c_str(), &end);
        if (end == in.c_str() || *end != '\0') return "'" + in + "' is not a number";
        if (!std::isfinite(v)) return "'" + in + "' is not a finite number";
        if (v < lo || v > hi || (open_lo && v == lo))
          return in + " is out of range: expected a number in " + range;
        return std::string();
      },
      "NUMBER in " + range);
}
inline CLI::Validator positive(double hi) { return finite_in(0.0, hi, true); }

// shm_link / mirror: whether this process has a shared-memory device link / mirrors it (--help lists only
// the options a process uses).
inline void add_bus_options(CLI::App& app, BusOptions& o, bool shm_link = true, bool mirror = true) {
  app.add_option("--lcm-url", o.lcm_url, "LCM provider: udpm://... between processes/hosts, memq:// in-process")
      ->envname("LCM_DEFAULT_URL")
      ->capture_default_str();
  app.add_option("--channel-suffix", o.channel_suffix,
                 "appended to every channel name (several sessions on one bus); [A-Za-z0-9_]")
      ->capture_default_str();
  app.add_option("--session-key-file", o.session_key_file,
                 "session key (>= 32 bytes, chmod 600): every message carries a MAC and a sequence number, "
                 "messages without the right MAC, replays and tampered bytes are dropped and counted")
      ->envname("HAPTREE_SESSION_KEY_FILE")
      ->each([](const std::string& path) { set_process_session_key_file(path); });
  if (shm_link) app.add_flag("--shm", o.shm, "carry device state and feedback over same-host shared memory");
  if (mirror)
    app.add_option("--mirror-rate-hz", o.mirror_rate_hz,
                   "rate at which shared-memory channels are republished on LCM for lcm-logger (0: off)")
        ->check(finite_in(0.0, 10000.0))
        ->capture_default_str();
}

// SIGINT/SIGTERM set the returned flag, which the process's run loop polls.
inline std::atomic<bool>& install_stop_signals() {
  static std::atomic<bool> stop{false};
  auto on_signal = [](int) {
    stop = true;
    unlink_own_shm_segments();   // nothing left even if a loop is slow to stop
  };
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  return stop;
}

}  // namespace haptree::bus
