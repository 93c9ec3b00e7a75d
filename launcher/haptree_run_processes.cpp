// `haptree_run --processes`: see haptree_run_processes.hpp.
#include "launcher/haptree_run_processes.hpp"

#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <deque>
#include <fstream>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <vector>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/shm_channel.hpp"
#include "haptree/dca.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "haptree/lcmt_process_stats.hpp"
#include "launcher/find_executable.hpp"
#include "launcher/haptree_status.hpp"
#include "launcher/tcpq_hub.hpp"
#include "viewer/viewer.hpp"

namespace haptree::launcher {

namespace {

using Clock = std::chrono::steady_clock;

struct Child {
  std::string name;
  std::string log;
  pid_t pid = -1;
  bool reaped = false;
  int status = 0;
  bool asked_to_stop = false;
};

std::string describe_status(int st) {
  if (WIFEXITED(st)) return "exit code " + std::to_string(WEXITSTATUS(st));
  if (WIFSIGNALED(st)) return std::string("killed by signal ") + std::to_string(WTERMSIG(st)) + " (" +
                              strsignal(WTERMSIG(st)) + ")";
  return "status " + std::to_string(st);
}

bool clean_exit(const Child& c) { return c.reaped && WIFEXITED(c.status) && WEXITSTATUS(c.status) == 0; }

// fork + exec with stdout/stderr into the log; the child gets its own process group (the launcher
// forwards Ctrl-C itself) and SIGTERM if the launcher dies.
pid_t spawn(const std::vector<std::string>& args, const std::string& log) {
  std::vector<char*> argv;
  for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  const int fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) throw std::runtime_error("cannot create log file " + log + ": " + std::strerror(errno));
  const pid_t parent = ::getpid();
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::setpgid(0, 0);
    ::prctl(PR_SET_PDEATHSIG, SIGTERM);
    if (::getppid() != parent) ::_exit(126);
    ::dup2(fd, 1);
    ::dup2(fd, 2);
    ::execv(argv[0], argv.data());
    const char msg[] = "haptree_run: exec failed\n";
    (void)!::write(2, msg, sizeof(msg) - 1);
    ::_exit(127);
  }
  ::close(fd);
  if (pid < 0) throw std::runtime_error(std::string("fork failed: ") + std::strerror(errno));
  return pid;
}

std::vector<std::string> tail_lines(const std::string& path, size_t n) {
  std::ifstream f(path);
  std::deque<std::string> q;
  std::string line;
  while (std::getline(f, line)) {
    q.push_back(line);
    if (q.size() > n) q.pop_front();
  }
  return {q.begin(), q.end()};
}

// The line of a child's log that contains `key` (the final spdlog summary), "" if none.
std::string find_line(const std::string& path, const std::string& key) {
  std::ifstream f(path);
  std::string line, found;
  while (std::getline(f, line))
    if (line.find(key) != std::string::npos) found = line;
  return found;
}

struct Stats {
  std::mutex m;
  lcmt_process_stats sim{};
  std::vector<lcmt_process_stats> couplers;
  bool have_sim = false;
  std::vector<bool> have_coupler;
};

// A named extra of a stats message, 0 if absent.
double extra_value(const lcmt_process_stats& m, const char* name) {
  for (int i = 0; i < m.n_extra && i < static_cast<int>(m.extra_names.size()); ++i)
    if (m.extra_names[static_cast<size_t>(i)] == name) return m.extra_values[static_cast<size_t>(i)];
  return 0.0;
}

struct FeedbackTally {
  int64_t count = 0, nonfinite = 0;
  double max_n = 0;
  void add(const lcmt_feedback& f) {
    const double x = std::sqrt(f.force_n[0] * f.force_n[0] + f.force_n[1] * f.force_n[1] + f.force_n[2] * f.force_n[2]);
    ++count;
    if (!std::isfinite(x)) ++nonfinite;
    else max_n = std::max(max_n, x);
  }
};

}  // namespace

