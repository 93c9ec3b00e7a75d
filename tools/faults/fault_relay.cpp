// fault_relay: a fault-injecting datagram relay between two UDP multicast groups (a test tool).
// The "server" side publishes LCM udpm on group A, the "workstation" side on group B; the relay forwards
// every datagram A -> B and B -> A and, during scheduled phases, delays, jitters, reorders, duplicates,
// drops or blacks out the datagrams. Used by docs/network_faults.md and scripts/network_faults.sh (ctest integration_network_faults)
// where this machine's kernel has no sch_netem. Run it only inside a network namespace (ttl 1 by default).
//
// One thread, poll() on the two receive sockets, a min-heap of datagrams due for sending. Its own
// datagrams come back to it (multicast loopback); they are recognised by their source port and dropped,
// so A -> B -> A loops cannot form. The run time is bounded (--duration), so a test cannot leave it behind.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <time.h>
#include <signal.h>
#include <sys/socket.h>
#include <unistd.h>

#include <CLI/CLI.hpp>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <queue>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

namespace {

struct Endpoint {
  in_addr group{};
  uint16_t port = 0;
};

Endpoint parse_endpoint(const std::string& s) {
  const auto colon = s.rfind(':');
  Endpoint e;
  if (colon == std::string::npos || ::inet_pton(AF_INET, s.substr(0, colon).c_str(), &e.group) != 1)
    throw std::invalid_argument("'" + s + "': expected GROUP:PORT, e.g. 239.255.76.67:7667");
  const long p = std::strtol(s.c_str() + colon + 1, nullptr, 10);
  if (p <= 0 || p > 65535) throw std::invalid_argument("'" + s + "': port must be 1..65535");
  if ((ntohl(e.group.s_addr) >> 28) != 14) throw std::invalid_argument("'" + s + "': not a multicast group (224.0.0.0/4)");
  e.port = static_cast<uint16_t>(p);
  return e;
}

// Faults of one phase. Probabilities in [0, 1], times in seconds.
struct Faults {
  double delay_s = 0, jitter_s = 0;   // each datagram: delay + uniform(-jitter, +jitter), at least 0
  double reorder = 0;                 // share held back by reorder_hold_s so that later ones overtake it
  double reorder_hold_s = 0.003;
  double dup = 0;                     // share sent twice
  double drop = 0;                    // share dropped (loss is measured with nftables; this is for the relay alone)
  bool blackout = false;              // nothing passes
};

struct Phase {
  double duration_s = 0;
  std::string spec;
  Faults f;
};

double number(const std::string& key, const std::string& v, double lo, double hi) {
  char* end = nullptr;
  const double x = std::strtod(v.c_str(), &end);
  if (v.empty() || *end != '\0' || !std::isfinite(x) || x < lo || x > hi) {
    std::ostringstream os;
    os << "'" << key << "=" << v << "': expected a number in [" << lo << ", " << hi << "]";
    throw std::invalid_argument(os.str());
  }
  return x;
}

// "SECONDS:SPEC", SPEC = none | comma list of delay=MS jitter=MS reorder=PCT hold=MS dup=PCT drop=PCT blackout
Phase parse_phase(const std::string& s) {
  const auto colon = s.find(':');
  if (colon == std::string::npos) throw std::invalid_argument("--phase '" + s + "': expected SECONDS:SPEC");
  Phase p;
  p.duration_s = number("seconds", s.substr(0, colon), 0.001, 3600);
  p.spec = s.substr(colon + 1);
  std::stringstream ss(p.spec);
  for (std::string item; std::getline(ss, item, ',');) {
    const auto eq = item.find('=');
    const std::string k = item.substr(0, eq), v = eq == std::string::npos ? "" : item.substr(eq + 1);
    if (k == "none" && eq == std::string::npos) continue;
    if (k == "blackout" && eq == std::string::npos) { p.f.blackout = true; continue; }
    if (eq == std::string::npos) throw std::invalid_argument("--phase '" + s + "': unknown fault '" + item + "'");
    if (k == "delay") p.f.delay_s = number(k, v, 0, 10000) * 1e-3;
    else if (k == "jitter") p.f.jitter_s = number(k, v, 0, 10000) * 1e-3;
    else if (k == "reorder") p.f.reorder = number(k, v, 0, 100) / 100;
    else if (k == "hold") p.f.reorder_hold_s = number(k, v, 0, 10000) * 1e-3;
    else if (k == "dup") p.f.dup = number(k, v, 0, 100) / 100;
    else if (k == "drop") p.f.drop = number(k, v, 0, 100) / 100;
    else throw std::invalid_argument("--phase '" + s + "': unknown fault '" + k + "'");
  }
  return p;
}

int recv_socket(const Endpoint& e) {
  const int fd = ::socket(AF_INET, SOCK_DGRAM, 0);
  if (fd < 0) throw std::runtime_error(std::string("socket: ") + std::strerror(errno));
  const int one = 1;
  ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);   // shares the port with LCM's sockets
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(e.port);
  a.sin_addr.s_addr = htonl(INADDR_ANY);
  if (::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0)
    throw std::runtime_error("bind port " + std::to_string(e.port) + ": " + std::strerror(errno));
  ip_mreq m{};
  m.imr_multiaddr = e.group;
  m.imr_interface.s_addr = htonl(INADDR_ANY);
  if (::setsockopt(fd, IPPROTO_IP, IP_ADD_MEMBERSHIP, &m, sizeof m) != 0)
    throw std::runtime_error(std::string("IP_ADD_MEMBERSHIP (is there a multicast route?): ") + std::strerror(errno));
  const int rcvbuf = 4 << 20;
  ::setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
  return fd;
}

