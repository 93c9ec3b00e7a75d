#include "haptree/device/registry.hpp"

#include <mutex>
#include <sstream>
#include <stdexcept>

#include "haptree/bus/channels.hpp"
#include "haptree/device/browser.hpp"
#include "haptree/device/forcedimension.hpp"
#include "haptree/device/inverse3.hpp"
#include "haptree/device/openhaptics.hpp"
#include "haptree/device/replay.hpp"
#include "haptree/device/simulated.hpp"

namespace haptree::device {

double option_double(const DeviceConfig& c, const std::string& key, double fallback) {
  auto it = c.options.find(key);
  if (it == c.options.end()) return fallback;
  try {
    size_t used = 0;
    const double v = std::stod(it->second, &used);
    if (used != it->second.size()) throw std::invalid_argument("trailing characters");
    return v;
  } catch (const std::exception&) {
    throw std::invalid_argument("device option " + key + "='" + it->second + "' is not a number");
  }
}

Vec3 option_vec3(const DeviceConfig& c, const std::string& key, const Vec3& fallback) {
  auto it = c.options.find(key);
  if (it == c.options.end()) return fallback;
  std::istringstream in(it->second);
  Vec3 v;
  char sep1 = 0, sep2 = 0;
  if (!(in >> v.x() >> sep1 >> v.y() >> sep2 >> v.z()) || sep1 != ',' || sep2 != ',' || !(in >> std::ws).eof())
    throw std::invalid_argument("device option " + key + "='" + it->second + "' is not 'x,y,z'");
  return v;
}

std::string option_string(const DeviceConfig& c, const std::string& key, const std::string& fallback) {
  auto it = c.options.find(key);
  return it == c.options.end() ? fallback : it->second;
}

namespace {

GrabPullRelease script_options(const DeviceConfig& c) {
  GrabPullRelease p;
  p.start_m = option_vec3(c, "start_m", p.start_m);
  p.grab_m = option_vec3(c, "grab_m", p.grab_m);
  p.pull_direction = option_vec3(c, "pull_direction", p.pull_direction);
  p.pull_distance_m = option_double(c, "pull_distance_m", p.pull_distance_m);
  p.approach_s = option_double(c, "approach_s", p.approach_s);
  p.settle_s = option_double(c, "settle_s", p.settle_s);
  p.pull_s = option_double(c, "pull_s", p.pull_s);
  p.hold_s = option_double(c, "hold_s", p.hold_s);
  p.rest_s = option_double(c, "rest_s", p.rest_s);
  return p;
}

struct Registry {
  std::mutex mutex;
  std::map<std::string, DeviceFactory> factories;
  Registry() {
    factories["scripted"] = [](const DeviceConfig& c) -> std::unique_ptr<Device> {
      return std::make_unique<ScriptedDevice>(c.spec, make_grab_pull_release(script_options(c)));
    };
    factories["virtual_hand"] = [](const DeviceConfig& c) -> std::unique_ptr<Device> {
      VirtualHandParams p;
      p.mass_kg = option_double(c, "mass_kg", p.mass_kg);
      p.stiffness_n_per_m = option_double(c, "stiffness_n_per_m", p.stiffness_n_per_m);
      p.damping_n_s_per_m = option_double(c, "damping_n_s_per_m", p.damping_n_s_per_m);
      p.max_substep_s = option_double(c, "max_substep_s", p.max_substep_s);
      return std::make_unique<VirtualHand>(c.spec, p, make_grab_pull_release(script_options(c)));
    };
    factories["replay"] = [](const DeviceConfig& c) -> std::unique_ptr<Device> {
      const std::string log = option_string(c, "log", "");
      const std::string channel = option_string(c, "channel", "");
      if (log.empty() || channel.empty())
        throw std::invalid_argument("device 'replay' needs options log=<file.lcm> and channel=<name>");
      return std::make_unique<ReplayDevice>(c.spec, log, channel, option_double(c, "loop", 0) != 0);
    };
    factories["openhaptics"] = make_openhaptics_device;
    factories["forcedimension"] = make_forcedimension_device;
    factories["browser"] = [](const DeviceConfig& c) -> std::unique_ptr<Device> {
      if (!c.bus) throw std::invalid_argument("device 'browser' reads the viewer's pointer from the bus: no bus given");
      BrowserParams p;
      p.timeout_s = option_double(c, "timeout_s", p.timeout_s);
      p.smoothing_s = option_double(c, "smoothing_s", p.smoothing_s);
      p.switch_s = option_double(c, "switch_s", p.switch_s);
      if (!(p.timeout_s > 0 && p.timeout_s <= 10) || !(p.smoothing_s > 0 && p.smoothing_s <= 1) ||
          !(p.switch_s >= 0 && p.switch_s <= 1))
        throw std::invalid_argument("device 'browser': timeout_s must be in (0, 10], smoothing_s in (0, 1], "
                                    "switch_s in [0, 1]");
      const std::string fb = option_string(c, "fallback", "none");
      std::unique_ptr<Device> fallback;
      if (fb == "scripted") {
        fallback = std::make_unique<ScriptedDevice>(c.spec, make_grab_pull_release(script_options(c)));
      } else if (fb != "none") {
        throw std::invalid_argument("device 'browser': fallback='" + fb + "' (expected scripted or none)");
      }
      return std::make_unique<BrowserDevice>(c.spec, p, *c.bus, bus::channel::pointer(c.device_id, c.channel_suffix),
                                             std::move(fallback));
    };
    factories["inverse3"] = [](const DeviceConfig& c) -> std::unique_ptr<Device> {
      Inverse3Params p;
      p.url = option_string(c, "url", p.url);
      p.device_id = option_string(c, "device_id", p.device_id);
      p.grip_id = option_string(c, "grip_id", p.grip_id);
      p.axes = option_string(c, "axes", p.axes);
      p.origin_m = option_vec3(c, "origin_m", p.origin_m);
      p.rate_hz = option_double(c, "rate_hz", c.spec.rate_hz);
      p.timeout_s = option_double(c, "timeout_s", p.timeout_s);
      p.connect_timeout_s = option_double(c, "connect_timeout_s", p.connect_timeout_s);
      p.force_key = option_string(c, "force_key", p.force_key);
      return std::make_unique<Inverse3Device>(c.spec, p);
    };
  }
};

Registry& registry() {
  static Registry r;  // built on first use: no static-initialisation order or dropped-object issues
  return r;
}

}  // namespace

void register_device(const std::string& name, DeviceFactory factory) {
  auto& r = registry();
  std::lock_guard<std::mutex> lock(r.mutex);
  if (!factory) throw std::invalid_argument("register_device('" + name + "'): empty factory");
  if (!r.factories.emplace(name, std::move(factory)).second)
    throw std::invalid_argument("register_device: a device named '" + name + "' is already registered");
}

bool unregister_device(const std::string& name) {
  auto& r = registry();
  std::lock_guard<std::mutex> lock(r.mutex);
  return r.factories.erase(name) == 1;
}

std::vector<std::string> device_names() {
  auto& r = registry();
  std::lock_guard<std::mutex> lock(r.mutex);
  std::vector<std::string> names;
  for (const auto& kv : r.factories) names.push_back(kv.first);
  return names;
}

std::unique_ptr<Device> make_device(const std::string& name, const DeviceConfig& config) {
  DeviceFactory f;
  {
    auto& r = registry();
    std::lock_guard<std::mutex> lock(r.mutex);
    auto it = r.factories.find(name);
    if (it == r.factories.end()) {
      std::string known;
      for (const auto& kv : r.factories) known += (known.empty() ? "" : ", ") + kv.first;
      throw std::invalid_argument("unknown device '" + name + "'; known devices: " + known);
    }
    f = it->second;
  }
  return f(config);
}

}  // namespace haptree::device
