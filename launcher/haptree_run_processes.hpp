#pragma once
// `haptree_run --processes`: the launcher's session with the real sim_server, coupler and device_bridge
// executables as child processes on this host (docs/processes.md).
#include <atomic>
#include <limits>
#include <string>
#include <vector>

#include "haptree/bus/session_config.hpp"
#include "sim_server/sim_server.hpp"

namespace haptree::launcher {

struct ProcessesOptions {
  bool enabled = false;
  std::string bin_dir;            // "" = next to haptree_run in the build tree
  std::string transport = "shm";  // shm (+ loopback tcpq hub) | udpm (private netns only)
  std::string log_dir;            // "" = mkdtemp /tmp/haptree_run.XXXXXX
  std::string argv0;
};

// The launcher's session options (the same for both modes).
struct SessionOptions {
  SimServerOptions sim;
  double duration_s = 10;
  int users = 1;
  double coupler_rate_hz = 10000;
  double position_scale = 10, force_scale = 0.5, stiffness = 20, damping = 0, max_force_n = 3;
  double pull_distance_m = 0.03;
  double stale_after_s = 0.05;   // coupler watchdog (haptree_run passes the coupler's default)
  double mirror_rate_hz = 100;   // device_bridge's shm -> LCM mirror (FEEDBACK + the state it answers)
  // Viewer: port 0 = none. Users below scripted_users run the scripted pull until their page
  // takes over; the others are browser-only (idle until a tab grabs). -1 = all scripted, no browser.
  int viewer_port = 0;
  std::string viewer_bind = "127.0.0.1";
  // Viewer access (viewer --viewer-token-file etc.): "" token file = a random token the launcher writes into
  // the log folder (mode 0600) for the viewer and prints in the URL.
  std::string viewer_token_file, viewer_watch_token_file, viewer_tls_cert, viewer_tls_key;
  bool viewer_no_token = false;
  std::vector<std::string> viewer_mesh_paths;
  int scripted_users = -1;
  // Each user's device (one per user): kind "" = the scripted pull (or the page's browser device);
  // otherwise a registry kind (device_bridge --device-kind) with its key=value options.
  std::vector<bus::UserDevice> user_devices;
  // The gain check's options (--device-model, --clamp-gains, ...): the coupler of each user with an own
  // device runs the check again against the limits its device_bridge reports at open.
  std::string device_model = "simulated";
  bool clamp_gains = false;
  double device_damping_n_s_per_m = std::numeric_limits<double>::quiet_NaN();   // NaN: the table's
  double sim_dt_s = 1e-3;
  std::string session_key_file;   // "" = none (or $HAPTREE_SESSION_KEY_FILE, which the children inherit)
  bool json = false;              // status as one JSON object per line
};

// "" if this process runs in a network namespace other than PID 1's and without a default route
// (udpm ttl=0 there cannot reach another machine); otherwise the reason, in plain words.
std::string private_netns_problem();

// Spawns the children, prints the status line every second and the summary, stops them after
// duration_s or when `stop` becomes true (SIGTERM, then SIGKILL after 5 s), reaps them. Returns 0 if
// every child exited 0 after being asked to, 1 (with the child's log tail on stderr) otherwise.
int run_processes(const ProcessesOptions& po, const SessionOptions& se, const std::atomic<bool>& stop);

}  // namespace haptree::launcher
