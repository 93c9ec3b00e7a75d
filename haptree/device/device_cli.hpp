// Command-line options of the device-limit check (coupler, haptree_run): one call to add them, one to
// enforce them after parsing. Header-only so haptree_device does not depend on CLI11.
#pragma once

#include <CLI/CLI.hpp>

#include <cstdio>
#include <string>

#include "haptree/device/device_info.hpp"

namespace haptree::device {

struct DeviceLimitOptions {
  std::string model = "simulated";
  bool clamp = false;
  double physical_damping_n_s_per_m = kUnknown;
  double sim_dt_s = 1e-3;
};

inline void add_device_limit_options(CLI::App& app, DeviceLimitOptions& o, bool with_sim_dt = true) {
  app.add_option("--device-model", o.model,
                 "device whose limits the gains are checked against at start: " + device_model_names() +
                     " (docs/devices.md)")
      ->capture_default_str();
  app.add_flag("--clamp-gains", o.clamp,
               "lower gains that exceed a device limit or the passivity bound to that limit instead of "
               "refusing to start");
  app.add_option("--device-damping-n-s-per-m", o.physical_damping_n_s_per_m,
                 "physical damping b of device + hand for the passivity bound K < min(2b/T, 2b/dt_sim) "
                 "(default: the device table's; real devices have none)");
  if (with_sim_dt)
    app.add_option("--sim-dt-s", o.sim_dt_s,
                   "wall time between coefficient snapshots, the dt_sim of the passivity bound")
        ->capture_default_str();
}

// Checks the gains (in place) against the device and the passivity bound. Returns false after printing
// why when it refuses; with o.clamp it lowers what it can, says so, and returns true.
// `reported`: the limits an open device reported (Device::describe()); they take precedence over the
// --device-model table entry, which stays the fallback for what the device does not report.
inline bool enforce_device_limits(const DeviceLimitOptions& o, double& stiffness, double& damping,
                                  double position_scale, double force_scale, double& max_force_n,
                                  double rate_hz, const char* who, const DeviceDescription* reported = nullptr) {
  const DeviceInfo* table = find_device_info(o.model);
  if (!table) {
    std::fprintf(stderr, "%s: --device-model '%s' is not known; known: %s\n", who, o.model.c_str(),
                 device_model_names().c_str());
    return false;
  }
  const DeviceInfo merged = reported ? with_reported_limits(*table, *reported) : *table;
  const DeviceInfo* dev = &merged;
  CouplingGains g;
  g.stiffness = stiffness;
  g.damping = damping;
  g.position_scale = position_scale;
  g.force_scale = force_scale;
  g.max_force_n = max_force_n;
  g.rate_hz = rate_hz;
  g.sim_dt_s = o.sim_dt_s;
  g.physical_damping_n_s_per_m = o.physical_damping_n_s_per_m;
  const GainCheck c = check_gains(*dev, g);
  if (c.ok()) return true;
  for (const auto& p : c.problems) std::fprintf(stderr, "%s: unsafe gains: %s\n", who, p.c_str());
  if (!o.clamp || !c.clampable) {
    std::fprintf(stderr, "%s: refusing to start%s\n", who,
                 c.clampable ? " (lower the gains, or pass --clamp-gains to lower them to the limits)" : "");
    return false;
  }
  std::fprintf(stderr, "%s: --clamp-gains: stiffness %g -> %g, damping %g -> %g, max force %g -> %g N\n", who,
               stiffness, c.clamped.stiffness, damping, c.clamped.damping, max_force_n, c.clamped.max_force_n);
  stiffness = c.clamped.stiffness;
  damping = c.clamped.damping;
  max_force_n = c.clamped.max_force_n;
  return true;
}

}  // namespace haptree::device
