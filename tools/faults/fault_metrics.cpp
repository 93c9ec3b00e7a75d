// fault_metrics: the network-fault table from a workstation-side LCM log (docs/network_faults.md).
// Prints one markdown row per fault phase and exits 1 when a limit is broken: |f| above the clamp, a
// force change faster than the rate limit, a non-finite force, no recovery within the settle window, or a
// watchdog ramp to zero longer than --max-ramp-ms.
#include <CLI/CLI.hpp>

#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "haptree/bus/channels.hpp"
#include "tools/faults/fault_metrics.hpp"

int main(int argc, char** argv) {
  CLI::App app{"fault_metrics: per-fault figures of the FEEDBACK forces in an LCM log (docs/network_faults.md)"};
  std::string log;
  std::vector<std::string> phases;
  int device = 0, user = 0;
  // The rate and ramp checks are off unless asked for: both read the coupler's publication stamps, which a
  // loaded machine delays (the device's own per-tick bound is exact, and scripts/network_faults.sh checks it).
  double settle_s = 1.0, max_force_n = 3.0, rate_limit = INFINITY, max_ramp_ms = INFINITY, rate_tolerance = 0.1;
  app.add_option("log", log, "LCM log recorded on the workstation side (lcm-logger)")->required();
  app.add_option("--phase", phases, "NAME:START_UTIME:END_UTIME of a fault (µs, system clock), repeatable")->required();
  app.add_option("--device", device, "device id (FEEDBACK channel)")->capture_default_str();
  app.add_option("--user", user, "user id (COEFFS channel)")->capture_default_str();
  app.add_option("--settle-s", settle_s, "fault-free time after each fault in which it must recover, s")->capture_default_str();
  app.add_option("--max-force-n", max_force_n, "the device clamp, N")->capture_default_str();
  app.add_option("--rate-limit-n-per-s", rate_limit, "largest allowed force change rate over >= 1 ms, N/s")->capture_default_str();
  app.add_option("--rate-tolerance", rate_tolerance,
                 "allowance on the rate for timestamp jitter: FEEDBACK is stamped at publication, after the loop "
                 "read its clock, so a few µs of jitter per 1 ms span (the device's per-tick step is exact)")
      ->capture_default_str();
  app.add_option("--max-ramp-ms", max_ramp_ms, "longest allowed stale-to-zero ramp, ms")->capture_default_str();
  std::vector<std::string> expects;
  app.add_option("--expect", expects,
                 "NAME:KEY:LO:HI, repeatable: the fault must have shown up (KEY = delivered, latency_ms, reordered, "
                 "duplicated, snapshot_hz, trips, feedback_hz, max_force_n); exit 1 if KEY is outside [LO, HI]");
  CLI11_PARSE(app, argc, argv);
  const auto s = haptree::faults::read_session_log(log, haptree::bus::channel::feedback(device),
                                                   haptree::bus::channel::coeffs(user));
  if (!s.error.empty()) {
    std::fprintf(stderr, "fault_metrics: %s\n", s.error.c_str());
    return 2;
  }
  std::printf("| fault | feedback Hz | snapshots Hz | delivered | latency ms | reordered | duplicated | max \\|f\\| N | "
              "max rate N/s | max step N | trips | ramp to 0 ms | zero after ms | recover ms |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  int bad = 0;
  for (const auto& ph : phases) {
    const auto c1 = ph.find(':'), c2 = ph.rfind(':');
    if (c1 == std::string::npos || c1 == c2) {
      std::fprintf(stderr, "fault_metrics: --phase '%s': expected NAME:START:END\n", ph.c_str());
      return 2;
    }
    const auto m = haptree::faults::phase_metrics(s, ph.substr(0, c1), std::stoll(ph.substr(c1 + 1, c2 - c1 - 1)),
                                                  std::stoll(ph.substr(c2 + 1)), static_cast<int64_t>(settle_s * 1e6));
    std::printf("| %s | %.0f | %.0f | %.3f | %.2f | %lld | %lld | %.3f | %.0f | %.3f | %lld | %.1f | %.1f | %.1f |\n",
                m.name.c_str(), m.feedback_hz, m.snapshot_hz, m.delivered, m.latency_ms,
                static_cast<long long>(m.snapshots_reordered),
                static_cast<long long>(m.snapshots_duplicated), m.max_force_n, m.max_rate_n_per_s, m.max_step_n,
                static_cast<long long>(m.trips), m.ramp_ms, m.zero_after_ms, m.recover_ms);
    std::string why;
    if (m.feedbacks == 0) why += " no FEEDBACK in the phase;";
    if (m.nonfinite) why += " non-finite force;";
    if (m.max_force_n > max_force_n * (1 + 1e-12)) why += " force above the clamp;";
    if (m.max_rate_n_per_s > rate_limit * (1 + rate_tolerance)) why += " force changed faster than the rate limit;";
    if (m.ramp_ms > max_ramp_ms) why += " ramp to zero too slow;";
    if (std::isnan(m.recover_ms)) why += " no recovery within the settle window;";
    for (const auto& e : expects) {   // NAME:KEY:LO:HI; NAME may contain spaces, not ':'
      const auto a = e.find(':'), b = e.find(':', a + 1), c = e.find(':', b + 1);
      if (c == std::string::npos) {
        std::fprintf(stderr, "fault_metrics: --expect '%s': expected NAME:KEY:LO:HI\n", e.c_str());
        return 2;
      }
      if (e.substr(0, a) != m.name) continue;
      const std::string key = e.substr(a + 1, b - a - 1);
      const double lo = std::stod(e.substr(b + 1, c - b - 1)), hi = std::stod(e.substr(c + 1));
      double v = std::nan("");
      if (key == "delivered") v = m.delivered;
      else if (key == "latency_ms") v = m.latency_ms;
      else if (key == "reordered") v = static_cast<double>(m.snapshots_reordered);
      else if (key == "duplicated") v = static_cast<double>(m.snapshots_duplicated);
      else if (key == "snapshot_hz") v = m.snapshot_hz;
      else if (key == "trips") v = static_cast<double>(m.trips);
      else if (key == "feedback_hz") v = m.feedback_hz;
      else if (key == "max_force_n") v = m.max_force_n;
      else {
        std::fprintf(stderr, "fault_metrics: --expect '%s': unknown key '%s'\n", e.c_str(), key.c_str());
        return 2;
      }
      if (!(v >= lo && v <= hi)) why += " " + key + " = " + std::to_string(v) + " outside [" + e.substr(b + 1) + "];";
    }
    if (!why.empty()) {
      std::fprintf(stderr, "fault_metrics: %s:%s\n", m.name.c_str(), why.c_str());
      ++bad;
    }
  }
  return bad ? 1 : 0;
}
