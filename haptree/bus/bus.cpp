#include "haptree/bus/bus.hpp"
#include "haptree/bus/delivery.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <cstdlib>
#include <sstream>

namespace haptree::bus {

const char* to_string(DecodeResult r) noexcept {
  switch (r) {
    case DecodeResult::kOk: return "ok";
    case DecodeResult::kTooShort: return "too short";
    case DecodeResult::kWrongType: return "type fingerprint differs (another type or another schema layout)";
    case DecodeResult::kMalformed: return "malformed";
    case DecodeResult::kSchemaMismatch: return "schema_version differs from this build";
  }
  return "?";
}

namespace {

struct UdpmAddress {
  std::string group = "239.255.76.67";
  int port = 7667;
  int ttl = 0;
};

// udpm://GROUP:PORT?ttl=N (every part optional, as in lcm_create).
UdpmAddress parse_udpm(const std::string& url) {
  UdpmAddress a;
  std::string rest = url.substr(std::string("udpm://").size());
  std::string query;
  if (auto q = rest.find('?'); q != std::string::npos) {
    query = rest.substr(q + 1);
    rest = rest.substr(0, q);
  }
  if (!rest.empty()) {
    if (auto c = rest.find(':'); c != std::string::npos) {
      a.group = rest.substr(0, c);
      a.port = std::atoi(rest.substr(c + 1).c_str());
    } else {
      a.group = rest;
    }
  }
  std::istringstream qs(query);
  for (std::string kv; std::getline(qs, kv, '&');)
    if (kv.rfind("ttl=", 0) == 0) a.ttl = std::atoi(kv.c_str() + 4);
  return a;
}

}  // namespace

std::string diagnose_lcm_url(const std::string& url_in) {
  std::string url = url_in;
  if (url.empty()) {
    const char* env = std::getenv("LCM_DEFAULT_URL");
    url = env ? env : "udpm://239.255.76.67:7667?ttl=0";
  }
  if (url.rfind("udpm://", 0) != 0) return "";
  const UdpmAddress a = parse_udpm(url);
  in_addr group{};
  if (inet_pton(AF_INET, a.group.c_str(), &group) != 1 || (ntohl(group.s_addr) >> 28) != 0xE)
    return "LCM URL '" + url + "': '" + a.group +
           "' is not an IPv4 multicast address (224.0.0.0 - 239.255.255.255); use e.g. "
           "udpm://239.255.76.67:7667?ttl=0";
  if (a.port <= 0 || a.port > 65535)
    return "LCM URL '" + url + "': port " + std::to_string(a.port) + " is not in 1..65535";

  const int fd = ::socket(AF_INET, SOCK_DGRAM, 0);
  if (fd < 0) return std::string("cannot open a UDP socket: ") + std::strerror(errno);
  std::string problem;
  sockaddr_in dst{};
  dst.sin_family = AF_INET;
  dst.sin_port = htons(static_cast<uint16_t>(a.port));
  dst.sin_addr = group;
  if (::connect(fd, reinterpret_cast<sockaddr*>(&dst), sizeof dst) != 0) {
    const int e = errno;
    problem = "LCM udpm cannot reach multicast group " + a.group + " (" + std::strerror(e) +
              "): this machine has no route for multicast traffic. On one host, run:\n"
              "  sudo ip link set lo multicast on && sudo ip route add 224.0.0.0/4 dev lo\n"
              "Between hosts, route it through the network interface instead:\n"
              "  sudo ip route add 224.0.0.0/4 dev <interface>   (see `ip link` for the name)\n"
              "For a single process, use --lcm-url memq:// instead.";
  } else {
    {
      ip_mreq mreq{};
      mreq.imr_multiaddr = group;
      mreq.imr_interface.s_addr = htonl(INADDR_ANY);
      const int rfd = ::socket(AF_INET, SOCK_DGRAM, 0);
      if (rfd >= 0 && ::setsockopt(rfd, IPPROTO_IP, IP_ADD_MEMBERSHIP, &mreq, sizeof mreq) != 0) {
        problem = "LCM udpm cannot join multicast group " + a.group + " (" + std::strerror(errno) +
                  "). Usually the route is missing or points at an interface without multicast. Run:\n"
                  "  sudo ip link set lo multicast on && sudo ip route add 224.0.0.0/4 dev lo\n"
                  "(or `dev <interface>` between hosts).";
      }
      if (rfd >= 0) ::close(rfd);
    }
  }
  ::close(fd);
  return problem;
}

// A keyed session names its key by fingerprint; an unkeyed one that crosses hosts says who can inject.
static void announce_session(const std::string& url_in, const Authenticator* auth) {
  std::string url = url_in;
  if (url.empty()) {
    const char* env = std::getenv("LCM_DEFAULT_URL");
    url = env ? env : "udpm://239.255.76.67:7667?ttl=0";
  }
  if (auth) {
    std::fprintf(stderr, "[haptree bus] %s: session key %s: every message is authenticated (HMAC-SHA512-256, "
                 "sender %08x)\n", url.c_str(), auth->key().fingerprint.c_str(), auth->sender_id());
  } else if (url.rfind("udpm://", 0) == 0 && parse_udpm(url).ttl > 0) {
    std::fprintf(stderr,
                 "[haptree bus] WARNING: %s crosses hosts (ttl=%d) WITHOUT a session key: anyone on the LAN "
                 "can push forces into this session (USER_FORCE) and into the device (FEEDBACK, snapshots). "
                 "Give every process --session-key-file FILE (or HAPTREE_SESSION_KEY_FILE).\n",
                 url.c_str(), parse_udpm(url).ttl);
  }
}

Bus::Bus(const std::string& url, std::shared_ptr<const SessionKey> key) : url_(url) {
  const std::string problem = diagnose_lcm_url(url);
  if (!problem.empty()) throw BusError(problem);
  lcm_ = std::make_unique<lcm::LCM>(url);
  if (!lcm_->good()) {
    throw BusError("LCM could not start with URL '" + url +
                   "' (LCM printed the reason above, if any). Valid forms: memq://, "
                   "udpm://239.255.76.67:7667?ttl=0, file:///path/log.lcm?mode=w");
  }
  if (key) auth_ = std::make_unique<Authenticator>(std::move(key));
  announce_session(url, auth_.get());
}

Bus::~Bus() = default;

int Bus::publish_raw(const std::string& channel, const void* data, int size) noexcept {
  int r = -1;
  try {
    if (auth_) {   // keyed: publish the bytes + trailer from a per-thread buffer (no allocation once grown)
      thread_local std::vector<uint8_t> sealed;
      if (size < 0) return fail_publish();
      sealed.resize(static_cast<size_t>(size) + kAuthTrailerBytes);
      if (size > 0) std::memcpy(sealed.data(), data, static_cast<size_t>(size));
      const size_t n = auth_->seal(channel, sealed.data(), static_cast<size_t>(size));
      r = lcm_->publish(channel, sealed.data(), static_cast<unsigned>(n));
    } else {
      r = lcm_->publish(channel, data, static_cast<unsigned>(size));
    }
  } catch (...) {
    r = -1;
  }
  if (r != 0) return fail_publish();
  return 0;
}

RawSubscription& Bus::subscribe_raw(const std::string& channel, RawSubscription::Callback cb) {
  auto sub = std::make_unique<RawSubscription>(channel, std::move(cb));
  auto* raw = sub.get();
  raw->auth = auth_.get();   // before the first message can arrive
  {
    std::lock_guard<std::mutex> lock(delivery_mutex());
    raw->c_subscription =
        lcm_subscribe(lcm_->getUnderlyingLCM(), channel.c_str(), &RawSubscription::dispatch, raw);
  }
  add(std::move(sub));
  return *raw;
}

std::mutex& delivery_mutex() {
  static std::mutex m;
  return m;
}

void set_delivery(Bus& bus, RawSubscription& sub, bool on) {
  std::lock_guard<std::mutex> lock(delivery_mutex());
  if (on == (sub.c_subscription != nullptr)) return;
  lcm_t* c = bus.lcm().getUnderlyingLCM();
  if (on) {
    sub.c_subscription = lcm_subscribe(c, sub.channel().c_str(), &RawSubscription::dispatch, &sub);
  } else {
    lcm_unsubscribe(c, sub.c_subscription);   // safe against a dispatch in progress (see bus.hpp)
    sub.c_subscription = nullptr;
  }
}

void Bus::add(std::unique_ptr<SubscriptionBase> sub) {
  std::lock_guard<std::mutex> lock(subs_mutex_);
  subs_.push_back(std::move(sub));
}

// lcm_handle_timeout() itself is select() + lcm_handle(), but FD_SET on the provider's fd: the tcpq
// provider's fd is -1 between a lost hub connection and its reconnect, and glibc's fortified FD_SET
// aborts the process on it ("bit out of range 0 - FD_SETSIZE"). A launcher SIGKILLed with its hub made
// the device_bridge abort before it could unlink its shared-memory segments. poll() has neither
// limit (it ignores a negative fd); the result codes are lcm_handle_timeout's.
int Bus::handle_timeout(int timeout_ms) noexcept {
  try {
    const int fd = lcm_->getFileno();
    if (fd < 0) {
      if (timeout_ms > 0) std::this_thread::sleep_for(std::chrono::milliseconds(timeout_ms));
      return -1;
    }
    pollfd p{fd, POLLIN, 0};
    const int r = ::poll(&p, 1, timeout_ms);
    if (r < 0) return errno == EINTR ? 0 : -1;
    if (r == 0) return 0;
    return lcm_->handle() == 0 ? 1 : -1;
  } catch (...) {
    return -1;
  }
}

int64_t Bus::rejected_total() const {
  std::lock_guard<std::mutex> lock(subs_mutex_);
  int64_t n = 0;
  for (const auto& s : subs_) n += s->stats().rejected();
  return n;
}

std::vector<const SubscriptionBase*> Bus::subscriptions() const {
  std::lock_guard<std::mutex> lock(subs_mutex_);
  std::vector<const SubscriptionBase*> out;
  for (const auto& s : subs_) out.push_back(s.get());
  return out;
}

HandlerThread::HandlerThread(Bus& bus, int timeout_ms) : bus_(bus), timeout_ms_(timeout_ms) {
  thread_ = std::thread([this] {
    while (!stop_.load(std::memory_order_relaxed)) {
      const int r = bus_.handle_timeout(timeout_ms_);
      if (r > 0) handled_.fetch_add(1, std::memory_order_relaxed);
      else if (r < 0) {
        errors_.fetch_add(1, std::memory_order_relaxed);
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
      }
    }
  });
}

HandlerThread::~HandlerThread() { stop(); }

void HandlerThread::stop() {
  stop_.store(true);
  if (thread_.joinable()) thread_.join();
}

}  // namespace haptree::bus