std::string private_netns_problem() {
  const std::string self = read_link("/proc/self/ns/net"), init = read_link("/proc/1/ns/net");
  if (self.empty()) return "cannot read /proc/self/ns/net";
  if (init.empty()) {
    // PID 1 not visible (container, hidepid): accept only a namespace whose sole interface is lo.
    std::ifstream dev("/proc/self/net/dev");   // this namespace's interfaces (sysfs shows the mounter's)
    if (!dev) return "cannot tell whether this network namespace is private (/proc/1/ns/net and /proc/self/net/dev unreadable)";
    std::string others, l;
    while (std::getline(dev, l)) {
      const auto colon = l.find(':');
      if (colon == std::string::npos) continue;
      const auto b = l.find_first_not_of(' ');
      const std::string name = l.substr(b, colon - b);
      if (name != "lo") others += " " + name;
    }
    if (!others.empty())
      return "/proc/1/ns/net is unreadable and this network namespace has interfaces other than lo (" + others.substr(1) +
             "): udpm could leave this host; use --transport shm, or run in a fresh `unshare -n`";
  } else if (self == init)
    return "haptree_run runs in the machine's own network namespace (" + self +
           "): udpm multicast could leave this host. Run it in a private one, e.g.\n"
           "  sudo unshare -n sh -c 'ip link set lo up && ip link set lo multicast on && "
           "ip route add 224.0.0.0/4 dev lo && haptree_run --processes --transport udpm'\n"
           "or use the default --transport shm (shared memory + 127.0.0.1 hub).";
  std::ifstream r("/proc/net/route");
  std::string line;
  std::getline(r, line);
  while (std::getline(r, line)) {
    char iface[64] = {0};
    unsigned dest = 1;
    if (std::sscanf(line.c_str(), "%63s %x", iface, &dest) == 2 && dest == 0)
      return std::string("this network namespace has a default route (via ") + iface +
             "): udpm could leave this host; use --transport shm";
  }
  return "";
}

