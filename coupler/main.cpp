// coupler: O(log n) force feedback at haptic rate for one user/device.
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <atomic>
#include <vector>

#include "coupler/coupler.hpp"
#include "haptree/bus/cli.hpp"
#include "haptree/device/device_cli.hpp"

int main(int argc, char** argv) {
  CLI::App app{"haptree coupler: O(log n) force feedback at haptic rate (one per user/device)"};
  haptree::CouplerOptions o;
  haptree::bus::BusOptions b;
  haptree::bus::add_bus_options(app, b);
  std::vector<double> offset{0, 0, 0};
  app.add_option("--user", o.user, "user id (HAPTREE_COEFFS_<user>, HAPTREE_USER_FORCE_<user>)")->capture_default_str();
  app.add_option("--device", o.device, "device id (HAPTREE_DEVICE_STATE_<id>, HAPTREE_FEEDBACK_<id>)")->capture_default_str();
  app.add_option("--rate-hz", o.rate_hz, "coupling loop rate")->capture_default_str();
  app.add_flag("!--sleep", o.busy_wait, "pace with sleep_until instead of busy waiting");
  app.add_option("--stiffness", o.stiffness, "k_s, scene force per scene length")->capture_default_str();
  app.add_option("--damping", o.damping, "b_s, scene force per scene velocity")->capture_default_str();
  app.add_option("--position-scale", o.position_scale, "scene length units per device metre")->capture_default_str();
  app.add_option("--force-scale", o.force_scale, "newtons per scene force unit")->capture_default_str();
  app.add_option("--offset", offset, "scene position of the device origin (3 values)")->expected(3);
  app.add_option("--grab-body", o.grab_body, "body to grab (-1: nearest to the device point)")->capture_default_str();
  app.add_option("--max-force-n", o.max_force_n, "force clamp, N")->capture_default_str();
  app.add_option("--stale-after-s", o.stale_after_s, "watchdog: input age that counts as stale")->capture_default_str();
  app.add_option("--user-force-rate-hz", o.user_force_rate_hz, "USER_FORCE publication rate")->capture_default_str();
  haptree::device::DeviceLimitOptions limits;   // gains vs device and passivity bound (docs/devices.md)
  haptree::device::add_device_limit_options(app, limits);
  CLI11_PARSE(app, argc, argv);
  if (!haptree::device::enforce_device_limits(limits, o.stiffness, o.damping, o.position_scale, o.force_scale,
                                              o.max_force_n, o.rate_hz, "coupler"))
    return 2;
  o.offset = haptree::Vec3(offset[0], offset[1], offset[2]);
  o.shm = b.shm;
  o.channel_suffix = b.channel_suffix;
  std::atomic<bool>& g_stop = haptree::bus::install_stop_signals();
  try {
    haptree::bus::Bus bus(b.lcm_url);
    haptree::bus::HandlerThread handler(bus);
    haptree::Coupler coupler(bus, o);
    const int rc = coupler.run(g_stop);
    handler.stop();   // no callback may run into a destroyed Coupler
    spdlog::info("coupler: {} iterations, {} snapshots, {} rejected", coupler.counters().iterations.load(),
                 coupler.counters().snapshots_accepted.load(), coupler.rejected_messages());
    return rc;
  } catch (const std::exception& e) {
    spdlog::critical("{}", e.what());
    return 1;
  }
}
