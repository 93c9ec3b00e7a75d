// TcpqHub: see tcpq_hub.hpp.
#include "launcher/tcpq_hub.hpp"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <memory>
#include <regex>
#include <stdexcept>
#include <unordered_map>
#include <vector>

namespace haptree::launcher {

namespace {

constexpr uint32_t kMagicServer = 0x287617fa;
constexpr uint32_t kMagicClient = 0x287617fb;
constexpr uint32_t kVersion = 0x0100;
constexpr uint32_t kPublish = 1, kSubscribe = 2, kUnsubscribe = 3;
constexpr uint32_t kMaxChannel = 1024;
constexpr uint32_t kMaxData = 64u << 20;

uint32_t get_u32(const uint8_t* p) {
  uint32_t v;
  std::memcpy(&v, p, 4);
  return ntohl(v);
}
void put_u32(std::string& s, uint32_t v) {
  const uint32_t n = htonl(v);
  s.append(reinterpret_cast<const char*>(&n), 4);
}

struct Client {
  int fd = -1;
  bool greeted = false;
  std::vector<uint8_t> in;
  size_t in_off = 0;
  std::string out;
  size_t out_off = 0;
  std::vector<std::string> sub_names;
  std::vector<std::regex> subs;
  std::unordered_map<std::string, bool> match_cache;
  bool dead = false;

