// "Server host" and "workstation host" on one machine: two private network namespaces joined by a veth pair,
// each with its multicast route, and one session file that every process of both hosts reads
// (examples/sessions/two_hosts.toml, the recipe of docs/processes.md, "Two hosts"): sim_server + viewer on
// the server; a coupler and a device_bridge for each of two users on the workstation; LCM udpm ttl=1,
// keyed. Checked: both users' forces are fed back, the scene state arrives on the workstation, the viewer
// answers the workstation, a stranger on the segment without the key is refused, killing the server ramps
// both devices to zero and a restarted server is taken back. Nothing leaves the machine: the namespaces,
// the veth pair and the 10.213.0.0/24 addresses exist only inside this test and are deleted at the end,
// even on failure. Needs root (ip netns); without it the test fails with a clear message (no skip).
#include <gtest/gtest.h>
#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <sched.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <mutex>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "haptree/bus/auth.hpp"
#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "haptree/lcmt_process_stats.hpp"
#include "haptree/lcmt_scene_state.hpp"
#include "haptree/lcmt_user_force.hpp"
#include "tests/integration/spawn.hpp"

namespace haptree {
namespace {

using Clock = std::chrono::steady_clock;
const std::string kSession = HAPTREE_SOURCE_DIR "/examples/sessions/two_hosts.toml";
constexpr const char* kUrl = "udpm://239.255.76.67:7667?ttl=1";   // the file's lcm-url
constexpr const char* kServerAddress = "10.213.0.1";               // the file's viewer-bind
constexpr int kViewerPort = 8080;                                  // the file's viewer-port
constexpr double kMaxForceN = 3.0;                                 // the file's max-force-n

int sh(const std::string& cmd) { return std::system((cmd + " >/dev/null 2>&1").c_str()); }

// Creates the server and workstation namespaces + veth pair, deletes them in the destructor (also on failure).
struct TwoNamespaces {
  std::string a, b, va, vb, error;
  TwoNamespaces() {
    const std::string id = std::to_string(::getpid());
    a = "htA" + id;
    b = "htB" + id;
    va = "htva" + id;
    vb = "htvb" + id;
    // Per host, as docs/processes.md says: the address, the link up with multicast, the multicast route.
    const std::vector<std::string> cmds = {
        "ip netns add " + a,
        "ip netns add " + b,
        "ip link add " + va + " type veth peer name " + vb,
        "ip link set " + va + " netns " + a,
        "ip link set " + vb + " netns " + b,
        "ip netns exec " + a + " ip addr add 10.213.0.1/24 dev " + va,
        "ip netns exec " + b + " ip addr add 10.213.0.2/24 dev " + vb,
        "ip netns exec " + a + " ip link set lo up",
        "ip netns exec " + b + " ip link set lo up",
        "ip netns exec " + a + " ip link set " + va + " up multicast on",
        "ip netns exec " + b + " ip link set " + vb + " up multicast on",
        "ip netns exec " + a + " ip route add 224.0.0.0/4 dev " + va,
        "ip netns exec " + b + " ip route add 224.0.0.0/4 dev " + vb,
    };
    if (::geteuid() != 0) {
      error = "not root: this test creates two network namespaces and a veth pair (ip netns add) and needs root "
              "(CI runs it as root); exclude it with `ctest -LE netns`.";
      return;
    }
    for (const auto& c : cmds) {
      if (sh(c) != 0) {
        error = "network namespace set-up failed at `" + c + "` (needs root and iproute2; exclude with `ctest -LE netns`)";
        return;
      }
    }
  }
  ~TwoNamespaces() {
    sh("ip netns delete " + a);  // deleting a namespace destroys its veth end and so the pair
    sh("ip netns delete " + b);
    sh("ip link delete " + va);  // in case the pair was never moved
  }
};

pid_t spawn_in(const std::string& ns, std::vector<std::string> args, const std::string& log) {
  args.insert(args.begin(), {"ip", "netns", "exec", ns});  // ip execs the program: the pid is the program's
  return testing::spawn_logged(args, log, /*search_path=*/true);
}

std::string slurp(const std::string& path) {
  std::ifstream f(path);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

double now_s() { return std::chrono::duration<double>(Clock::now().time_since_epoch()).count(); }

// HTTP GET `path` on addr:port; the status line, or why not.
std::string http_status(const char* addr, int port, const std::string& path) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in sa{};
  sa.sin_family = AF_INET;
  sa.sin_port = htons(static_cast<uint16_t>(port));
  ::inet_pton(AF_INET, addr, &sa.sin_addr);
  timeval tv{2, 0};
  ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&sa), sizeof sa) != 0) {
    ::close(fd);
    return "connect failed";
  }
  const std::string req = "GET " + path + " HTTP/1.0\r\nHost: " + std::string(addr) + "\r\n\r\n";
  (void)!::write(fd, req.data(), req.size());
  char buf[256] = {0};
  const ssize_t n = ::read(fd, buf, sizeof buf - 1);
  ::close(fd);
  if (n <= 0) return "no answer";
  std::string s(buf, static_cast<size_t>(n));
  return s.substr(0, s.find('\r'));
}

