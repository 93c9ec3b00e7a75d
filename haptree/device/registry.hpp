// Devices by name, so real SDKs plug in without the processes knowing them:
//   haptree::device::register_device("phantom", [](const DeviceConfig& c) { return std::make_unique<...>(c); });
// Built in: "scripted", "virtual_hand", "replay", "browser", and the real devices "openhaptics",
// "forcedimension" (vendor libraries loaded at run time) and "inverse3" (the Haply Inverse Service over
// a local WebSocket); options below; docs/devices.md.
#pragma once

#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "haptree/device/device.hpp"

namespace haptree::bus {
class Bus;
}

namespace haptree::device {

struct DeviceConfig {
  DeviceSpec spec;
  // Free-form options as strings (from a command line or a config file). Built-ins read:
  //  scripted / virtual_hand (the script or target, GrabPullRelease): start_m, grab_m, pull_direction
  //    ("x,y,z"), pull_distance_m, approach_s, settle_s, pull_s, hold_s, rest_s
  //  virtual_hand: mass_kg, stiffness_n_per_m, damping_n_s_per_m, max_substep_s
  //  replay: log (path, required), channel (required), loop (0/1)
  //  inverse3 (Haply Inverse Service, haptree/device/inverse3.hpp): url, device_id, grip_id, axes, origin_m,
  //    rate_hz (default the bridge's rate), timeout_s, connect_timeout_s, force_key (vector|values)
  //  browser (the mouse in the viewer's page, needs bus): fallback (scripted|none, default none; the
  //    scripted options above apply to it), timeout_s, smoothing_s, switch_s
  //  real devices: axes (vendor axes -> haptree's, AxisMap; each family documents its default), lib
  //    (the vendor library's path or name), and openhaptics: name (device name; default device),
  //    forcedimension: id (device index; default the first device)
  std::map<std::string, std::string> options;
  // Set by device_bridge for devices fed from the bus (browser): the bus, this device's id, the suffix.
  bus::Bus* bus = nullptr;
  int device_id = 0;
  std::string channel_suffix;
};

using DeviceFactory = std::function<std::unique_ptr<Device>(const DeviceConfig&)>;

// Throws std::invalid_argument if the name is taken.
void register_device(const std::string& name, DeviceFactory factory);
// Removes a registration (plug-in unloading, tests). False if the name was not registered.
bool unregister_device(const std::string& name);
// Throws std::invalid_argument listing the known names when `name` is unknown, or naming the option
// and its value when an option is malformed.
std::unique_ptr<Device> make_device(const std::string& name, const DeviceConfig& config);
std::vector<std::string> device_names();

// Option readers used by the built-ins (and handy for plug-ins); throw std::invalid_argument with key/value.
double option_double(const DeviceConfig& c, const std::string& key, double fallback);
Vec3 option_vec3(const DeviceConfig& c, const std::string& key, const Vec3& fallback);
std::string option_string(const DeviceConfig& c, const std::string& key, const std::string& fallback);

}  // namespace haptree::device