int send_socket(int ttl, uint16_t* port) {
  const int fd = ::socket(AF_INET, SOCK_DGRAM, 0);
  if (fd < 0) throw std::runtime_error(std::string("socket: ") + std::strerror(errno));
  const unsigned char t = static_cast<unsigned char>(ttl), loop = 1;
  ::setsockopt(fd, IPPROTO_IP, IP_MULTICAST_TTL, &t, sizeof t);
  ::setsockopt(fd, IPPROTO_IP, IP_MULTICAST_LOOP, &loop, sizeof loop);   // receivers on this host too
  sockaddr_in a{};
  a.sin_family = AF_INET;
  if (::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0)
    throw std::runtime_error(std::string("bind: ") + std::strerror(errno));
  socklen_t n = sizeof a;
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &n);
  *port = ntohs(a.sin_port);
  return fd;
}

using Clock = std::chrono::steady_clock;

struct Pending {
  double due_s;
  uint64_t order;   // FIFO among equal due times
  int dir;          // 0: A -> B, 1: B -> A
  std::vector<uint8_t> bytes;
  bool operator>(const Pending& o) const { return due_s != o.due_s ? due_s > o.due_s : order > o.order; }
};

std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop.store(true); }

int64_t wall_utime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "fault_relay: forwards UDP multicast datagrams between group A and group B (both ways) and injects "
      "delay, jitter, reordering, duplication, loss and blackouts in scheduled phases. A test tool: run it "
      "inside a network namespace (docs/network_faults.md)."};
  std::string a_str = "239.255.76.67:7667", b_str = "239.255.76.68:7668";
  std::vector<std::string> phase_str;
  double duration_s = 60;
  int ttl = 1;
  uint64_t seed = 1;
  app.add_option("--a", a_str, "side A, GROUP:PORT (e.g. the server's udpm URL)")->capture_default_str();
  app.add_option("--b", b_str, "side B, GROUP:PORT (e.g. the workstation's udpm URL)")->capture_default_str();
  app.add_option("--phase", phase_str,
                 "SECONDS:SPEC, repeatable, run in order from the start; SPEC = none, or a comma list of "
                 "delay=MS jitter=MS (uniform +-) reorder=PCT hold=MS (reordered ones held back, default 3) "
                 "dup=PCT drop=PCT blackout. After the last phase datagrams pass unchanged.");
  app.add_option("--duration", duration_s, "exit after this many seconds (bounds a test's run)")
      ->check(CLI::Range(0.01, 86400.0))->capture_default_str();
  app.add_option("--ttl", ttl, "multicast TTL of forwarded datagrams")->check(CLI::Range(0, 255))->capture_default_str();
  app.add_option("--seed", seed, "random seed (faults are reproducible per seed)")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  try {
    const Endpoint ep[2] = {parse_endpoint(a_str), parse_endpoint(b_str)};
    if (ep[0].port == ep[1].port)
      throw std::invalid_argument("--a and --b need different ports (a socket receives a port's datagrams of every group)");
    std::vector<Phase> phases;
    for (const auto& s : phase_str) phases.push_back(parse_phase(s));
    const int rx[2] = {recv_socket(ep[0]), recv_socket(ep[1])};
    uint16_t own_port[2];
    const int tx[2] = {send_socket(ttl, &own_port[0]), send_socket(ttl, &own_port[1])};   // tx[d]: towards side 1-d
    ::signal(SIGTERM, on_signal);
    ::signal(SIGINT, on_signal);

    const Clock::time_point t0 = Clock::now();
    const int64_t u0 = wall_utime();
    auto now_s = [&] { return std::chrono::duration<double>(Clock::now() - t0).count(); };
    // The schedule in wall-clock microseconds (the clock of LCM's utime and lcm-logger), for the analysis.
    double start = 0;
    for (size_t i = 0; i < phases.size(); ++i) {
      std::printf("fault_relay: phase %zu '%s' %lld %lld\n", i, phases[i].spec.c_str(),
                  static_cast<long long>(u0 + std::llround(start * 1e6)),
                  static_cast<long long>(u0 + std::llround((start + phases[i].duration_s) * 1e6)));
      start += phases[i].duration_s;
    }
    std::fflush(stdout);

    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> u01(0, 1);
    std::priority_queue<Pending, std::vector<Pending>, std::greater<>> due;
    constexpr size_t kMaxPending = 100000;   // bounds memory if a phase delays far more than arrives
    uint64_t order = 0;
    int64_t in[2] = {0, 0}, out[2] = {0, 0}, dropped[2] = {0, 0}, dups[2] = {0, 0}, held[2] = {0, 0};
    std::vector<uint8_t> buf(65536);
    pollfd pf[2] = {{rx[0], POLLIN, 0}, {rx[1], POLLIN, 0}};
    while (!g_stop.load() && now_s() < duration_s) {
      double t = now_s();
      while (!due.empty() && due.top().due_s <= t) {
        const Pending& p = due.top();
        sockaddr_in to{};
        to.sin_family = AF_INET;
        to.sin_addr = ep[1 - p.dir].group;
        to.sin_port = htons(ep[1 - p.dir].port);
        if (::sendto(tx[p.dir], p.bytes.data(), p.bytes.size(), 0, reinterpret_cast<sockaddr*>(&to), sizeof to) >= 0)
          ++out[p.dir];
        due.pop();
      }
      double wait_s = 0.05;
      if (!due.empty()) wait_s = std::clamp(due.top().due_s - t, 0.0, 0.05);
      const timespec ts{0, static_cast<long>(wait_s * 1e9)};   // ppoll: microsecond-scale delays need ns timeouts
      const int n = ::ppoll(pf, 2, &ts, nullptr);
      if (n < 0 && errno != EINTR) throw std::runtime_error(std::string("poll: ") + std::strerror(errno));
      t = now_s();
      const Phase* ph = nullptr;
      double acc = 0;
      for (const auto& p : phases) {
        if (t < acc + p.duration_s) { ph = &p; break; }
        acc += p.duration_s;
      }
      const Faults f = ph ? ph->f : Faults{};
      for (int d = 0; d < 2 && n > 0; ++d) {
        if (!(pf[d].revents & POLLIN)) continue;
        for (;;) {
          sockaddr_in from{};
          socklen_t fl = sizeof from;
          const ssize_t len = ::recvfrom(rx[d], buf.data(), buf.size(), MSG_DONTWAIT, reinterpret_cast<sockaddr*>(&from), &fl);
          if (len < 0) break;
          const uint16_t sport = ntohs(from.sin_port);
          if (sport == own_port[0] || sport == own_port[1]) continue;   // our own forwarded datagram
          ++in[d];
          if (f.blackout || u01(rng) < f.drop || due.size() >= kMaxPending) {
            ++dropped[d];
            continue;
          }
          double delay = f.delay_s + (f.jitter_s > 0 ? (2 * u01(rng) - 1) * f.jitter_s : 0);
          if (u01(rng) < f.reorder) {
            delay += f.reorder_hold_s;
            ++held[d];
          }
          const int copies = u01(rng) < f.dup ? 2 : 1;
          dups[d] += copies - 1;
          for (int c = 0; c < copies; ++c)
            due.push(Pending{t + std::max(0.0, delay), order++, d, std::vector<uint8_t>(buf.begin(), buf.begin() + len)});
        }
      }
    }
    std::printf("fault_relay: A->B %lld in, %lld out, %lld dropped, %lld duplicated, %lld held back; "
                "B->A %lld in, %lld out, %lld dropped, %lld duplicated, %lld held back\n",
                static_cast<long long>(in[0]), static_cast<long long>(out[0]), static_cast<long long>(dropped[0]),
                static_cast<long long>(dups[0]), static_cast<long long>(held[0]), static_cast<long long>(in[1]),
                static_cast<long long>(out[1]), static_cast<long long>(dropped[1]), static_cast<long long>(dups[1]),
                static_cast<long long>(held[1]));
    for (int d = 0; d < 2; ++d) {
      ::close(rx[d]);
      ::close(tx[d]);
    }
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fault_relay: %s\n", e.what());
    return 2;
  }
}
