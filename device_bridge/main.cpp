// device_bridge: runs one device (scripted, virtual_hand, replay, SDK) and links it to its coupler.
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <atomic>
#include <string>
#include <vector>

#include "device_bridge/device_bridge.hpp"
#include "haptree/bus/cli.hpp"
#include "haptree/bus/realtime_cli.hpp"
#include "haptree/bus/session_config.hpp"

int main(int argc, char** argv) {
  CLI::App app{"haptree device_bridge: device <-> DEVICE_STATE / FEEDBACK"};
  haptree::bus::ProgramCli cli(app, "device_bridge",
                               {{"--rate-hz", "--device-rate-hz"}, {"--kind", "--device-kind"}, {"--option", "--device-option"}},
                               "device");
  haptree::DeviceBridgeOptions o;
  haptree::bus::BusOptions b;
  haptree::bus::add_bus_options(app, b);
  std::vector<std::string> kv;
  app.add_option("--device", o.device, "device id (HAPTREE_DEVICE_STATE_<id>, HAPTREE_FEEDBACK_<id>; picks the session file's [user.N])")->check(CLI::Range(0, 1000000))->capture_default_str();
  app.add_option("--device-kind", o.kind,
                 "the device, by name: scripted | virtual_hand | replay | browser (the mouse in the viewer's page; "
                 "--device-option fallback=scripted keeps the script until the page's first press) | openhaptics (3D "
                 "Systems Touch, Phantom) | forcedimension (omega, delta, sigma, lambda, Novint Falcon) | inverse3 "
                 "(Haply Inverse3 through the Haply Inverse Service); docs/devices.md")
      ->capture_default_str();
  app.add_option("--device-option", kv, "device option key=value, repeated (e.g. pull_distance_m=0.03, log=FILE; real "
                                        "devices: lib=PATH, axes=y,z,x, openhaptics name=NAME, forcedimension id=N, "
                                        "inverse3 url=ws://127.0.0.1:10001 device_id=ID)");
  bool probe = false;
  app.add_flag("--probe", probe, "open the device, print its model, serial, limits, position and buttons, close it "
                                 "and exit (0; 1 if it cannot be opened or read). Force output stays off");
  app.add_option("--device-rate-hz", o.rate_hz, "device loop rate, Hz")->check(haptree::bus::positive(1e5))->capture_default_str();
  app.add_option("--max-force-n", o.max_force_n, "device force limit, N")->check(haptree::bus::positive(1000))->capture_default_str();
  haptree::bus::RealtimeOptions rt;   // docs/performance.md, "Latency per transport"
  haptree::bus::add_realtime_options(app, rt,
                                     "after publishing a pose, poll shared-memory feedback until its answer arrives "
                                     "(then sleep to the next tick) instead of waiting for the next tick");
  app.add_option("--max-force-rate-n-per-s", o.max_force_rate_n_per_s,
                 "bound on any change of the rendered force, N/s (a jerk guard at the hand); 0: the clamp within "
                 "5 ms, 600 N/s for 3 N. FEEDBACK older than 10 ms ramps to zero in 5 ms, and back in over 0.1 s")
      ->check(CLI::Range(0.0, 1e6))->capture_default_str();
  app.add_option("--feedback-timeout-s", o.feedback_timeout_s,
                 "FEEDBACK older than this ramps the force to zero (the device's own watchdog), s")
      ->check(CLI::Range(1e-4, 10.0))->capture_default_str();
  if (const int rc = cli.parse(argc, argv); rc >= 0) return rc;
  o.busy_poll = rt.busy_poll;
  for (const auto& s : kv) {
    const auto eq = s.find('=');
    if (eq == std::string::npos) {
      spdlog::critical("--device-option '{}': expected key=value", s);
      return 2;
    }
    o.options[s.substr(0, eq)] = s.substr(eq + 1);
  }
  if (probe) return haptree::probe_device(o, 0.2, stdout, stderr);
  haptree::install_device_crash_handlers();   // a crash still writes zero force to a real device
  o.shm = b.shm;
  o.mirror_rate_hz = b.mirror_rate_hz;
  o.channel_suffix = b.channel_suffix;
  std::atomic<bool>& g_stop = haptree::bus::install_stop_signals();
  const haptree::bus::RealtimeReport rt_report = haptree::bus::apply_realtime(rt);   // before any thread
  haptree::bus::log_realtime_report(rt_report, "device_bridge");
  try {
    haptree::bus::Bus bus(b.lcm_url);
    haptree::bus::HandlerThread handler(bus);
    // over udpm the handler brings the feedback: above the loop; over shm it carries nothing the loop
    // waits for: below, so the group's datagrams never delay a pose's answer
    if (const auto w = haptree::bus::set_io_thread_priority(handler.native_handle(), rt_report, !o.shm); !w.empty())
      spdlog::warn("device_bridge: real-time: {}", w);
    haptree::DeviceBridge bridge(bus, o);
    const int rc = bridge.run(g_stop);
    handler.stop();
    if (rc == haptree::kExitDeviceFault)
      spdlog::critical("device_bridge {}: {}; zero force and torque written, force output off, device closed",
                       o.device, bridge.fault());
    spdlog::info("device_bridge: {} readings, {} feedbacks, max |f| {:.3f} N, pose-to-force latency p50 {:.1f} us "
                 "p99 {:.1f} us ({} samples), p99.9 {:.1f} us, max force step {:.4f} N/tick",
                 bridge.readings(), bridge.feedbacks(), bridge.max_force_seen_n(), bridge.latency_percentile_us(0.5),
                 bridge.latency_percentile_us(0.99), bridge.latency_samples(), bridge.latency_percentile_us(0.999),
                 bridge.max_force_step_n());
    return rc;
  } catch (const std::exception& e) {
    spdlog::critical("{}", e.what());
    return 1;
  }
}
