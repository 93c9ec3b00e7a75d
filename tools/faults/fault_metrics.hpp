// Network-fault figures from an LCM log of the workstation side (docs/network_faults.md): per fault phase,
// the FEEDBACK forces the device got (max |f| against the clamp, the fastest change against a rate limit,
// the watchdog's ramp to zero, the time to recover) and the feedback and snapshot rates.
// The table of tools/faults/fault_metrics, which scripts/network_faults.sh (ctest integration_network_faults) runs.
#pragma once

#include <lcm/lcm-cpp.hpp>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include "haptree/bus/wire.hpp"
#include "haptree/lcmt_feedback.hpp"

namespace haptree::faults {

struct FeedbackSample {
  int64_t utime;   // the coupler's stamp (system clock, µs)
  double force;    // |force_n|
  double fx, fy, fz;
  int32_t flags;
};

struct SessionLog {
  std::vector<FeedbackSample> feedback;   // in log order
  std::vector<int64_t> snapshot_utime;    // log time of each COEFFS datagram the workstation received
  std::vector<int64_t> snapshot_version;  // its version (server step), to count reordered and duplicated ones
  std::vector<int64_t> snapshot_stamp;    // the server's utime in it (same clock: one machine)
  std::string error;
};

inline SessionLog read_session_log(const std::string& path, const std::string& feedback_channel,
                                   const std::string& coeffs_channel) {
  SessionLog s;
  lcm::LogFile f(path, "r");
  if (!f.good()) {
    s.error = "cannot open LCM log '" + path + "'";
    return s;
  }
  for (const lcm::LogEvent* ev = f.readNextEvent(); ev != nullptr; ev = f.readNextEvent()) {
    if (ev->channel == coeffs_channel) {
      // lcmt_coupling_snapshot: 8-byte type hash, schema_version (int32), utime, instance_id,
      // model_fingerprint, version (big-endian int64 at byte 36). Read in place: no full decode needed.
      if (ev->datalen < 44) continue;
      const auto* b = static_cast<const uint8_t*>(ev->data);
      uint64_t v = 0, u = 0;
      for (int k = 36; k < 44; ++k) v = (v << 8) | b[k];
      for (int k = 12; k < 20; ++k) u = (u << 8) | b[k];
      s.snapshot_utime.push_back(ev->timestamp);
      s.snapshot_version.push_back(static_cast<int64_t>(v));
      s.snapshot_stamp.push_back(static_cast<int64_t>(u));
    } else if (ev->channel == feedback_channel) {
      lcmt_feedback m;
      if (bus::decode_checked(ev->data, static_cast<uint32_t>(ev->datalen), m) != bus::DecodeResult::kOk) continue;
      const double x = m.force_n[0], y = m.force_n[1], z = m.force_n[2];
      s.feedback.push_back({m.utime, std::sqrt(x * x + y * y + z * z), x, y, z, m.flags});
    }
  }
  return s;
}

struct PhaseMetrics {
  std::string name;
  int64_t feedbacks = 0;
  double feedback_hz = 0, snapshot_hz = 0;   // during the fault
  double max_force_n = 0;                    // over fault + settle window
  double max_rate_n_per_s = 0;               // fastest change over any >= 1 ms span (fault + settle window)
  double max_step_n = 0;                     // largest change between consecutive FEEDBACKs
  int64_t trips = 0;                         // fresh -> stale transitions (FLAG_STALE rising)
  double ramp_ms = std::numeric_limits<double>::quiet_NaN();        // stale edge -> first exact zero (longest)
  double zero_after_ms = std::numeric_limits<double>::quiet_NaN();  // fault start -> first exact zero
  double recover_ms = 0;   // fault end -> first FEEDBACK without the watchdog flag (0: never tripped); NaN: not within the settle window
  double delivered = 0;     // distinct snapshot versions received / versions the server sent (it sends every step)
  double latency_ms = 0;    // mean server stamp -> workstation log time of the snapshots
  int64_t snapshots_reordered = 0;          // COEFFS older than one received before (during the fault)
  int64_t snapshots_duplicated = 0;         // COEFFS equal to the newest received before
  bool nonfinite = false;
};

// Fault phase [start, end) in µs, followed by a settle window (no fault) of settle_us, where the recovery
// is measured. Span for the rate: a device renders at 1 kHz, so changes are judged over >= 1 ms.
inline PhaseMetrics phase_metrics(const SessionLog& s, const std::string& name, int64_t start, int64_t end,
                                  int64_t settle_us, int64_t span_us = 1000) {
  PhaseMetrics p;
  p.name = name;
  const auto& fb = s.feedback;
  const int64_t stop = end + settle_us;
  size_t j = 0;   // for the rate: newest sample at least span_us older than sample i
  bool prev_stale = false, have_prev = false, tripped_at_end = false, recovered = false;
  double stale_edge_us = -1;
  bool seen_end = false;
  for (size_t i = 0; i < fb.size(); ++i) {
    const FeedbackSample& x = fb[i];
    if (x.utime < start) {
      prev_stale = (x.flags & lcmt_feedback::FLAG_STALE) != 0;
      have_prev = true;
      continue;
    }
    if (x.utime >= stop) break;
    if (!std::isfinite(x.force)) p.nonfinite = true;
    if (x.utime < end) ++p.feedbacks;
    p.max_force_n = std::max(p.max_force_n, x.force);
    if (i > 0 && fb[i - 1].utime >= start) {
      const FeedbackSample& y = fb[i - 1];
      p.max_step_n = std::max(p.max_step_n, std::sqrt((x.fx - y.fx) * (x.fx - y.fx) + (x.fy - y.fy) * (x.fy - y.fy) +
                                                      (x.fz - y.fz) * (x.fz - y.fz)));
    }
    while (j + 1 < i && fb[j + 1].utime <= x.utime - span_us) ++j;
    if (j < i && fb[j].utime >= start && fb[j].utime <= x.utime - span_us) {
      const FeedbackSample& y = fb[j];
      const double d = std::sqrt((x.fx - y.fx) * (x.fx - y.fx) + (x.fy - y.fy) * (x.fy - y.fy) + (x.fz - y.fz) * (x.fz - y.fz));
      p.max_rate_n_per_s = std::max(p.max_rate_n_per_s, d / (1e-6 * static_cast<double>(x.utime - y.utime)));
    }
    const bool stale = (x.flags & lcmt_feedback::FLAG_STALE) != 0;
    if (stale && !(have_prev && prev_stale)) {
      ++p.trips;
      stale_edge_us = static_cast<double>(x.utime);
    }
    if (x.force == 0 && (x.flags & lcmt_feedback::FLAG_WATCHDOG) && stale_edge_us >= 0) {
      const double r = 1e-3 * (static_cast<double>(x.utime) - stale_edge_us);
      p.ramp_ms = std::isnan(p.ramp_ms) ? r : std::max(p.ramp_ms, r);
      if (std::isnan(p.zero_after_ms)) p.zero_after_ms = 1e-3 * static_cast<double>(x.utime - start);
      stale_edge_us = -1;
    }
    if (x.utime >= end && !seen_end) {   // first sample of the settle window: was the watchdog still acting?
      seen_end = true;
      tripped_at_end = i > 0 && (fb[i - 1].flags & lcmt_feedback::FLAG_WATCHDOG) != 0 && fb[i - 1].utime >= start;
    }
    if (seen_end && tripped_at_end && !recovered && !(x.flags & lcmt_feedback::FLAG_WATCHDOG)) {
      recovered = true;
      p.recover_ms = 1e-3 * static_cast<double>(x.utime - end);
    }
    prev_stale = stale;
    have_prev = true;
  }
  if (tripped_at_end && !recovered) p.recover_ms = std::numeric_limits<double>::quiet_NaN();
  const double dur_s = 1e-6 * static_cast<double>(end - start);
  p.feedback_hz = dur_s > 0 ? static_cast<double>(p.feedbacks) / dur_s : 0;
  const auto n_snap = std::count_if(s.snapshot_utime.begin(), s.snapshot_utime.end(),
                                    [&](int64_t t) { return t >= start && t < end; });
  p.snapshot_hz = dur_s > 0 ? static_cast<double>(n_snap) / dur_s : 0;
  int64_t newest = -1, vmin = std::numeric_limits<int64_t>::max(), vmax = -1;
  std::vector<int64_t> seen;
  double lat = 0;
  for (size_t k = 0; k < s.snapshot_utime.size(); ++k) {
    const int64_t v = s.snapshot_version[k];
    if (s.snapshot_utime[k] >= start && s.snapshot_utime[k] < end) {
      if (v < newest) ++p.snapshots_reordered;
      if (v == newest) ++p.snapshots_duplicated;
      vmin = std::min(vmin, v);
      vmax = std::max(vmax, v);
      seen.push_back(v);
      lat += 1e-3 * static_cast<double>(s.snapshot_utime[k] - s.snapshot_stamp[k]);
    }
    newest = std::max(newest, v);
  }
  if (!seen.empty()) {
    std::sort(seen.begin(), seen.end());
    const auto distinct = std::unique(seen.begin(), seen.end()) - seen.begin();
    p.delivered = static_cast<double>(distinct) / static_cast<double>(vmax - vmin + 1);
    p.latency_ms = lat / static_cast<double>(n_snap);
  }
  return p;
}

}  // namespace haptree::faults