  bool wants(const std::string& channel) {
    auto it = match_cache.find(channel);
    if (it != match_cache.end()) return it->second;
    bool m = false;
    for (const auto& r : subs)
      if (std::regex_match(channel, r)) {
        m = true;
        break;
      }
    match_cache.emplace(channel, m);
    return m;
  }
  size_t pending() const { return out.size() - out_off; }
};

}  // namespace

TcpqHub::TcpqHub(int port, size_t max_queue_bytes) : max_queue_bytes_(max_queue_bytes) {
  listen_fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (listen_fd_ < 0) throw std::runtime_error(std::string("tcpq hub: socket(): ") + std::strerror(errno));
  const int one = 1;
  ::setsockopt(listen_fd_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
  sockaddr_in sa{};
  sa.sin_family = AF_INET;
  sa.sin_port = htons(static_cast<uint16_t>(port));
  sa.sin_addr.s_addr = htonl(INADDR_LOOPBACK);   // loopback only: nothing reachable from outside
  if (::bind(listen_fd_, reinterpret_cast<sockaddr*>(&sa), sizeof(sa)) != 0 || ::listen(listen_fd_, 64) != 0) {
    const std::string why = std::strerror(errno);
    ::close(listen_fd_);
    throw std::runtime_error("tcpq hub: cannot listen on 127.0.0.1:" + std::to_string(port) + ": " + why +
                             " (is the loopback interface up? `ip link set lo up`)");
  }
  socklen_t len = sizeof(sa);
  ::getsockname(listen_fd_, reinterpret_cast<sockaddr*>(&sa), &len);
  port_ = ntohs(sa.sin_port);
  ::fcntl(listen_fd_, F_SETFL, ::fcntl(listen_fd_, F_GETFL) | O_NONBLOCK);
  thread_ = std::thread([this] { loop(); });
}

TcpqHub::~TcpqHub() { stop(); }

void TcpqHub::stop() {
  if (stop_.exchange(true)) return;
  if (thread_.joinable()) thread_.join();
  if (listen_fd_ >= 0) ::close(listen_fd_);
  listen_fd_ = -1;
}

void TcpqHub::loop() {
  std::vector<std::unique_ptr<Client>> clients;
  std::vector<pollfd> pfds;
  std::vector<uint8_t> rbuf(1 << 16);
  std::string frame;
  auto fail = [this](Client& c) {
    c.dead = true;
    protocol_errors_.fetch_add(1);
  };
  // Parses every complete frame in c.in; forwards publications.
  auto parse = [&](Client& c) {
    for (;;) {
      const size_t avail = c.in.size() - c.in_off;
      const uint8_t* p = c.in.data() + c.in_off;
      if (!c.greeted) {
        if (avail < 8) return;
        if (get_u32(p) != kMagicClient) return fail(c);
        std::string hello;
        put_u32(hello, kMagicServer);
        put_u32(hello, kVersion);
        c.out.append(hello);
        c.greeted = true;
        c.in_off += 8;
        continue;
      }
      if (avail < 8) return;
      const uint32_t type = get_u32(p), clen = get_u32(p + 4);
      if (clen > kMaxChannel || (type != kPublish && type != kSubscribe && type != kUnsubscribe)) return fail(c);
      if (avail < 8 + clen) return;
      const std::string channel(reinterpret_cast<const char*>(p + 8), clen);
      if (type == kPublish) {
        if (avail < 12 + clen) return;
        const uint32_t dlen = get_u32(p + 8 + clen);
        if (dlen > kMaxData) return fail(c);
        if (avail < 12 + clen + dlen) return;
        messages_in_.fetch_add(1, std::memory_order_relaxed);
        frame.clear();
        put_u32(frame, kPublish);
        put_u32(frame, clen);
        frame.append(channel);
        put_u32(frame, dlen);
        frame.append(reinterpret_cast<const char*>(p + 12 + clen), dlen);
        for (auto& o : clients) {
          if (o->dead || !o->greeted || !o->wants(channel)) continue;
          if (o->pending() + frame.size() > max_queue_bytes_) {
            dropped_.fetch_add(1, std::memory_order_relaxed);
            continue;
          }
          o->out.append(frame);
          messages_out_.fetch_add(1, std::memory_order_relaxed);
        }
        c.in_off += 12 + clen + dlen;
      } else {
        if (type == kSubscribe) {
          try {
            c.subs.emplace_back(channel, std::regex::ECMAScript | std::regex::optimize);
            c.sub_names.push_back(channel);
          } catch (const std::regex_error&) {
            protocol_errors_.fetch_add(1);
          }
        } else {
          for (size_t i = 0; i < c.sub_names.size(); ++i)
            if (c.sub_names[i] == channel) {
              c.sub_names.erase(c.sub_names.begin() + static_cast<std::ptrdiff_t>(i));
              c.subs.erase(c.subs.begin() + static_cast<std::ptrdiff_t>(i));
              break;
            }
        }
        c.match_cache.clear();
        c.in_off += 8 + clen;
      }
    }
  };

  while (!stop_.load()) {
    pfds.clear();
    pfds.push_back({listen_fd_, POLLIN, 0});
    for (auto& c : clients) pfds.push_back({c->fd, static_cast<short>(POLLIN | (c->pending() ? POLLOUT : 0)), 0});
    if (::poll(pfds.data(), pfds.size(), 10) < 0 && errno != EINTR) break;
    if (pfds[0].revents & POLLIN) {
      for (;;) {
        const int fd = ::accept4(listen_fd_, nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
        if (fd < 0) break;
        const int one = 1;
        ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
        auto c = std::make_unique<Client>();
        c->fd = fd;
        clients.push_back(std::move(c));
        accepted_.fetch_add(1);
        connected_.fetch_add(1);
      }
    }
    // read (only the clients that were polled: new ones are read next round)
    for (size_t i = 1; i < pfds.size(); ++i) {
      Client& c = *clients[i - 1];
      if (!(pfds[i].revents & (POLLIN | POLLHUP | POLLERR))) continue;
      for (;;) {
        const ssize_t n = ::recv(c.fd, rbuf.data(), rbuf.size(), 0);
        if (n > 0) {
          c.in.insert(c.in.end(), rbuf.begin(), rbuf.begin() + n);
          if (static_cast<size_t>(n) < rbuf.size()) break;
          continue;
        }
        if (n == 0 || (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)) c.dead = true;
        break;
      }
      const int one = 1;   // ack at once: the lcm client writes a message in several small send()s (Nagle)
      ::setsockopt(c.fd, IPPROTO_TCP, TCP_QUICKACK, &one, sizeof(one));
      if (!c.dead) parse(c);
      if (c.in_off > 0 && (c.in_off == c.in.size() || c.in_off > (1u << 20))) {
        c.in.erase(c.in.begin(), c.in.begin() + static_cast<std::ptrdiff_t>(c.in_off));
        c.in_off = 0;
      }
    }
    // write
    for (auto& c : clients) {
      while (!c->dead && c->pending()) {
        const ssize_t n = ::send(c->fd, c->out.data() + c->out_off, c->pending(), MSG_NOSIGNAL);
        if (n > 0) {
          c->out_off += static_cast<size_t>(n);
          continue;
        }
        if (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) c->dead = true;
        break;
      }
      if (c->out_off == c->out.size()) {
        c->out.clear();
        c->out_off = 0;
      } else if (c->out_off > (1u << 20)) {
        c->out.erase(0, c->out_off);
        c->out_off = 0;
      }
    }
    for (size_t i = 0; i < clients.size();) {
      if (clients[i]->dead) {
        ::close(clients[i]->fd);
        clients.erase(clients.begin() + static_cast<std::ptrdiff_t>(i));
        connected_.fetch_sub(1);
      } else {
        ++i;
      }
    }
  }
  for (auto& c : clients) ::close(c->fd);
  connected_ = 0;
}

}  // namespace haptree::launcher
