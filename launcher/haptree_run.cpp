// haptree_run: the README's main command. Starts sim_server, one coupler and one device_bridge per user
// as threads over one memq:// Bus (the embedded default: same classes as the three processes), shows a
// live status line once per second and a summary at the end. No display, no network needed.
// --processes: the same session with the three real executables as child processes on this host
// (launcher/haptree_run_processes.cpp): device link over shared memory, the rest over a loopback-only LCM
// tcpq hub run by the launcher (or udpm, only inside a private network namespace).
#include <CLI/CLI.hpp>
#include <spdlog/sinks/stdout_color_sinks.h>
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
#include "haptree/bus/cli.hpp"
#include "haptree/bus/session_config.hpp"
#include "haptree/dca.hpp"
#include "imd_bridge/imd_server.hpp"
#include "haptree/device/device_cli.hpp"
#include "haptree/device/registry.hpp"
#include "sim_server/sim_server.hpp"
#include "launcher/haptree_run_processes.hpp"
#include "launcher/haptree_status.hpp"
#include "viewer/viewer.hpp"

namespace {
std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop = true; }

// The viewer, embedded: the same class as the `viewer` executable, on the session's bus.
struct ViewerLaunch {
  int port = 8080;              // 0 = no viewer
  std::string bind = "127.0.0.1";
  int users = 2;                // tabs that can pull at once (couplers are started for them)
  std::string token_file, watch_token_file, tls_cert, tls_key;
  bool no_token = false;
  std::vector<std::string> mesh_paths;
};
std::unique_ptr<haptree::Viewer> start_viewer(haptree::bus::Bus& bus, const haptree::SimServerOptions& so,
                                              const ViewerLaunch& vl, int users, FILE* out) {
  if (vl.port <= 0) return nullptr;
  haptree::ViewerOptions vo;
  vo.bind = vl.bind;
  vo.port = vl.port;
  vo.scene = so.scene;
  vo.n = so.n;
  vo.urdf = so.urdf;
  vo.users = users;
  vo.token_file = vl.token_file;
  vo.watch_token_file = vl.watch_token_file;
  vo.no_token = vl.no_token;
  vo.tls_cert = vl.tls_cert;
  vo.tls_key = vl.tls_key;
  vo.mesh_paths = vl.mesh_paths;
  auto v = std::make_unique<haptree::Viewer>(bus, vo);
  std::fprintf(out, "viewer: open %s\n", v->url().c_str());
  if (!v->watch_url().empty()) std::fprintf(out, "viewer: watch only %s\n", v->watch_url().c_str());
  std::fflush(out);
  return v;
}
}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"haptree_run: sim_server + coupler + scripted device (grab, pull, release). Default: one process,\n"
               "the three classes in threads over memq://. --processes: the three real executables as child\n"
               "processes on this host (device link over shared memory, the rest over a 127.0.0.1-only LCM\n"
               "tcpq hub run by haptree_run; nothing leaves the machine); Ctrl-C/SIGTERM stop and reap them,\n"
               "exit code 1 with the child's log tail if any child fails"};
  haptree::bus::ProgramCli cli(app, "haptree_run");
  haptree::SimServerOptions so;
  so.scene = "protein_like";
  so.n = 64;
  so.rate_hz = 1000;
  double duration_s = 0;
  ViewerLaunch vl;
  int users = 1;
  double coupler_rate_hz = 10000;
  double position_scale = 10, force_scale = 0.5, stiffness = 20, damping = 0, max_force_n = 3;
  double pull_distance_m = 0.03;
  double stale_after_s = haptree::CouplerOptions{}.stale_after_s;
  std::string lcm_url = "memq://";
  app.add_option("--scene", so.scene, "chain|binary_tree|random_tree|star|protein_like, molecule name or PDB")->capture_default_str();
  app.add_option("--n", so.n, "bodies of a procedural scene (count)")->check(CLI::Range(1, 1 << 20))->capture_default_str();
  app.add_option("--urdf", so.urdf, "URDF file instead of --scene");
  app.add_option("--mesh-path", vl.mesh_paths, "viewer: folder(s) where the URDF's package:// and relative mesh files are found (paths)");
  app.add_option("--budget-dofs", so.budget_dofs, "adaptive budget, active degrees of freedom (count)")->check(CLI::Range(1, 1 << 24))->capture_default_str();
  app.add_option("--dt", so.dt, "time step, scene time units: s for procedural and URDF scenes, ps for molecules (default: 0.001 s; 0.0005 ps for molecules)")->check(haptree::bus::positive(1.0))->capture_default_str();
  std::vector<double> gravity;
  app.add_option("--gravity", gravity,
                 "X,Y,Z gravity of procedural/URDF scenes, m/s^2 (default: none for protein_like, which "
                 "stands for a molecule; 0,0,-9.81 for the robot scenes; molecules never have gravity)")
      ->delimiter(',')->expected(3)->check(haptree::bus::finite_in(-1e4, 1e4));
  app.add_option("--sim-rate-hz", so.rate_hz, "simulation step rate, Hz (0 = free-running)")->check(haptree::bus::finite_in(0, 1e6))->capture_default_str();
  app.add_option("--duration-s", duration_s, "wall-clock run time, s (0 = until Ctrl-C)")
      ->check(haptree::bus::finite_in(0.0, 1e7))->capture_default_str();
  app.add_option("--viewer-port", vl.port,
                 "web viewer's HTTP/WebSocket port: http://127.0.0.1:PORT/ (the scene live; a tab's mouse pulls as a user); 0 = off")
      ->check(CLI::Range(0, 65535))->capture_default_str();
  app.add_option("--viewer-bind", vl.bind, "address the viewer listens on, IPv4 (127.0.0.1: this machine only)")
      ->capture_default_str();
  app.add_option("--viewer-token-file", vl.token_file,
                 "file whose first line is the viewer's token that may pull (default: a random token, printed in the URL)")
      ->check(CLI::ExistingFile);
  app.add_option("--viewer-watch-token-file", vl.watch_token_file, "file whose first line is a watch-only viewer token")
      ->check(CLI::ExistingFile);
  app.add_flag("--viewer-no-token", vl.no_token,
               "viewer without a token (only with a loopback --viewer-bind: anyone on this machine can pull)");
  app.add_option("--viewer-tls-cert", vl.tls_cert, "PEM certificate: the viewer over https:// and wss:// (with --viewer-tls-key)")
      ->check(CLI::ExistingFile);
  app.add_option("--viewer-tls-key", vl.tls_key, "PEM private key of --viewer-tls-cert")->check(CLI::ExistingFile);
  app.add_option("--viewer-users", vl.users,
                 "users a page can be, count (couplers are started for max(--users, this); the ones past --users have "
                 "no script)")->check(CLI::Range(1, 8))->capture_default_str();
  app.add_option("--users", users, "users, count (one coupler + one scripted device each, pulling different bodies)")
      ->check(CLI::Range(1, 8))->capture_default_str();
  app.add_option("--coupler-rate-hz", coupler_rate_hz, "coupling loop rate, Hz")->check(haptree::bus::positive(1e5))->capture_default_str();
  app.add_option("--position-scale", position_scale, "scene length units per device metre (m/m for SI scenes; nm/m for molecules; default 10, 1 for molecules)")->check(haptree::bus::positive(1e12))->capture_default_str();
  app.add_option("--force-scale", force_scale, "N at the device per scene force unit (N/N for SI scenes; N per kJ/(mol nm) for molecules)")->check(haptree::bus::positive(1e12))->capture_default_str();
  app.add_option("--stiffness", stiffness, "coupling stiffness k_s, scene force per scene length (N/m for SI scenes; kJ/(mol nm^2) for molecules; default 20, 200 for molecules)")->check(haptree::bus::positive(1e12))->capture_default_str();
  app.add_option("--damping", damping, "coupling damping b_s, scene force per scene velocity (N s/m for SI scenes; kJ ps/(mol nm^2) for molecules)")->check(haptree::bus::finite_in(0, 1e12))->capture_default_str();
  app.add_option("--max-force-n", max_force_n, "device force limit, N")->check(haptree::bus::positive(1000))->capture_default_str();
  app.add_option("--stale-after-s", stale_after_s, "coupler watchdog: snapshot/pose age that counts as stale, s")
      ->check(haptree::bus::positive(10))->capture_default_str();
  app.add_option("--pull-distance-m", pull_distance_m, "scripted pull distance, device m")->check(haptree::bus::finite_in(-1, 1))->capture_default_str();
  app.add_option("--lcm-url", lcm_url, "bus for all threads (memq:// keeps everything in-process; embedded mode only)")
      ->capture_default_str();
  std::string device_kind;
  std::vector<std::string> device_options;
  app.add_option("--device-kind", device_kind,
                 "user 0's device instead of the scripted pull: a device_bridge kind (" +
                     fmt::format("{}", fmt::join(haptree::device::device_names(), " | ")) +
                     ", or one a plug-in registers); the other users keep the script unless the session file's\n"
                     "[user.N] names their device");
  app.add_option("--device-option", device_options,
                 "option of --device-kind's device, key=value (repeat for several; see docs/devices.md)")
      ->check(CLI::Validator(
          [](std::string& in) -> std::string {
            return in.find('=') == std::string::npos || in.front() == '=' ? "'" + in + "' is not key=value" : "";
          },
          "KEY=VALUE"));
  haptree::launcher::ProcessesOptions po;
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
  double mirror_rate_hz = 100;
  app.add_option("--mirror-rate-hz", mirror_rate_hz,
                 "--processes --transport shm: rate at which each device_bridge republishes on the bus a FEEDBACK and "
                 "the device state it answers (what lcm-logger records and replay_coupling replays); 0: off")
      ->check(CLI::Range(0.0, 10000.0))->capture_default_str();
  app.add_option("--log-dir", po.log_dir,
                 "--processes: folder for the children's logs (default: a new /tmp/haptree_run.XXXXXX)");
  // ---- IMD: --imd-port serves the session over IMD from inside the launcher; the IMD pull
  // is one more user (id = --users), which sim_server listens to. ----
  haptree::ImdServerOptions imd;
  imd.port = 0;   // 0 here = off
  app.add_option("--imd-port", imd.port,
                 "serve the session over IMD on this TCP port (VMD: `mol new <pdb>`, `imd connect localhost PORT`); "
                 "molecular scenes; 0 = off")->check(CLI::Range(0, 65535))->capture_default_str();
  app.add_option("--imd-bind", imd.bind, "IMD listen address, IPv4")->capture_default_str();
  app.add_option("--imd-version", imd.version, "IMD version announced: 2 (VMD) or 3")->check(CLI::IsMember({2, 3}))
      ->capture_default_str();
  // ---- end IMD options ----
  haptree::device::DeviceLimitOptions limits;   // gains vs device and passivity bound (docs/devices.md)
  haptree::device::add_device_limit_options(app, limits, /*with_sim_dt=*/false);
  std::string session_key_file;
  app.add_option("--session-key-file", session_key_file,
                 "session key (>= 32 bytes, chmod 600), given to every process of the session: every message "
                 "carries a MAC and a sequence number; messages without the right MAC are dropped and counted")
      ->envname("HAPTREE_SESSION_KEY_FILE")
      ->each([](const std::string& path) { haptree::bus::set_process_session_key_file(path); });
  bool json = false;
  app.add_flag("--json", json,
               "status as JSON for scripts: one object per line per status tick (stdout), instead of the text line");
  const int rc = cli.parse(argc, argv, [&] {   // molecules: their own time step, device mapping and spring
    const haptree::bus::SceneDefaults sd = haptree::bus::scene_defaults(so.scene, so.urdf);
    haptree::bus::set_default(app, "--dt", so.dt, sd.dt);
    haptree::bus::set_default(app, "--position-scale", position_scale, sd.position_scale);
    haptree::bus::set_default(app, "--stiffness", stiffness, sd.stiffness);
  });
  if (rc >= 0) return rc;
  if (json) spdlog::set_default_logger(spdlog::stderr_color_mt("haptree_run"));   // stdout: the status objects only
  limits.sim_dt_s = so.rate_hz > 0 ? 1.0 / so.rate_hz : limits.sim_dt_s;   // one snapshot per sim step
  if (!haptree::device::enforce_device_limits(limits, stiffness, damping, position_scale, force_scale,
                                              max_force_n, coupler_rate_hz, "haptree_run"))
    return 2;
  if (so.scene == "protein_like" && app.count("--n") > 0 && so.urdf.empty())
    spdlog::warn("--n {} is ignored: protein_like has a fixed size (343 backbone bodies, 857 DOF)", so.n);
  if (gravity.size() == 3) so.gravity = haptree::Vec3(gravity[0], gravity[1], gravity[2]);
  const int scripted_users = users;
  if (vl.port > 0) users = std::max(users, vl.users);   // couplers + browser devices for every page user
  so.users = users;
  // Each user's own device: user 0's from the command line (or [user.0]), the others' from [user.N].
  std::vector<haptree::bus::UserDevice> user_devices(static_cast<size_t>(users));
  user_devices[0] = {device_kind, device_options};
  for (const auto& [u, d] : cli.file_user_devices()) {
    if (u >= users) {
      spdlog::critical("haptree_run: the session file's [user.{}] names a device, but the session has {} user(s) "
                       "(--users)", u, users);
      return 2;
    }
    if (d.kind.empty()) {
      spdlog::critical("haptree_run: the session file's [user.{}] has device-option but no device-kind", u);
      return 2;
    }
    user_devices[static_cast<size_t>(u)] = d;
  }
  // The server's limit on incoming user forces: the coupler's own clamp (2 x max_force_n / force_scale).
  {
    haptree::CouplerOptions co;
    co.max_force_n = max_force_n;
    co.force_scale = force_scale;
    so.max_user_force = haptree::user_force_limit(co);
  }
  if (imd.port > 0) {   // IMD: one more user for the IMD pull
    if (po.enabled) {
      std::fprintf(stderr, "haptree_run: --imd-port runs in the embedded launcher; with --processes start "
                           "build/imd_bridge/imd_bridge beside sim_server (README: VMD through IMD)\n");
      return 2;
    }
    so.users = users + 1;
    imd.user_id = users;
    imd.scene = so.scene;
    so.max_user_force = std::max(so.max_user_force, imd.max_force);   // the IMD pull has its own clamp
  }
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  if (po.enabled) {
    po.argv0 = argv[0];
    haptree::launcher::SessionOptions se;
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
    se.stale_after_s = stale_after_s;
    se.mirror_rate_hz = mirror_rate_hz;
    se.viewer_port = vl.port;
    se.viewer_bind = vl.bind;
    se.viewer_token_file = vl.token_file;
    se.viewer_watch_token_file = vl.watch_token_file;
    se.viewer_tls_cert = vl.tls_cert;
    se.viewer_tls_key = vl.tls_key;
    se.viewer_no_token = vl.no_token;
    se.viewer_mesh_paths = vl.mesh_paths;
    se.scripted_users = vl.port > 0 ? scripted_users : -1;
    se.user_devices = user_devices;
    se.session_key_file = session_key_file;
    se.json = json;
    se.device_model = limits.model;
    se.clamp_gains = limits.clamp;
    se.device_damping_n_s_per_m = limits.physical_damping_n_s_per_m;
    se.sim_dt_s = limits.sim_dt_s;
    return haptree::launcher::run_processes(po, se, g_stop);
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
      haptree::DeviceBridgeOptions bo;
      bo.device = u;
      bo.kind = vl.port > 0 ? "browser" : "scripted";   // with a viewer the page can take the user over
      if (vl.port > 0) bo.options["fallback"] = u < scripted_users ? "scripted" : "none";
      bo.rate_hz = 1000;
      bo.max_force_n = max_force_n;
      bo.feedback_timeout_s = 0.05;
      bo.options["grab_m"] = "0,0,0.01";
      bo.options["pull_distance_m"] = std::to_string(pull_distance_m);
      bo.options["pull_direction"] = u % 2 == 0 ? "1,0,0" : "0,1,0";
      bo.options["hold_s"] = std::to_string(duration_s > 0 ? std::max(0.5, duration_s - 3.0) : 1e9);
      if (const auto& ud = user_devices[static_cast<size_t>(u)]; !ud.kind.empty()) {   // own device, not the script
        bo.kind = ud.kind;
        bo.options.clear();
        for (const auto& kv : ud.options) {
          const auto eq = kv.find('=');
          bo.options[kv.substr(0, eq)] = kv.substr(eq + 1);
        }
      }
      bridges.push_back(std::make_unique<haptree::DeviceBridge>(bus, bo));
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
      // A page's pointer may reach any atom (the browser device inverts the mapping): the glitch limit on
      // device positions covers twice the scene's reach from the grabbed body, at least the 1 m default.
      double reach = 0;
      for (int k = 1; k < model.nbodies; ++k) reach = std::max(reach, (d0.r[k] - d0.r[b]).norm());
      co.max_device_position_m = std::min(1e3, std::max(co.max_device_position_m, 2.0 * reach / position_scale));
      co.model_fingerprint = model.fingerprint;   // refuse any other model on the bus
      co.stale_after_s = stale_after_s;
      // The user's own device reported its limits at open: the gains are checked against them too.
      if (!user_devices[static_cast<size_t>(u)].kind.empty()) {
        const haptree::device::DeviceDescription d = bridges.back()->description();
        if (!haptree::device::enforce_device_limits(limits, co.stiffness, co.damping, co.position_scale, co.force_scale,
                                                    co.max_force_n, co.rate_hz, "haptree_run", &d))
          return 2;
      }
      couplers.push_back(std::make_unique<haptree::Coupler>(bus, co));
    }
    spdlog::info("haptree_run: scene {} ({} bodies, {} DOF), {} user(s) pulling bodies {}, {}", so.scene,
                 model.nbodies - 1, model.nv, users, fmt::join(bodies, ","),
                 duration_s > 0 ? fmt::format("{:.0f} s", duration_s) : std::string("until Ctrl-C"));
    std::unique_ptr<haptree::Viewer> viewer = start_viewer(bus, so, vl, users, json ? stderr : stdout);
    // IMD: the ImdServer on the same bus, in its own thread (binds before the session starts).
    std::unique_ptr<haptree::ImdServer> imd_server;
    if (imd.port > 0) imd_server = std::make_unique<haptree::ImdServer>(bus, imd);
    haptree::bus::HandlerThread handler(bus, 5);
    std::atomic<bool> stop{false};
    std::vector<std::thread> threads;
    threads.emplace_back([&] { server.run(stop); });
    for (auto& c : couplers) threads.emplace_back([&stop, p = c.get()] { p->run(stop); });
    for (auto& b : bridges) threads.emplace_back([&stop, p = b.get()] { p->run(stop); });
    if (viewer) threads.emplace_back([&stop, p = viewer.get()] { p->run(stop); });
    std::thread imd_thread;   // IMD: its own thread, joined with the others
    if (imd_server) imd_thread = std::thread([&] { imd_server->run(stop); });
    const auto t0 = std::chrono::steady_clock::now();
    double max_force = 0, max_rate = 0, sum_step_ms = 0;
    int lines = 0;
    while (!g_stop) {
      std::this_thread::sleep_for(std::chrono::seconds(1));
      const double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      haptree::launcher::StatusSample st;
      st.t_s = t;
      st.sim.started = server.steps_done() > 0;
      st.sim.step_ms = server.last_step_ms();
      st.sim.active_dofs = server.active_dofs();
      st.sim.steps = server.steps_done();
      for (auto& c : couplers) {
        const auto& k = c->counters();
        max_force = std::max(max_force, k.force_n.load());
        max_rate = std::max(max_rate, k.rate_hz.load());
        haptree::launcher::UserStatus us;
        us.user = c->options().user;
        us.started = true;
        us.rate_hz = k.rate_hz.load();   // 0 until the first window closes: shown as "—"
        us.force_n = k.force_n.load();
        us.grab_body = k.rate_hz.load() > 0 ? k.grab_body.load() : -1;
        us.snapshot_age_ms = k.snapshot_age_ms.load();
        st.users.push_back(us);
      }
      if (imd_server) {   // IMD status
        st.imd.on = true;
        st.imd.port = imd_server->port();
        st.imd.receiver = imd_server->client_connected();
        st.imd.frames = imd_server->counters().frames_sent.load();
      }
      const std::string line = json ? haptree::launcher::status_json(st) : haptree::launcher::status_text(st);
      sum_step_ms += server.last_step_ms();
      ++lines;
      std::printf("%s\n", line.c_str());
      std::fflush(stdout);
      if (duration_s > 0 && t >= duration_s) break;
    }
    stop = true;
    FILE* out = json ? stderr : stdout;   // --json: stdout carries only the status objects
    for (auto& th : threads) th.join();
    if (imd_thread.joinable()) imd_thread.join();
    handler.stop();
    std::fprintf(out, "summary: %lld sim steps (%lld snapshots, last %zu bytes), mean sampled step %.3f ms, "
                "longest step after the first %.2f ms (step %lld), %lld blow-up resets\n",
                static_cast<long long>(server.steps_done()), static_cast<long long>(server.snapshots_published()),
                server.last_snapshot_bytes(), lines ? sum_step_ms / lines : 0.0, server.longest_step_ms(),
                static_cast<long long>(server.longest_step_index()), static_cast<long long>(server.resets()));
    for (size_t u = 0; u < couplers.size(); ++u) {
      const auto& k = couplers[u]->counters();
      std::fprintf(out, "  user %zu: body %d, %lld coupler iterations, %lld snapshots accepted, %lld rejected, "
                   "max |f| at device %.3f N, device pose-to-force latency p50 %.1f us p99 %.1f us, "
                   "%lld watchdog trips (%lld while pulling), oldest input while pulling %.1f ms\n",
                  u, bodies[u], static_cast<long long>(k.iterations.load()),
                  static_cast<long long>(k.snapshots_accepted.load()),
                  static_cast<long long>(couplers[u]->rejected_messages()), bridges[u]->max_force_seen_n(),
                  bridges[u]->latency_percentile_us(0.5), bridges[u]->latency_percentile_us(0.99),
                  static_cast<long long>(couplers[u]->watchdog_trips()),
                  static_cast<long long>(k.grab_watchdog_trips.load()), k.max_grab_input_age_ms.load());
    }
    std::fprintf(out, "  peak coupler rate %.0f Hz, peak |f| %.3f N\n", max_rate, max_force);
    if (viewer)
      std::fprintf(out, "  viewer: %lld frames sent, %lld dropped for slow tabs, %lld pointer messages\n",
                  static_cast<long long>(viewer->frames_sent()), static_cast<long long>(viewer->frames_dropped()),
                  static_cast<long long>(viewer->pointer_messages()));
    if (imd_server) {   // IMD summary
      const auto& k = imd_server->counters();
      std::fprintf(out, "  imd: %lld receiver(s), %lld dropped, %lld frames sent (%lld skipped), %lld MDCOMM packets\n",
                  static_cast<long long>(k.clients.load()), static_cast<long long>(k.dropped.load()),
                  static_cast<long long>(k.frames_sent.load()), static_cast<long long>(k.frames_skipped.load()),
                  static_cast<long long>(k.mdcomm.load()));
    }
    return 0;
  } catch (const std::exception& e) {
    spdlog::critical("{}", e.what());
    return 1;
  }
}
