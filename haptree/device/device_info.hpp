// Device table in the spirit of CHAI3D's cHapticDeviceInfo, and the start-up check of the coupling gains
// against a device and against the passivity bound (docs/accuracy_and_stability.md, docs/devices.md).
//
// Every number of a real device is CHAI3D's own specification of that device (repository and file in
// `source`); a field CHAI3D does not give is NaN ("not known"), never a guess.
#pragma once

#include <limits>
#include <string>
#include <vector>

#include "haptree/device/device.hpp"

namespace haptree::device {

constexpr double kUnknown = std::numeric_limits<double>::quiet_NaN();

struct DeviceInfo {
  std::string name;                        // --device-model NAME (lower case, no spaces)
  std::string model;                       // manufacturer and model as the vendor names it
  double max_force_n = kUnknown;           // largest linear force it renders (CHAI3D m_maxLinearForce)
  double max_continuous_force_n = kUnknown;  // sustained force, where the source gives one
  double max_torque_nm = 0;                // 0: renders no torque (m_maxAngularTorque)
  double max_stiffness_n_per_m = kUnknown; // largest stable closed-loop stiffness (m_maxLinearStiffness)
  double max_damping_n_s_per_m = kUnknown; // largest stable rendered damping (m_maxLinearDamping)
  double workspace_radius_m = kUnknown;    // m_workspaceRadius
  // Physical damping b of device + hand, the b of the passivity bound K < min(2b/T, 2b/dt_sim).
  // No vendor table gives it: NaN for real devices (pass --device-damping-n-s-per-m).
  double physical_damping_n_s_per_m = kUnknown;
  std::string source;                      // where the numbers come from
};

// The table: "simulated" (the default; generous limits, the virtual hand's 8 N·s/m damping) and the
// devices CHAI3D 3.3 describes.
const std::vector<DeviceInfo>& device_table();
// nullptr if unknown. Names are matched case-insensitively.
const DeviceInfo* find_device_info(const std::string& name);
// "simulated, touch, phantom_omni, ..." for --help and error messages.
std::string device_model_names();
// The DeviceSpec a driver of this device would publish (unknown fields keep DeviceSpec's defaults).
DeviceSpec to_device_spec(const DeviceInfo& info);

// The limits a device reported at open (DeviceDescription, NaN = not reported) over the table entry
// `fallback` (--device-model): each reported limit replaces the table's, the others stay, and model and
// source say which came from where. The physical damping b always stays the fallback's (no device reports it).
DeviceInfo with_reported_limits(const DeviceInfo& fallback, const DeviceDescription& reported);

// The coupler's gains, in its own units (CouplerOptions), and the two periods of the loop.
struct CouplingGains {
  double stiffness = 0;          // k_s, scene force / scene length
  double damping = 0;            // b_s, scene force / scene velocity
  double position_scale = 1;     // scene length per device metre
  double force_scale = 1;        // newtons per scene force
  double time_scale = 1;         // scene time per device second
  double max_force_n = 0;        // the coupler's force clamp
  double rate_hz = 1000;         // haptic loop: T = 1 / rate_hz
  double sim_dt_s = 1e-3;        // wall time between coefficient snapshots (dt_sim of the bound)
  double physical_damping_n_s_per_m = kUnknown;  // b; NaN: the device's table value
};

// What the device feels: K = k_s · force_scale · position_scale (N/m) and
// B = b_s · force_scale · position_scale / time_scale (N·s/m).
double device_stiffness_n_per_m(const CouplingGains& g);
double device_damping_n_s_per_m(const CouplingGains& g);

struct GainCheck {
  std::vector<std::string> problems;  // one sentence per violated limit: which, value, limit, factor
  CouplingGains clamped;              // the input with every violated gain lowered to its limit
  bool clampable = true;              // false if a problem cannot be fixed by lowering a gain
  double stiffness_n_per_m = 0, damping_n_s_per_m = 0;   // K and B of the input
  double passivity_bound_n_per_m = kUnknown;             // min(2b/T, 2b/dt_sim)
  bool ok() const { return problems.empty(); }
};

// Checks, in this order: the inputs are finite and positive where they must be; force clamp ≤ the
// device's max force; K ≤ max stiffness; B ≤ max damping; K ≤ min(2b/T, 2b/dt_sim). Pure function.
GainCheck check_gains(const DeviceInfo& device, const CouplingGains& gains);

}  // namespace haptree::device