// What the workstation-side probe saw: a keyed listener and an unkeyed stranger in the workstation's
// namespace, forked from the test (setns), for `seconds`. Written to `out` as lines:
//   F <user> <steady time s> <|f| N>      every FEEDBACK of users 0 and 1
//   S <count>                             scene-state messages
//   R <max rejected of sim_server's stats>
//   H <viewer's HTTP status line with the token>
//   N <viewer's HTTP status line without it>
pid_t start_probe(const std::string& ns, const std::string& key_file, const std::string& token, double seconds,
                  const std::string& out) {
  std::fflush(nullptr);
  const pid_t pid = ::fork();
  if (pid != 0) return pid;
  std::FILE* f = std::fopen(out.c_str(), "w");
  const int nsfd = ::open(("/var/run/netns/" + ns).c_str(), O_RDONLY | O_CLOEXEC);
  if (!f || nsfd < 0 || ::setns(nsfd, CLONE_NEWNET) != 0) ::_exit(3);
  try {
    bus::set_process_session_key_file(key_file);
    bus::Bus keyed(kUrl);
    bus::Bus stranger(kUrl, nullptr);   // on the segment, without the key
    std::mutex m;
    std::vector<std::string> lines;
    std::atomic<int64_t> scene{0}, rejected{0};
    for (int u = 0; u < 2; ++u)
      keyed.subscribe<lcmt_feedback>(bus::channel::feedback(u), [&, u](const lcmt_feedback& fb, const std::string&) {
        const double x = std::sqrt(fb.force_n[0] * fb.force_n[0] + fb.force_n[1] * fb.force_n[1] +
                                   fb.force_n[2] * fb.force_n[2]);
        char line[96];
        std::snprintf(line, sizeof line, "F %d %.6f %.6g", u, now_s(), x);
        std::lock_guard<std::mutex> l(m);
        lines.emplace_back(line);
      });
    keyed.subscribe<lcmt_scene_state>(bus::channel::scene_state(),
                                      [&](const lcmt_scene_state&, const std::string&) { ++scene; });
    keyed.subscribe<lcmt_process_stats>(bus::channel::stats("sim_server"),
                                        [&](const lcmt_process_stats& s, const std::string&) {
                                          rejected = std::max<int64_t>(rejected.load(), s.rejected_messages);
                                        });
    bus::HandlerThread handler(keyed, 5);
    lcmt_user_force uf{};
    bus::stamp(uf, 0x5eed);
    uf.active = true;
    uf.user_id = 0;
    uf.grab_body = 1;
    uf.force[5] = 1000;   // a big pull on user 0's body, if it were taken
    std::string http, http_no_token;
    const auto t0 = Clock::now();
    while (Clock::now() - t0 < std::chrono::duration<double>(seconds)) {
      uf.utime = std::chrono::duration_cast<std::chrono::microseconds>(
                     std::chrono::system_clock::now().time_since_epoch()).count();
      ++uf.seq;
      stranger.publish(bus::channel::user_force(0), uf);
      if (http.empty() && Clock::now() - t0 > std::chrono::milliseconds(1500)) {
        http = http_status(kServerAddress, kViewerPort, "/?token=" + token);
        http_no_token = http_status(kServerAddress, kViewerPort, "/");
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    handler.stop();
    std::lock_guard<std::mutex> l(m);
    for (const auto& s : lines) std::fprintf(f, "%s\n", s.c_str());
    std::fprintf(f, "S %lld\nR %lld\nH %s\nN %s\n", static_cast<long long>(scene.load()),
                 static_cast<long long>(rejected.load()), http.c_str(), http_no_token.c_str());
    std::fclose(f);
    ::_exit(0);
  } catch (const std::exception& e) {
    std::fprintf(f, "E %s\n", e.what());
    std::fclose(f);
    ::_exit(4);
  }
}

struct Feedback {
  int user;
  double t, f;
};

double max_force(const std::vector<Feedback>& fb, int user, double t0, double t1, int* count = nullptr) {
  double m = 0;
  int n = 0;
  for (const auto& x : fb)
    if (x.user == user && x.t >= t0 && x.t < t1) {
      m = std::max(m, std::isfinite(x.f) ? x.f : 1e300);
      ++n;
    }
  if (count) *count = n;
  return m;
}

TEST(TwoHosts, ServerAndWorkstationNamespacesOverVethUdpm) {
  TwoNamespaces ns;
  ASSERT_TRUE(ns.error.empty()) << ns.error;
  const std::string dir = ::testing::TempDir() + "two_hosts/";
  ::mkdir(dir.c_str(), 0755);
  // The session key: 32 random bytes, readable by the owner only (the file names /etc/haptree/session.key;
  // the test's own key file overrides it on the command line).
  const std::string key = dir + "session.key";
  ASSERT_EQ(sh("head -c 32 /dev/urandom > " + key + " && chmod 600 " + key), 0);
  // The viewer's pull token (the file names /etc/haptree/viewer.token; overridden like the key).
  const std::string token = "two-hosts-test-token-0123456789";
  const std::string token_file = dir + "viewer.token";
  std::ofstream(token_file) << token << "\n";
  auto with = [&](std::vector<std::string> a) {
    a.insert(a.begin() + 1, {"--config", kSession, "--session-key-file", key});
    return a;
  };
  const double t_begin = now_s();
  const pid_t probe = start_probe(ns.b, key, token, 11.0, dir + "probe.txt");
  ASSERT_GT(probe, 0);
  pid_t sim = spawn_in(ns.a, with({HAPTREE_SIM_SERVER}), dir + "sim_server.log");
  const pid_t viewer = spawn_in(ns.a, with({HAPTREE_VIEWER, "--viewer-token-file", token_file}), dir + "viewer.log");
  std::vector<pid_t> ws;   // workstation: bridges, then couplers
  for (int u = 0; u < 2; ++u)
    ws.push_back(spawn_in(ns.b, with({HAPTREE_DEVICE_BRIDGE, "--device", std::to_string(u)}),
                          dir + "device_bridge_" + std::to_string(u) + ".log"));
  for (int u = 0; u < 2; ++u)
    ws.push_back(spawn_in(ns.b, with({HAPTREE_COUPLER, "--user", std::to_string(u)}),
                          dir + "coupler_" + std::to_string(u) + ".log"));
  // The scripted pulls are complete 1.4 s after the start (approach 0.2 s, settle 0.2 s, pull 1 s).
  std::this_thread::sleep_for(std::chrono::milliseconds(4000));
  const double t_kill = now_s();
  ::kill(sim, SIGKILL);
  testing::reap(sim);
  std::this_thread::sleep_for(std::chrono::milliseconds(1500));
  const double t_restart = now_s();
  sim = spawn_in(ns.a, with({HAPTREE_SIM_SERVER}), dir + "sim_server_restarted.log");
  std::this_thread::sleep_for(std::chrono::milliseconds(4000));
  const double t_end = now_s();
  std::string exits;
  int bad_exit = 0;
  for (pid_t p : {ws[0], ws[1], ws[2], ws[3], viewer, sim}) {
    const int rc = p > 0 ? testing::stop_and_reap(p) : -1;
    exits += " " + std::to_string(rc);
    if (rc != 0) ++bad_exit;
  }
  ASSERT_EQ(testing::reap(probe), 0) << slurp(dir + "probe.txt");

  std::vector<Feedback> fb;
  long long scene = -1, rejected = -1;
  std::string http, http_no_token;
  {
    std::ifstream in(dir + "probe.txt");
    std::string line;
    while (std::getline(in, line)) {
      Feedback x{};
      if (std::sscanf(line.c_str(), "F %d %lf %lf", &x.user, &x.t, &x.f) == 3) fb.push_back(x);
      else if (line.rfind("S ", 0) == 0) scene = std::atoll(line.c_str() + 2);
      else if (line.rfind("R ", 0) == 0) rejected = std::atoll(line.c_str() + 2);
      else if (line.rfind("H ", 0) == 0) http = line.substr(2);
      else if (line.rfind("N ", 0) == 0) http_no_token = line.substr(2);
    }
  }
  EXPECT_EQ(bad_exit, 0) << "exit codes (bridges, couplers, viewer, restarted server):" << exits;
  // Before the kill: both users pulled, clamped. After: zero within the coupler's 50 ms stale time and
  // the 5 ms ramp (0.3 s margin for the udpm path and the process exit). After the restart: pulled again.
  for (int u = 0; u < 2; ++u) {
    int n_before = 0, n_dead = 0, n_after = 0;
    const double before = max_force(fb, u, t_kill - 1.5, t_kill, &n_before);
    const double dead = max_force(fb, u, t_kill + 0.3, t_restart, &n_dead);
    const double after = max_force(fb, u, t_restart + 2.0, t_end, &n_after);
    std::printf("user %d: max |f| %.3f N before the kill (%d feedbacks), %.3g N while the server is dead (%d), "
                "%.3f N after the restart (%d)\n", u, before, n_before, dead, n_dead, after, n_after);
    EXPECT_GT(n_before, 100) << "user " << u;
    EXPECT_GT(before, 0.05) << "user " << u;
    EXPECT_LE(before, kMaxForceN + 1e-9) << "user " << u;
    EXPECT_GT(n_dead, 10) << "user " << u << ": the coupler must keep feeding back (zero) while the server is gone";
    EXPECT_EQ(dead, 0.0) << "user " << u;
    EXPECT_GT(n_after, 100) << "user " << u;
    EXPECT_GT(after, 0.05) << "user " << u << ": the restarted server was not taken back";
    EXPECT_LE(after, kMaxForceN + 1e-9) << "user " << u;
    const std::string log = slurp(dir + "coupler_" + std::to_string(u) + ".log");
    std::smatch m;
    long long restarts = -1;
    if (std::regex_search(log, m, std::regex(R"((\d+) restarts)"))) restarts = std::stoll(m[1]);
    EXPECT_GE(restarts, 1) << log;
  }
  std::printf("scene-state messages on the workstation: %lld; viewer from the workstation: %s (without the "
              "token: %s); sim_server refused %lld messages (the stranger's); session %.1f s\n", scene, http.c_str(),
              http_no_token.c_str(), rejected,
              t_end - t_begin);
  EXPECT_GT(scene, 50);   // 30 Hz for ~8 s of live server
  EXPECT_NE(http.find(" 200"), std::string::npos) << http << "\n" << slurp(dir + "viewer.log");
  EXPECT_NE(http_no_token.find(" 403"), std::string::npos) << "without the token: " << http_no_token;
  EXPECT_GT(rejected, 10) << "the stranger's unkeyed USER_FORCE must be refused and counted";
}

}  // namespace
}  // namespace haptree
