// haptree_run: the README's main command. Starts sim_server, one coupler and one device_bridge per user
// as threads over one memq:// Bus (the embedded default: same classes as the three processes), shows a
// live status line once per second and a summary at the end. No display, no network needed.
// --processes: the same session with the three real executables as child processes on this host
// (tools/haptree_run_processes.cpp): device link over shared memory, the rest over a loopback-only LCM
// tcpq hub run by the launcher (or udpm, only inside a private network namespace).
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "coupler/coupler.hpp"
#include "device_bridge/device_bridge.hpp"
#include "haptree/bus/bus.hpp"
#include "haptree/dca.hpp"
#include "haptree/device/device_cli.hpp"
#include "sim_server/sim_server.hpp"
#include "tools/haptree_run_processes.hpp"

namespace {
std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop = true; }
}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"haptree_run: sim_server + coupler + scripted device (grab, pull, release). Default: one process,\n"
               "the three classes in threads over memq://. --processes: the three real executables as child\n"
               "processes on this host (device link over shared memory, the rest over a 127.0.0.1-only LCM\n"
               "tcpq hub run by haptree_run; nothing leaves the machine); Ctrl-C/SIGTERM stop and reap them,\n"
               "exit code 1 with the child's log tail if any child fails"};
  haptree::SimServerOptions so;
  so.scene = "protein_like";
  so.n = 64;
  so.rate_hz = 1000;
  double duration_s = 10;
  int users = 1;
  double coupler_rate_hz = 10000;
  double position_scale = 10, force_scale = 0.5, stiffness = 20, damping = 0, max_force_n = 3;
  double pull_distance_m = 0.03;
  std::string lcm_url = "memq://";
  app.add_option("--scene", so.scene, "chain|binary_tree|random_tree|star|protein_like, molecule name or PDB")->capture_default_str();
  app.add_option("--n", so.n, "bodies of a procedural scene")->capture_default_str();
  app.add_option("--urdf", so.urdf, "URDF file instead of --scene");
  app.add_option("--budget-dofs", so.budget_dofs, "adaptive budget")->capture_default_str();
  app.add_option("--dt", so.dt, "sim time step (scene units)")->capture_default_str();
  std::vector<double> gravity;
  app.add_option("--gravity", gravity,
                 "X,Y,Z gravity of procedural/URDF scenes, m/s^2 (default: none for protein_like, which "
                 "stands for a molecule; 0,0,-9.81 for the robot scenes; molecules never have gravity)")
      ->delimiter(',')->expected(3);
  app.add_option("--sim-rate-hz", so.rate_hz, "sim step rate (0 = free-running)")->capture_default_str();
  app.add_option("--duration-s", duration_s, "wall-clock run time")->capture_default_str();
  app.add_option("--users", users, "users (one coupler + one scripted device each, pulling different bodies)")
      ->check(CLI::Range(1, 8))->capture_default_str();
  app.add_option("--coupler-rate-hz", coupler_rate_hz, "coupling loop rate")->capture_default_str();
  app.add_option("--position-scale", position_scale, "scene length per device metre")->capture_default_str();
  app.add_option("--force-scale", force_scale, "N per scene force unit")->capture_default_str();
  app.add_option("--stiffness", stiffness, "k_s (scene units)")->capture_default_str();
  app.add_option("--damping", damping, "b_s (scene units)")->capture_default_str();
  app.add_option("--max-force-n", max_force_n, "device force limit")->capture_default_str();
  app.add_option("--pull-distance-m", pull_distance_m, "scripted pull, device metres")->capture_default_str();
  app.add_option("--lcm-url", lcm_url, "bus for all threads (memq:// keeps everything in-process; embedded mode only)")
      ->capture_default_str();
  haptree::tools::ProcessesOptions po;
  app.add_flag("--processes", po.enabled,
               "run sim_server, coupler(s) and device_bridge(s) as real child processes instead of threads");
  app.add_option("--bin-dir", po.bin_dir,
                 "--processes: folder holding sim_server, coupler, device_bridge (default: found next to "
                 "haptree_run in the build tree: ../sim_server/sim_server etc., or the same folder)");
  app.add_option("--transport", po.transport,
                 "--processes: shm = device link over shared memory + loopback tcpq hub (127.0.0.1) for the rest; "
                 "udpm = everything over udpm ttl=0, refused unless haptree_run runs in a private network "
                 "namespace (e.g. `unshare -n` with a multicast route on lo)")
      ->check(CLI::IsMember({"shm", "udpm"}))->capture_default_str();
  app.add_option("--log-dir", po.log_dir,
                 "--processes: folder for the children's logs (default: a new /tmp/haptree_run.XXXXXX)");
  haptree::device::DeviceLimitOptions limits;   // gains vs device and passivity bound (docs/devices.md)
  haptree::device::add_device_limit_options(app, limits, /*with_sim_dt=*/false);
  CLI11_PARSE(app, argc, argv);
  limits.sim_dt_s = so.rate_hz > 0 ? 1.0 / so.rate_hz : limits.sim_dt_s;   // one snapshot per sim step
  if (!haptree::device::enforce_device_limits(limits, stiffness, damping, position_scale, force_scale,
                                              max_force_n, coupler_rate_hz, "haptree_run"))
    return 2;
  if (gravity.size() == 3) so.gravity = haptree::Vec3(gravity[0], gravity[1], gravity[2]);
  so.users = users;
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  if (po.enabled) {
    po.argv0 = argv[0];
    haptree::tools::SessionOptions se;
    se.sim = so;
    se.duration_s = duration_s;
    se.users = users;
    se.coupler_rate_hz = coupler_rate_hz;
    se.position_scale = position_scale;
    se.force_scale = force_scale;
    se.stiffness = stiffness;
    se.damping = damping;
    se.max_force_n = max_force_n;
    se.pull_distance_m = pull_distance_m;
    return haptree::tools::run_processes(po, se, g_stop);
  }
  try {
    haptree::bus::Bus bus(lcm_url);
    haptree::SimServer server(bus, so);
    const haptree::Model& model = server.model();
    // Bodies to pull: spread over the model; the device's grab waypoint maps exactly onto each body's
    // origin at q = 0 (offset), so the coupler's nearest-body pick takes that body.
    haptree::Data d0(model);
    haptree::State s0(model);
    haptree::forward_kinematics(model, d0, s0.q);
    const haptree::Vec3 grab_m(0.0, 0.0, 0.01);
    std::vector<std::unique_ptr<haptree::Coupler>> couplers;
    std::vector<std::unique_ptr<haptree::DeviceBridge>> bridges;
    std::vector<int> bodies;
    for (int u = 0; u < users; ++u) {
      const int b = std::max(1, (model.nbodies - 1) - u * (model.nbodies - 1) / (users + 1));
      bodies.push_back(b);
      haptree::CouplerOptions co;
      co.user = u;
      co.device = u;
      co.rate_hz = coupler_rate_hz;
      co.busy_wait = false;   // threads share 2 cores with the sim: sleep-until pacing
      co.stiffness = stiffness;
      co.damping = damping;
      co.position_scale = position_scale;
      co.force_scale = force_scale;
      co.max_force_n = max_force_n;
      co.grab_body = b;
      co.offset = d0.r[b] - position_scale * grab_m;
      co.stale_after_s = 0.05;   // in-process on shared cores: tolerate sim steps up to 50 ms
      couplers.push_back(std::make_unique<haptree::Coupler>(bus, co));
      haptree::DeviceBridgeOptions bo;
      bo.device = u;
      bo.kind = "scripted";
      bo.rate_hz = 1000;
      bo.max_force_n = max_force_n;
      bo.feedback_timeout_s = 0.05;
      bo.options["grab_m"] = "0,0,0.01";
      bo.options["pull_distance_m"] = std::to_string(pull_distance_m);
      bo.options["pull_direction"] = u % 2 == 0 ? "1,0,0" : "0,1,0";
      bo.options["hold_s"] = std::to_string(std::max(0.5, duration_s - 3.0));
      bridges.push_back(std::make_unique<haptree::DeviceBridge>(bus, bo));
    }
    spdlog::info("haptree_run: scene {} ({} bodies, {} DOF), {} user(s) pulling bodies {}, {:.0f} s", so.scene,
                 model.nbodies - 1, model.nv, users, fmt::join(bodies, ","), duration_s);
    haptree::bus::HandlerThread handler(bus, 5);
    std::atomic<bool> stop{false};
    std::vector<std::thread> threads;
    threads.emplace_back([&] { server.run(stop); });
    for (auto& c : couplers) threads.emplace_back([&stop, p = c.get()] { p->run(stop); });
    for (auto& b : bridges) threads.emplace_back([&stop, p = b.get()] { p->run(stop); });
    const auto t0 = std::chrono::steady_clock::now();
    double max_force = 0, max_rate = 0, sum_step_ms = 0;
    int lines = 0;
    int64_t last_it = 0;
    while (!g_stop) {
      std::this_thread::sleep_for(std::chrono::seconds(1));
      const double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      std::string line = fmt::format("t {:5.1f} s | sim step {:6.3f} ms, {:3d} active DOF, {} steps", t,
                                     server.last_step_ms(), server.active_dofs(), server.steps_done());
      for (auto& c : couplers) {
        const auto& k = c->counters();
        max_force = std::max(max_force, k.force_n.load());
        max_rate = std::max(max_rate, k.rate_hz.load());
        line += fmt::format(" | user {}: {:6.0f} Hz, |f| {:5.3f} N, snapshot age {:5.1f} ms", c->options().user,
                            k.rate_hz.load(), k.force_n.load(), k.snapshot_age_ms.load());
      }
      (void)last_it;
      sum_step_ms += server.last_step_ms();
      ++lines;
      std::printf("%s\n", line.c_str());
      std::fflush(stdout);
      if (t >= duration_s) break;
    }
    stop = true;
    for (auto& th : threads) th.join();
    handler.stop();
    std::printf("summary: %lld sim steps (%lld snapshots, last %zu bytes), mean sampled step %.3f ms, "
                "%lld blow-up resets\n",
                static_cast<long long>(server.steps_done()), static_cast<long long>(server.snapshots_published()),
                server.last_snapshot_bytes(), lines ? sum_step_ms / lines : 0.0,
                static_cast<long long>(server.resets()));
    for (size_t u = 0; u < couplers.size(); ++u) {
      const auto& k = couplers[u]->counters();
      std::printf("  user %zu: body %d, %lld coupler iterations, %lld snapshots accepted, %lld rejected, "
                  "max |f| at device %.3f N, device pose-to-force latency p50 %.1f us p99 %.1f us\n",
                  u, bodies[u], static_cast<long long>(k.iterations.load()),
                  static_cast<long long>(k.snapshots_accepted.load()),
                  static_cast<long long>(couplers[u]->rejected_messages()), bridges[u]->max_force_seen_n(),
                  bridges[u]->latency_percentile_us(0.5), bridges[u]->latency_percentile_us(0.99));
    }
    std::printf("  peak coupler rate %.0f Hz, peak |f| %.3f N\n", max_rate, max_force);
    return 0;
  } catch (const std::exception& e) {
    spdlog::critical("{}", e.what());
    return 1;
  }
}
