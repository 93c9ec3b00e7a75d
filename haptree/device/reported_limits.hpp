// The limits a device reported at open (Device::describe()), carried from device_bridge to its coupler
// as named values of device_bridge's lcmt_process_stats (HAPTREE_STATS_DEVICE_BRIDGE_<id>): the
// coupler checks its gains against them as it does against the --device-model table (device_cli.hpp).
// A limit the device does not report travels as NaN.
#pragma once

#include <cmath>
#include <string>
#include <vector>

#include "haptree/device/device.hpp"
#include "haptree/lcmt_process_stats.hpp"

namespace haptree::device {

// The stats channel's process name of device_bridge --device `id`.
inline std::string bridge_stats_name(int id) { return "device_bridge_" + std::to_string(id); }

namespace reported_detail {
struct Field {
  const char* name;
  double DeviceDescription::*member;
};
inline constexpr Field kFields[] = {
    {"device_max_force_n", &DeviceDescription::max_force_n},
    {"device_max_continuous_force_n", &DeviceDescription::max_continuous_force_n},
    {"device_max_torque_nm", &DeviceDescription::max_torque_nm},
    {"device_max_stiffness_n_per_m", &DeviceDescription::max_stiffness_n_per_m},
    {"device_max_damping_n_s_per_m", &DeviceDescription::max_damping_n_s_per_m},
    {"device_workspace_radius_m", &DeviceDescription::workspace_radius_m},
};
}  // namespace reported_detail

// Appends the reported limits of `d` to the message's named values.
inline void put_reported_limits(const DeviceDescription& d, lcmt_process_stats& m) {
  for (const auto& f : reported_detail::kFields) {
    m.extra_names.push_back(f.name);
    m.extra_values.push_back(d.*f.member);
  }
  m.n_extra = static_cast<int32_t>(m.extra_names.size());
}

// The limits in `m` (NaN: not reported); false if `m` carries none of the names (not a device_bridge
// that sends them).
inline bool get_reported_limits(const lcmt_process_stats& m, DeviceDescription& d) {
  bool any = false;
  const size_t n = std::min({static_cast<size_t>(std::max(m.n_extra, 0)), m.extra_names.size(), m.extra_values.size()});
  for (const auto& f : reported_detail::kFields)
    for (size_t i = 0; i < n; ++i)
      if (m.extra_names[i] == f.name) {
        d.*f.member = std::isfinite(m.extra_values[i]) ? m.extra_values[i] : DeviceDescription::kNotReported;
        any = true;
      }
  return any;
}

}  // namespace haptree::device
