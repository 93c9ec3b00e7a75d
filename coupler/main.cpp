// coupler: O(log n) force feedback at haptic rate for one user/device.
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <atomic>
#include <chrono>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "coupler/coupler.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/cli.hpp"
#include "haptree/bus/realtime_cli.hpp"
#include "haptree/bus/session_config.hpp"
#include "haptree/device/device_cli.hpp"
#include "haptree/device/reported_limits.hpp"

namespace {

// Waits for device_bridge `device`'s stats carrying its device's limits: 1 and `out` filled, 0 after
// `wait_s` without them, -1 if stopped first.
int wait_reported_limits(haptree::bus::Bus& bus, int device, const std::string& suffix, double wait_s,
                         const std::atomic<bool>& stop, haptree::device::DeviceDescription& out) {
  std::mutex m;
  bool got = false;
  auto& sub = bus.subscribe<haptree::lcmt_process_stats>(
      haptree::bus::channel::stats(haptree::device::bridge_stats_name(device), suffix),
      [&](const haptree::lcmt_process_stats& msg, const std::string&) {
        haptree::device::DeviceDescription d;
        if (!haptree::device::get_reported_limits(msg, d)) return;
        d.model = "device " + std::to_string(device);
        std::lock_guard<std::mutex> l(m);
        out = d;
        got = true;
      });
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(wait_s);
  int rc = 0;
  while (std::chrono::steady_clock::now() < end) {
    if (stop.load()) {
      rc = -1;
      break;
    }
    {
      std::lock_guard<std::mutex> l(m);
      if (got) {
        rc = 1;
        break;
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  sub.close();   // its callback captures this frame
  return rc;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"haptree coupler: O(log n) force feedback at haptic rate (one per user/device)"};
  haptree::bus::ProgramCli cli(app, "coupler", {{"--rate-hz", "--coupler-rate-hz"}}, "user");
  haptree::CouplerOptions o;
  haptree::bus::BusOptions b;
  haptree::bus::add_bus_options(app, b, /*shm_link=*/true, /*mirror=*/false);   // the device_bridge mirrors
  std::vector<double> offset{0, 0, 0};
  app.add_option("--user", o.user, "user id (HAPTREE_COEFFS_<user>, HAPTREE_USER_FORCE_<user>; picks the session file's [user.N])")
      ->check(CLI::Range(0, 1000000))->capture_default_str();
  app.add_option("--device", o.device, "device id (HAPTREE_DEVICE_STATE_<id>, HAPTREE_FEEDBACK_<id>); default: the user id")
      ->check(CLI::Range(0, 1000000));
  app.add_option("--coupler-rate-hz", o.rate_hz, "coupling loop rate, Hz")->check(haptree::bus::positive(1e5))->capture_default_str();
  app.add_flag("!--sleep", o.busy_wait, "pace with sleep_until instead of busy waiting (frees the CPU, costs jitter)");
  app.add_option("--stiffness", o.stiffness, "coupling stiffness k_s, scene force per scene length (N/m for SI scenes; kJ/(mol nm^2) for molecules)")->check(haptree::bus::positive(1e12))->capture_default_str();
  app.add_option("--damping", o.damping, "coupling damping b_s, scene force per scene velocity (N s/m for SI scenes; kJ ps/(mol nm^2) for molecules)")->check(haptree::bus::finite_in(0, 1e12))->capture_default_str();
  app.add_option("--position-scale", o.position_scale, "scene length units per device metre (m/m for SI scenes; nm/m for molecules)")->check(haptree::bus::positive(1e12))->capture_default_str();
  app.add_option("--force-scale", o.force_scale, "N at the device per scene force unit (N/N for SI scenes; N per kJ/(mol nm) for molecules)")->check(haptree::bus::positive(1e12))->capture_default_str();
  app.add_option("--offset", offset, "X,Y,Z scene position of the device origin, scene length units")->delimiter(',')->expected(3)->check(haptree::bus::finite_in(-1e12, 1e12));
  app.add_option("--grab-body", o.grab_body, "body index to grab (-1: the nearest to the device point)")
      ->check(CLI::Range(-1, 1 << 30))->capture_default_str();
  app.add_option("--grab-radius", o.grab_radius,
                 "with --grab-body -1: a press grabs the nearest body only within this distance of the device point, "
                 "scene length units (0: the nearest body wherever it is)")
      ->check(CLI::Range(0.0, 1e12))->capture_default_str();
  app.add_option("--max-force-n", o.max_force_n, "force clamp at the device, N (the user force sent to the server is clamped to 2 x this / --force-scale)")
      ->check(haptree::bus::positive(1000))->capture_default_str();
  app.add_option("--stale-after-s", o.stale_after_s, "watchdog: snapshot or device-pose age (s) that counts as stale; also the silence after which another "
                 "server or device instance is taken as a restart (default measured: docs/performance.md)")
      ->check(haptree::bus::positive(10))->capture_default_str();
  app.add_option("--user-force-rate-hz", o.user_force_rate_hz, "USER_FORCE publication rate, Hz")->check(haptree::bus::positive(1e5))->capture_default_str();
  app.add_option("--max-device-position-m", o.max_device_position_m,
                 "device position glitch limit, m: a device position farther than this from the device origin (or non-finite) is a glitch: refused "
                 "and counted; the watchdog zeroes the force")
      ->check(haptree::bus::positive(1e3))->capture_default_str();
  std::string fingerprint;
  app.add_option("--model-fingerprint", fingerprint,
                 "expected model fingerprint (up to 16 hex digits, as sim_server logs it); snapshots of any other model "
                 "are refused. Default: lock onto the first model heard")
      ->check(CLI::Validator(
          [](std::string& in) -> std::string {
            if (in.empty() || in.size() > 16 || in.find_first_not_of("0123456789abcdefABCDEF") != std::string::npos ||
                std::stoull(in, nullptr, 16) == 0)
              return "'" + in + "' is not a nonzero fingerprint of up to 16 hex digits";
            return "";
          },
          "HEX"));
  haptree::device::DeviceLimitOptions limits;   // gains vs device and passivity bound (docs/devices.md)
  haptree::device::add_device_limit_options(app, limits);
  double device_limits_wait_s = 0;
  app.add_option("--device-limits-wait-s", device_limits_wait_s,
                 "wait up to this long at start for the limits the device reports (device_bridge --device N publishes "
                 "them at open) and check the gains against them too, over --device-model's; s (0: --device-model "
                 "only; none within the wait: a warning, and --device-model only)")
      ->check(CLI::Range(0.0, 600.0))->capture_default_str();
  haptree::bus::RealtimeOptions rt;   // docs/performance.md, "Latency per transport"
  haptree::bus::add_realtime_options(app, rt,
                                     "with busy-wait pacing, iterate as soon as a new device pose arrives instead of "
                                     "at the next tick (pose-to-force latency; the rate stays --coupler-rate-hz)");
  const int rc = cli.parse(argc, argv, [&] {   // a user's own device unless told otherwise
    haptree::bus::set_default(app, "--device", o.device, o.user);
  });
  if (rc >= 0) return rc;
  if (rt.busy_poll && !o.busy_wait) {
    spdlog::critical("--busy-poll needs busy-wait pacing: drop --sleep");
    return 2;
  }
  o.busy_poll = rt.busy_poll;
  if (!haptree::device::enforce_device_limits(limits, o.stiffness, o.damping, o.position_scale, o.force_scale,
                                              o.max_force_n, o.rate_hz, "coupler"))
    return 2;
  o.offset = haptree::Vec3(offset[0], offset[1], offset[2]);
  if (!fingerprint.empty()) o.model_fingerprint = std::stoull(fingerprint, nullptr, 16);
  o.shm = b.shm;
  o.channel_suffix = b.channel_suffix;
  std::atomic<bool>& g_stop = haptree::bus::install_stop_signals();
  const haptree::bus::RealtimeReport rt_report = haptree::bus::apply_realtime(rt);   // before any thread
  haptree::bus::log_realtime_report(rt_report, "coupler");
  try {
    haptree::bus::Bus bus(b.lcm_url);
    haptree::bus::HandlerThread handler(bus);
    // above the loop: the handler brings the snapshots (and the poses over udpm) to a loop that may spin
    if (const auto w = haptree::bus::set_io_thread_priority(handler.native_handle(), rt_report, true); !w.empty())
      spdlog::warn("coupler: real-time: {}", w);
    if (device_limits_wait_s > 0) {
      haptree::device::DeviceDescription reported;
      const int got = wait_reported_limits(bus, o.device, o.channel_suffix, device_limits_wait_s, g_stop, reported);
      if (got < 0) return 0;   // stopped while waiting
      if (got == 0) {
        spdlog::warn("coupler {}: device_bridge {} reported no device limits within {} s: gains checked against "
                     "--device-model {} only", o.user, o.device, device_limits_wait_s, limits.model);
      } else if (!haptree::device::enforce_device_limits(limits, o.stiffness, o.damping, o.position_scale,
                                                         o.force_scale, o.max_force_n, o.rate_hz, "coupler", &reported)) {
        return 2;
      }
    }
    haptree::Coupler coupler(bus, o);
    const int rc = coupler.run(g_stop);
    handler.stop();   // no callback may run into a destroyed Coupler
    const auto& k = coupler.counters();
    spdlog::info("coupler: {} iterations, {} snapshots, {} rejected, {} watchdog trips, {} restarts, {} of {} "
                 "feedbacks while grabbing zeroed by the watchdog",
                 k.iterations.load(), k.snapshots_accepted.load(), coupler.rejected_messages(),
                 coupler.watchdog_trips(), k.restarts.load(), k.grab_watchdog_zeros.load(), k.grab_feedbacks.load());
    return rc;
  } catch (const std::exception& e) {
    spdlog::critical("{}", e.what());
    return 1;
  }
}
