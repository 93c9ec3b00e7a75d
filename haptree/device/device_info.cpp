#include "haptree/device/device_info.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>

namespace haptree::device {

namespace {

// CHAI3D 3.3.0, github.com/chai3d/chai3d at commit 7c76b1f2 (2024-08-15): the m_specifications each
// device class fills in (line numbers of that commit).
const char* kPhantom = "chai3d/chai3d src/devices/CPhantomDevices.cpp";
const char* kDelta = "chai3d/chai3d src/devices/CDeltaDevices.cpp";

DeviceInfo dev(const char* name, const char* model, double f, double tau, double k, double b, double r,
               std::string source) {
  DeviceInfo d;
  d.name = name;
  d.model = model;
  d.max_force_n = f;
  d.max_torque_nm = tau;
  d.max_stiffness_n_per_m = k;
  d.max_damping_n_s_per_m = b;
  d.workspace_radius_m = r;
  d.source = std::move(source);
  return d;
}

std::vector<DeviceInfo> make_table() {
  std::vector<DeviceInfo> t;
  DeviceInfo sim = dev("simulated", "haptree simulated device (scripted / virtual hand)", 1000, 0, 1e6, 1e4,
                       1.0, "haptree: no hardware; limits chosen generous so that any gains the "
                            "simulation survives pass; b = VirtualHandParams::damping_n_s_per_m");
  sim.physical_damping_n_s_per_m = 8.0;
  t.push_back(sim);
  const std::string p = kPhantom, d = kDelta;
  t.push_back(dev("touch", "3D Systems Touch", 3.3, 0, 400, 4.0, 0.075, p + " lines 495-507 (\"Touch\")"));
  t.push_back(dev("touch_x", "3D Systems Touch X", 6.0, 0, 1000, 8.0, 0.10,
                  p + " lines 436-448: CHAI3D has no Touch X entry and gives any OpenHaptics model it "
                      "does not name these generic \"PHANTOM\" values"));
  t.push_back(dev("phantom_omni", "SensAble PHANTOM Omni", 3.3, 0, 700, 5.0, 0.10,
                  p + " lines 519-531 (\"PHANTOM Omni\")"));
  t.push_back(dev("phantom_desktop", "SensAble PHANTOM Desktop", 7.9, 0, 1000, 5.0, 0.10,
                  p + " lines 543-555 (\"PHANTOM Desktop\")"));
  t.push_back(dev("phantom_premium_1.5_6dof", "SensAble PHANTOM Premium 1.5 6DOF", 8.5, 0.188, 800, 5.0,
                  0.12, p + " lines 567-579"));
  t.push_back(dev("phantom_premium_3.0_6dof", "SensAble PHANTOM Premium 3.0 6DOF", 22.0, 0.188, 1000, 5.0,
                  0.25, p + " lines 591-603"));
  t.push_back(dev("falcon", "Novint Falcon", 8.0, 0, 3000, 20.0, 0.04,
                  d + " lines 1136-1146 (DHD_DEVICE_FALCON)"));
  t.push_back(dev("delta.3", "Force Dimension delta.3", 20.0, 0, 5000, 30.0, 0.15,
                  d + " lines 783-793 (DHD_DEVICE_DELTA3)"));
  t.push_back(dev("omega.3", "Force Dimension omega.3", 12.0, 0, 5000, 30.0, 0.075,
                  d + " lines 815-825 (DHD_DEVICE_OMEGA3)"));
  t.push_back(dev("omega.6", "Force Dimension omega.6", 12.0, 0, 5000, 30.0, 0.075,
                  d + " lines 846-856 and 877-887 (DHD_DEVICE_OMEGA6_LEFT / _RIGHT)"));
  t.push_back(dev("omega.7", "Force Dimension omega.7", 12.0, 0, 5000, 30.0, 0.075,
                  d + " lines 908-918 and 940-950 (omega.7L / omega.7R; gripper 8 N)"));
  t.push_back(dev("sigma.7", "Force Dimension sigma.7", 12.0, 0.2, 4000, 30.0, 0.075,
                  d + " lines 973-983 and 1011-1021 (sigma.7L / sigma.7R; gripper 8 N)"));
  t.push_back(dev("lambda.7", "Force Dimension lambda.7", 12.0, 0.2, 8000, 30.0, 0.1125,
                  d + " lines 1055-1065 and 1100-1110 (lambda.7L / lambda.7R; gripper 8 N)"));
  return t;
}

std::string lower(std::string s) {
  for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return s;
}

std::string num(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.4g", v);
  return buf;
}

bool positive(double v) { return std::isfinite(v) && v > 0; }

// Above a limit: a clamped gain lands on its limit up to rounding (one product and one quotient), so
// a relative 1e-12 keeps a clamped set of gains passing the same check.
bool above(double value, double limit) { return value > limit * (1 + 1e-12); }

}  // namespace

const std::vector<DeviceInfo>& device_table() {
  static const std::vector<DeviceInfo> t = make_table();
  return t;
}

const DeviceInfo* find_device_info(const std::string& name) {
  const std::string n = lower(name);
  for (const auto& d : device_table())
    if (d.name == n) return &d;
  return nullptr;
}

std::string device_model_names() {
  std::string s;
  for (const auto& d : device_table()) s += (s.empty() ? "" : ", ") + d.name;
  return s;
}

DeviceSpec to_device_spec(const DeviceInfo& info) {
  DeviceSpec s;
  s.name = info.name;
  if (std::isfinite(info.max_force_n)) s.max_force_n = info.max_force_n;
  s.max_torque_nm = info.max_torque_nm;
  if (std::isfinite(info.workspace_radius_m)) s.workspace_radius_m = info.workspace_radius_m;
  if (std::isfinite(info.max_stiffness_n_per_m)) s.max_stiffness_n_per_m = info.max_stiffness_n_per_m;
  return s;
}

DeviceInfo with_reported_limits(const DeviceInfo& fallback, const DeviceDescription& r) {
  DeviceInfo d = fallback;
  std::string which;
  auto take = [&](double v, double& field, const char* name) {
    if (!std::isfinite(v)) return;
    field = v;
    which += (which.empty() ? "" : ", ") + std::string(name);
  };
  take(r.max_force_n, d.max_force_n, "max force");
  take(r.max_continuous_force_n, d.max_continuous_force_n, "continuous force");
  take(r.max_torque_nm, d.max_torque_nm, "max torque");
  take(r.max_stiffness_n_per_m, d.max_stiffness_n_per_m, "max stiffness");
  take(r.max_damping_n_s_per_m, d.max_damping_n_s_per_m, "max damping");
  take(r.workspace_radius_m, d.workspace_radius_m, "workspace radius");
  if (which.empty()) return d;
  if (!r.model.empty()) d.model = r.model;
  d.source = which + " reported by the device at open; the rest from --device-model " + fallback.name + " (" +
             fallback.source + ")";
  return d;
}

double device_stiffness_n_per_m(const CouplingGains& g) {
  return g.stiffness * g.force_scale * g.position_scale;
}
double device_damping_n_s_per_m(const CouplingGains& g) {
  return g.damping * g.force_scale * g.position_scale / g.time_scale;
}

GainCheck check_gains(const DeviceInfo& dev, const CouplingGains& g) {
  GainCheck c;
  c.clamped = g;
  auto refuse = [&](const std::string& what) {
    c.problems.push_back(what);
    c.clampable = false;
  };
  // Inputs: a gain that is not a number cannot be checked, let alone clamped.
  if (!(std::isfinite(g.stiffness) && g.stiffness >= 0)) refuse("--stiffness " + num(g.stiffness) + " must be a finite number >= 0");
  if (!(std::isfinite(g.damping) && g.damping >= 0)) refuse("--damping " + num(g.damping) + " must be a finite number >= 0");
  if (!positive(g.position_scale)) refuse("--position-scale " + num(g.position_scale) + " must be > 0");
  if (!positive(g.force_scale)) refuse("--force-scale " + num(g.force_scale) + " must be > 0");
  if (!positive(g.time_scale)) refuse("time scale " + num(g.time_scale) + " must be > 0");
  if (!positive(g.max_force_n)) refuse("--max-force-n " + num(g.max_force_n) + " must be > 0");
  if (!positive(g.rate_hz)) refuse("--rate-hz " + num(g.rate_hz) + " must be > 0");
  if (!positive(g.sim_dt_s)) refuse("--sim-dt-s " + num(g.sim_dt_s) + " must be > 0");
  if (!c.problems.empty()) return c;

  const double K = device_stiffness_n_per_m(g), B = device_damping_n_s_per_m(g);
  c.stiffness_n_per_m = K;
  c.damping_n_s_per_m = B;
  const std::string on = " on " + dev.model + " (" + dev.source + ")";
  // A limit is violated when the value is above it; the message says by which factor.
  auto over = [&](const std::string& what, double value, double limit, const std::string& unit,
                  const std::string& fix) {
    c.problems.push_back(what + " " + num(value) + " " + unit + " exceeds " + num(limit) + " " + unit +
                         " by a factor " + num(value / limit) + ": " + fix);
  };
  if (std::isfinite(dev.max_force_n) && above(g.max_force_n, dev.max_force_n)) {
    over("force clamp --max-force-n", g.max_force_n, dev.max_force_n, "N",
         "the device's max force" + on);
    c.clamped.max_force_n = dev.max_force_n;
  }
  double k_limit = std::numeric_limits<double>::infinity();
  std::string k_what;
  if (std::isfinite(dev.max_stiffness_n_per_m) && above(K, dev.max_stiffness_n_per_m)) {
    over("device stiffness K = stiffness x force-scale x position-scale =", K, dev.max_stiffness_n_per_m,
         "N/m", "the device's max stiffness" + on);
    k_limit = dev.max_stiffness_n_per_m;
  }
  if (std::isfinite(dev.max_damping_n_s_per_m) && above(B, dev.max_damping_n_s_per_m)) {
    over("device damping B = damping x force-scale x position-scale / time-scale =", B,
         dev.max_damping_n_s_per_m, "N s/m", "the device's max damping" + on);
    c.clamped.damping = g.damping * dev.max_damping_n_s_per_m / B;
  }
  // Passivity (docs/accuracy_and_stability.md, measured on 33 configurations): K < min(2b/T, 2b/dt_sim).
  const double b = std::isfinite(g.physical_damping_n_s_per_m) ? g.physical_damping_n_s_per_m
                                                               : dev.physical_damping_n_s_per_m;
  if (!(std::isfinite(b) && b >= 0)) {
    refuse("the passivity bound K < min(2b/T, 2b/dt_sim) needs the physical damping b of " + dev.model +
           " and the hand holding it, which no device table gives: pass --device-damping-n-s-per-m B");
  } else {
    const double T = 1.0 / g.rate_hz;
    c.passivity_bound_n_per_m = std::min(2 * b / T, 2 * b / g.sim_dt_s);
    if (above(K, c.passivity_bound_n_per_m)) {
      const bool sim_limited = g.sim_dt_s > T;
      over("device stiffness K", K, c.passivity_bound_n_per_m, "N/m",
           "the passivity bound min(2b/T, 2b/dt_sim) with b = " + num(b) + " N s/m, T = " + num(T) +
               " s, dt_sim = " + num(g.sim_dt_s) + " s (the " + (sim_limited ? "2b/dt_sim" : "2b/T") +
               " term; docs/accuracy_and_stability.md)");
      k_limit = std::min(k_limit, c.passivity_bound_n_per_m);
    }
  }
  if (std::isfinite(k_limit)) c.clamped.stiffness = g.stiffness * k_limit / K;
  return c;
}

}  // namespace haptree::device