int run_processes(const ProcessesOptions& po, const SessionOptions& se, const std::atomic<bool>& stop) {
  std::vector<Child> children;
  auto terminate_all = [&children](double grace_s) {
    // device bridges first (they stop rendering), then couplers, then the server
    for (int pass = 0; pass < 2; ++pass) {
      for (auto it = children.rbegin(); it != children.rend(); ++it) {
        if (it->reaped || it->pid <= 0) continue;
        ::kill(it->pid, pass == 0 ? SIGTERM : SIGKILL);
        it->asked_to_stop = true;
      }
      const auto deadline = Clock::now() + std::chrono::duration<double>(grace_s);
      bool all = false;
      while (!all && Clock::now() < deadline) {
        all = true;
        for (auto& c : children) {
          if (c.reaped || c.pid <= 0) continue;
          if (::waitpid(c.pid, &c.status, WNOHANG) == c.pid) c.reaped = true;
          else all = false;
        }
        if (!all) std::this_thread::sleep_for(std::chrono::milliseconds(5));
      }
      if (all) return;
      if (pass == 0)
        for (auto& c : children)
          if (!c.reaped && c.pid > 0) spdlog::warn("haptree_run: {} (pid {}) ignored SIGTERM for {:.0f} s: SIGKILL",
                                                   c.name, c.pid, grace_s);
    }
    for (auto& c : children)
      if (!c.reaped && c.pid > 0 && ::waitpid(c.pid, &c.status, 0) == c.pid) c.reaped = true;
  };
  // The session's shared-memory segments, unlinked once the children are reaped (a child killed by a
  // signal cannot unlink its own).
  std::vector<std::string> segments;
  auto remove_segments = [&segments] {
    for (const auto& ch : segments) bus::ShmChannel::remove(ch);
  };
  try {
    const bool shm = po.transport == "shm";
    for (const auto& r : bus::reclaim_stale_shm_segments())
      spdlog::info("haptree_run: removed the leftover shared-memory segment {}", r);
    const std::string exe_sim = find_executable("sim_server", po.bin_dir, po.argv0);
    const std::string exe_cpl = find_executable("coupler", po.bin_dir, po.argv0);
    const std::string exe_dev = find_executable("device_bridge", po.bin_dir, po.argv0);
    std::string url;
    std::unique_ptr<TcpqHub> hub;
    if (shm) {
      hub = std::make_unique<TcpqHub>(0);
      url = hub->url();
    } else {
      const std::string why = private_netns_problem();
      if (!why.empty()) {
        spdlog::critical("--transport udpm refused: {}", why);
        return 2;
      }
      url = "udpm://239.255.76.67:7667?ttl=0";
    }
    std::string log_dir = po.log_dir;
    if (log_dir.empty()) {
      char tmpl[] = "/tmp/haptree_run.XXXXXX";
      if (!::mkdtemp(tmpl)) throw std::runtime_error(std::string("mkdtemp failed: ") + std::strerror(errno));
      log_dir = tmpl;
    } else {
      ::mkdir(log_dir.c_str(), 0755);
    }
    // The model (for the pulled bodies and the device offsets): the scene loaded exactly as the server will.
    std::vector<int> bodies;
    std::vector<Vec3> offsets;
  std::vector<double> reaches;   // coupler --max-device-position-m per user
    int nbodies = 0, nv = 0;
    uint64_t fingerprint = 0;
    {
      bus::Bus probe("memq://");
      SimServer server(probe, se.sim);
      const Model& model = server.model();
      nbodies = model.nbodies - 1;
      nv = model.nv;
      fingerprint = model.fingerprint;
      Data d0(model);
      State s0(model);
      forward_kinematics(model, d0, s0.q);
      const Vec3 grab_m(0.0, 0.0, 0.01);
      for (int u = 0; u < se.users; ++u) {
        const int b = std::max(1, (model.nbodies - 1) - u * (model.nbodies - 1) / (se.users + 1));
        bodies.push_back(b);
        offsets.push_back(d0.r[b] - se.position_scale * grab_m);
        double reach = 0;   // a page's pointer may reach any atom: see haptree_run.cpp
        for (int k = 1; k < model.nbodies; ++k) reach = std::max(reach, (d0.r[k] - d0.r[b]).norm());
        reaches.push_back(std::min(1e3, std::max(1.0, 2.0 * reach / se.position_scale)));
      }
    }
    // A suffix of its own: the shared-memory segments and channels of two launchers never mix.
    const std::string suffix = "_R" + std::to_string(::getpid());
    if (shm)
      for (int u = 0; u < se.users; ++u)
        segments.insert(segments.end(), {bus::channel::device_state(u, suffix), bus::channel::feedback(u, suffix)});
    auto bus_owner = std::make_unique<bus::Bus>(url);   // destroyed before the hub (it unsubscribes)
    bus::Bus& bus = *bus_owner;
    Stats stats;
    stats.couplers.resize(static_cast<size_t>(se.users));
    stats.have_coupler.assign(static_cast<size_t>(se.users), false);
    bus.subscribe<lcmt_process_stats>(bus::channel::stats("sim_server", suffix),
                                      [&stats](const lcmt_process_stats& m, const std::string&) {
                                        std::lock_guard<std::mutex> l(stats.m);
                                        stats.sim = m;
                                        stats.have_sim = true;
                                      });
    std::vector<FeedbackTally> tally(static_cast<size_t>(se.users));
    std::mutex tally_m;
    std::vector<std::unique_ptr<bus::ShmReader>> fb_readers;
    for (int u = 0; u < se.users; ++u) {
      bus.subscribe<lcmt_process_stats>(bus::channel::stats("coupler_" + std::to_string(u), suffix),
                                        [&stats, u](const lcmt_process_stats& m, const std::string&) {
                                          std::lock_guard<std::mutex> l(stats.m);
                                          stats.couplers[static_cast<size_t>(u)] = m;
                                          stats.have_coupler[static_cast<size_t>(u)] = true;
                                        });
      if (shm) {
        fb_readers.push_back(std::make_unique<bus::ShmReader>(bus::channel::feedback(u, suffix)));
      } else {
        bus.subscribe<lcmt_feedback>(bus::channel::feedback(u, suffix),
                                     [&tally, &tally_m, u](const lcmt_feedback& f, const std::string&) {
                                       std::lock_guard<std::mutex> l(tally_m);
                                       tally[static_cast<size_t>(u)].add(f);
                                     });
      }
    }
    bus::HandlerThread handler(bus, 5);

    auto fmt_d = [](double v) { return fmt::format("{}", v); };
    std::vector<std::string> common = {"--lcm-url", url, "--channel-suffix", suffix};
    if (!se.session_key_file.empty()) common.insert(common.end(), {"--session-key-file", se.session_key_file});
    std::vector<std::string> sim = {exe_sim};
    sim.insert(sim.end(), common.begin(), common.end());
    if (!se.sim.urdf.empty()) sim.insert(sim.end(), {"--urdf", se.sim.urdf});
    sim.insert(sim.end(), {"--scene", se.sim.scene});
    if (se.sim.scene != "protein_like") sim.insert(sim.end(), {"--n", std::to_string(se.sim.n)});   // fixed size
    sim.insert(sim.end(), {"--budget-dofs", std::to_string(se.sim.budget_dofs), "--dt", fmt_d(se.sim.dt), "--sim-rate-hz",
                           fmt_d(se.sim.rate_hz), "--users", std::to_string(se.users), "--max-user-force",
                           fmt_d(se.sim.max_user_force)});
    if (se.sim.gravity.allFinite())
      sim.insert(sim.end(), {"--gravity", fmt::format("{},{},{}", se.sim.gravity.x(), se.sim.gravity.y(),
                                                      se.sim.gravity.z())});
    children.push_back({"sim_server", log_dir + "/sim_server.log"});
    children.back().pid = spawn(sim, children.back().log);
    for (int u = 0; u < se.users; ++u) {
      const Vec3& o = offsets[static_cast<size_t>(u)];
      std::vector<std::string> cpl = {exe_cpl};
      cpl.insert(cpl.end(), common.begin(), common.end());
      cpl.insert(cpl.end(), {"--user", std::to_string(u), "--device", std::to_string(u), "--coupler-rate-hz",
                             fmt_d(se.coupler_rate_hz), "--sleep", "--stiffness", fmt_d(se.stiffness), "--damping",
                             fmt_d(se.damping), "--position-scale", fmt_d(se.position_scale), "--force-scale",
                             fmt_d(se.force_scale), "--max-force-n", fmt_d(se.max_force_n), "--grab-body",
                             std::to_string(bodies[static_cast<size_t>(u)]), "--model-fingerprint",
                             fmt::format("{:016x}", fingerprint), "--stale-after-s", fmt_d(se.stale_after_s),
                             "--offset", fmt::format("{},{},{}", o.x(), o.y(), o.z()), "--max-device-position-m",
                             fmt_d(reaches[static_cast<size_t>(u)])});
      if (shm) cpl.push_back("--shm");
      const bool own_device =
          static_cast<size_t>(u) < se.user_devices.size() && !se.user_devices[static_cast<size_t>(u)].kind.empty();
      if (own_device) {   // the gains checked again against the limits the device reports
        cpl.insert(cpl.end(), {"--device-limits-wait-s", "10", "--device-model", se.device_model, "--sim-dt-s",
                               fmt_d(se.sim_dt_s)});
        if (se.clamp_gains) cpl.push_back("--clamp-gains");
        if (std::isfinite(se.device_damping_n_s_per_m))
          cpl.insert(cpl.end(), {"--device-damping-n-s-per-m", fmt_d(se.device_damping_n_s_per_m)});
      }
      const std::string cu = "coupler_" + std::to_string(u);
      children.push_back({cu, log_dir + "/" + cu + ".log"});
      children.back().pid = spawn(cpl, children.back().log);
    }
    const bool browser = se.viewer_port > 0;   // the page drives a browser device per user
    for (int u = 0; u < se.users; ++u) {
      std::vector<std::string> dev = {exe_dev};
      dev.insert(dev.end(), common.begin(), common.end());
      const bus::UserDevice* own =
          static_cast<size_t>(u) < se.user_devices.size() && !se.user_devices[static_cast<size_t>(u)].kind.empty()
              ? &se.user_devices[static_cast<size_t>(u)]
              : nullptr;
      if (own) {   // the user's own device instead of the script
        dev.insert(dev.end(), {"--device", std::to_string(u), "--device-kind", own->kind, "--device-rate-hz", "1000",
                               "--max-force-n", fmt_d(se.max_force_n)});
        for (const auto& kv : own->options) dev.insert(dev.end(), {"--device-option", kv});
        if (shm) dev.insert(dev.end(), {"--shm", "--mirror-rate-hz", fmt_d(se.mirror_rate_hz)});
        const std::string du = "device_bridge_" + std::to_string(u);
        children.push_back({du, log_dir + "/" + du + ".log"});
        children.back().pid = spawn(dev, children.back().log);
        continue;
      }
      if (browser)
        dev.insert(dev.end(), {"--device-option", u < se.scripted_users ? "fallback=scripted" : "fallback=none"});
      dev.insert(dev.end(), {"--device", std::to_string(u), "--device-kind", browser ? "browser" : "scripted", "--device-rate-hz", "1000",
                             "--max-force-n", fmt_d(se.max_force_n), "--device-option", "grab_m=0,0,0.01", "--device-option",
                             "pull_distance_m=" + fmt_d(se.pull_distance_m), "--device-option",
                             std::string("pull_direction=") + (u % 2 == 0 ? "1,0,0" : "0,1,0"), "--device-option",
                             "hold_s=" + fmt_d(se.duration_s > 0 ? std::max(0.5, se.duration_s - 3.0) : 1e9)});
      if (shm) dev.insert(dev.end(), {"--shm", "--mirror-rate-hz", fmt_d(se.mirror_rate_hz)});
      const std::string du = "device_bridge_" + std::to_string(u);
      children.push_back({du, log_dir + "/" + du + ".log"});
      children.back().pid = spawn(dev, children.back().log);
    }
    if (browser) {   // the viewer, beside the others on the same bus
      std::vector<std::string> vw = {find_executable("viewer", po.bin_dir, po.argv0)};
      vw.insert(vw.end(), common.begin(), common.end());
      vw.insert(vw.end(), {"--viewer-port", std::to_string(se.viewer_port), "--viewer-bind", se.viewer_bind, "--scene",
                           se.sim.scene, "--n", std::to_string(se.sim.n), "--viewer-users", std::to_string(se.users)});
      if (!se.sim.urdf.empty()) vw.insert(vw.end(), {"--urdf", se.sim.urdf});
      for (const auto& d : se.viewer_mesh_paths) vw.insert(vw.end(), {"--mesh-path", d});
      // The token goes to the viewer in a file (a command line is visible to every user in ps).
      std::string token, token_file = se.viewer_token_file;
      if (se.viewer_no_token) {
        vw.push_back("--viewer-no-token");
      } else {
        if (token_file.empty()) {
          token = random_viewer_token();
          token_file = log_dir + "/viewer.token";
          const int fd = ::open(token_file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
          if (fd < 0 || ::write(fd, (token + "\n").data(), token.size() + 1) != static_cast<ssize_t>(token.size() + 1))
            throw std::runtime_error("cannot write " + token_file);
          ::close(fd);
        } else {
          token = read_viewer_token_file(token_file);
        }
        vw.insert(vw.end(), {"--viewer-token-file", token_file});
      }
      if (!se.viewer_watch_token_file.empty()) vw.insert(vw.end(), {"--viewer-watch-token-file", se.viewer_watch_token_file});
      if (!se.viewer_tls_cert.empty()) vw.insert(vw.end(), {"--viewer-tls-cert", se.viewer_tls_cert, "--viewer-tls-key", se.viewer_tls_key});
      children.push_back({"viewer", log_dir + "/viewer.log"});
      children.back().pid = spawn(vw, children.back().log);
      std::fprintf(se.json ? stderr : stdout, "viewer: open %s://%s:%d/%s\n", se.viewer_tls_cert.empty() ? "http" : "https",
                   se.viewer_bind.c_str(), se.viewer_port, token.empty() ? "" : ("?token=" + token).c_str());
      std::fflush(se.json ? stderr : stdout);
    }
    spdlog::info("haptree_run --processes: scene {} ({} bodies, {} DOF), {} user(s) pulling bodies {}, {:.0f} s; "
                 "bus {} ({}), logs in {}",
                 se.sim.scene, nbodies, nv, se.users, fmt::join(bodies, ","), se.duration_s, url,
                 shm ? "device link over shared memory, the rest via the launcher's 127.0.0.1 hub" : "udpm ttl=0",
                 log_dir);
    for (const auto& c : children) spdlog::info("  {} pid {}", c.name, c.pid);

    const auto t0 = Clock::now();
    auto next_line = t0 + std::chrono::seconds(1);
    double max_rate = 0, sum_step_ms = 0;
    int lines = 0;
    const Child* failed = nullptr;
    lcmt_feedback fb{};
    while (!stop.load() && !failed) {
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
      for (size_t u = 0; u < fb_readers.size(); ++u)
        if (fb_readers[u]->read_msg(fb) == bus::ShmRead::kNew) {
          std::lock_guard<std::mutex> l(tally_m);
          tally[u].add(fb);
        }
      for (auto& c : children)
        if (!c.reaped && ::waitpid(c.pid, &c.status, WNOHANG) == c.pid) {
          c.reaped = true;
          if (!failed) failed = &c;
        }
      if (failed || Clock::now() < next_line) continue;
      next_line += std::chrono::seconds(1);
      const double t = std::chrono::duration<double>(Clock::now() - t0).count();
      haptree::launcher::StatusSample st;
      st.t_s = t;
      {
        std::lock_guard<std::mutex> l(stats.m);
        const double step_ms = stats.have_sim ? stats.sim.latency_p50_us * 1e-3 : 0.0;
        if (stats.have_sim) {
          // real-time factor: simulated time per second (s/s; ps/s for molecules), and the share of --sim-rate-hz kept
          st.sim.started = true;
          st.sim.step_ms = step_ms;
          st.sim.max_step_ms = extra_value(stats.sim, "max_step_ms");
          st.sim.active_dofs = stats.sim.n_extra > 0 ? static_cast<int>(stats.sim.extra_values[0]) : -1;
          st.sim.steps_per_s = stats.sim.loop_rate_hz;
          st.sim.real_time_factor = extra_value(stats.sim, "real_time_factor");
          st.sim.rate_fraction = extra_value(stats.sim, "rate_fraction");
          sum_step_ms += step_ms;
          ++lines;
        }
        for (int u = 0; u < se.users; ++u) {
          const auto& k = stats.couplers[static_cast<size_t>(u)];
          haptree::launcher::UserStatus us;
          us.user = u;
          us.started = stats.have_coupler[static_cast<size_t>(u)];
          {
            std::lock_guard<std::mutex> l2(tally_m);
            us.feedbacks = tally[static_cast<size_t>(u)].count;
          }
          if (us.started) {   // the coupler's stats of its last 1-s window
            max_rate = std::max(max_rate, k.loop_rate_hz);
            us.rate_hz = k.loop_rate_hz;
            us.force_n = extra_value(k, "force_n");
            us.grab_body = static_cast<int>(extra_value(k, "grab_body"));
            us.snapshot_age_ms = k.snapshot_age_ms;
          }
          st.users.push_back(us);
        }
      }
      const std::string line = se.json ? status_json(st) : status_text(st);
      std::printf("%s\n", line.c_str());
      std::fflush(stdout);
      if (se.duration_s > 0 && t >= se.duration_s) break;
    }
    FILE* out = se.json ? stderr : stdout;   // --json: stdout carries only the status objects
    if (stop.load() && !failed) std::fprintf(out, "haptree_run: interrupted, stopping the children\n");
    if (failed) {
      const double t = std::chrono::duration<double>(Clock::now() - t0).count();
      std::fprintf(stderr, "haptree_run: child %s (pid %d) stopped on its own after %.1f s: %s. Last lines of %s:\n",
                   failed->name.c_str(), failed->pid, t, describe_status(failed->status).c_str(), failed->log.c_str());
      for (const auto& l : tail_lines(failed->log, 8)) std::fprintf(stderr, "  | %s\n", l.c_str());
      std::fprintf(stderr, "haptree_run: stopping the other children\n");
    }
    terminate_all(5.0);
    fb_readers.clear();
    remove_segments();
    handler.stop();
    bus_owner.reset();
    if (hub) hub->stop();

    // Summary: the children's own final lines + what the launcher saw on the bus / shared memory.
    long long steps = 0, snaps = 0;
    const std::string sl = find_line(children[0].log, "sim_server: ");
    if (!sl.empty()) std::sscanf(sl.c_str() + sl.find("sim_server: "), "sim_server: %lld steps, %lld snapshots", &steps, &snaps);
    std::fprintf(out, "summary: %lld sim steps (%lld snapshots), mean sampled step %.3f ms\n", steps, snaps,
                lines ? sum_step_ms / lines : 0.0);
    for (int u = 0; u < se.users; ++u) {
      long long it = 0, acc = 0, rej = 0, readings = 0, feedbacks = 0;
      double fmax = 0, p50 = 0, p99 = 0;
      const std::string cl = find_line(log_dir + "/coupler_" + std::to_string(u) + ".log", "coupler: ");
      if (!cl.empty())
        std::sscanf(cl.c_str() + cl.find("coupler: "), "coupler: %lld iterations, %lld snapshots, %lld rejected", &it,
                    &acc, &rej);
      const std::string dl = find_line(log_dir + "/device_bridge_" + std::to_string(u) + ".log", "device_bridge: ");
      if (!dl.empty())
        std::sscanf(dl.c_str() + dl.find("device_bridge: "),
                    "device_bridge: %lld readings, %lld feedbacks, max |f| %lf N, pose-to-force latency p50 %lf us "
                    "p99 %lf us",
                    &readings, &feedbacks, &fmax, &p50, &p99);
      const auto& t = tally[static_cast<size_t>(u)];
      std::fprintf(out, "  user %d: body %d, %lld coupler iterations, %lld snapshots accepted, %lld rejected, "
                  "max |f| at device %.3f N, device pose-to-force latency p50 %.1f us p99 %.1f us, "
                  "%lld feedbacks applied by the device\n",
                  u, bodies[static_cast<size_t>(u)], it, acc, rej, fmax, p50, p99, feedbacks);
      std::fprintf(out, "  user %d: launcher saw %lld feedback messages (%lld non-finite)\n", u,
                  static_cast<long long>(t.count), static_cast<long long>(t.nonfinite));
    }
    std::fprintf(out, "  peak coupler rate %.0f Hz (1-s windows)\n", max_rate);
    if (hub)
      std::fprintf(out, "  hub 127.0.0.1:%d: %lld messages in, %lld out, %lld dropped\n", hub->port(),
                  static_cast<long long>(hub->messages_in()), static_cast<long long>(hub->messages_out()),
                  static_cast<long long>(hub->messages_dropped()));
    std::string exits;
    int bad = 0;
    for (const auto& c : children) {
      exits += fmt::format(" {} {}", c.name, c.reaped ? describe_status(c.status) : "not reaped");
      if (!clean_exit(c)) ++bad;
    }
    std::fprintf(out, "  children:%s; logs in %s\n", exits.c_str(), log_dir.c_str());
    std::fflush(out);
    if (failed || bad) {
      std::fprintf(stderr, "haptree_run: %d child process(es) failed (see above and the logs in %s)\n",
                   failed && bad == 0 ? 1 : bad, log_dir.c_str());
      return 1;
    }
    return 0;
  } catch (const std::exception& e) {
    terminate_all(2.0);
    remove_segments();
    spdlog::critical("haptree_run --processes: {}", e.what());
    return 1;
  }
}

}  // namespace haptree::launcher
