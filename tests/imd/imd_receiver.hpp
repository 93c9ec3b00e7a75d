// A minimal IMD receiver written from the IMD specification (IMDv3 document of Becksteinlab/imdclient
// and the v2 layout it inherits), with its own byte handling: it does not use haptree/imd, so the
// tests check that library rather than mirror it.
#pragma once

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <vector>

namespace haptree {
namespace {

using Clock = std::chrono::steady_clock;

// ---------------------------------------------------------------- a receiver from the spec

uint32_t be32(const uint8_t* p) { return (uint32_t(p[0]) << 24) | (uint32_t(p[1]) << 16) | (uint32_t(p[2]) << 8) | p[3]; }
void put_be32(std::vector<uint8_t>& v, uint32_t x) {
  for (int s = 24; s >= 0; s -= 8) v.push_back(uint8_t(x >> s));
}

struct Receiver {
  int fd = -1;
  explicit Receiver(int port, int rcvbuf = 0) {
    fd = ::socket(AF_INET, SOCK_STREAM, 0);
    if (rcvbuf > 0) ::setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_port = htons(static_cast<uint16_t>(port));
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (::connect(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) {
      ::close(fd);
      fd = -1;
    }
  }
  ~Receiver() { if (fd >= 0) ::close(fd); }
  // Reads exactly n bytes within timeout; false on timeout or EOF.
  bool read_exact(void* dst, size_t n, double timeout_s = 5) {
    auto* p = static_cast<uint8_t*>(dst);
    const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
    while (n > 0) {
      const int ms = static_cast<int>(std::chrono::duration<double, std::milli>(end - Clock::now()).count());
      if (ms <= 0) return false;
      pollfd f{fd, POLLIN, 0};
      if (::poll(&f, 1, ms) <= 0) return false;
      const ssize_t r = ::recv(fd, p, n, 0);
      if (r <= 0) return false;
      p += r;
      n -= static_cast<size_t>(r);
    }
    return true;
  }
  bool header(int32_t& type, int32_t& length, double timeout_s = 5) {
    uint8_t h[8];
    if (!read_exact(h, 8, timeout_s)) return false;
    type = static_cast<int32_t>(be32(h));
    length = static_cast<int32_t>(be32(h + 4));
    return true;
  }
  // The handshake: type 4 big-endian, version in the engine's byte order (here: ours).
  int handshake() {
    uint8_t h[8];
    if (!read_exact(h, 8)) return -1;
    if (be32(h) != 4) return -2;
    int32_t v;
    std::memcpy(&v, h + 4, 4);
    return v;
  }
  bool send_bytes(const std::vector<uint8_t>& b) {
    return ::send(fd, b.data(), b.size(), MSG_NOSIGNAL) == static_cast<ssize_t>(b.size());
  }
  bool send_simple(int32_t type, int32_t value = 0) {
    std::vector<uint8_t> b;
    put_be32(b, static_cast<uint32_t>(type));
    put_be32(b, static_cast<uint32_t>(value));
    return send_bytes(b);
  }
  // MDCOMM: big-endian header, body in the engine's order (native here).
  bool send_forces(const std::vector<int32_t>& idx, const std::vector<float>& f) {
    std::vector<uint8_t> b;
    put_be32(b, 6);
    put_be32(b, static_cast<uint32_t>(idx.size()));
    const size_t at = b.size();
    b.resize(at + 4 * idx.size() + 4 * f.size());
    std::memcpy(b.data() + at, idx.data(), 4 * idx.size());
    std::memcpy(b.data() + at + 4 * idx.size(), f.data(), 4 * f.size());
    return send_bytes(b);
  }
  // True once the engine closed the connection (EOF) within timeout; discards data on the way.
  bool closed_by_peer(double timeout_s = 5) {
    const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
    uint8_t buf[65536];
    while (Clock::now() < end) {
      pollfd f{fd, POLLIN, 0};
      if (::poll(&f, 1, 50) <= 0) continue;
      const ssize_t r = ::recv(fd, buf, sizeof buf, 0);
      if (r == 0) return true;
      if (r < 0 && errno != EAGAIN && errno != EINTR) return true;   // reset
    }
    return false;
  }
};

// One IMD frame as a receiver sees it.
struct Frame {
  bool has_time = false;
  double dt = 0, time = 0;
  int64_t step = -1;
  std::vector<float> x, v, f;   // Å, Å/ps, kJ/(mol Å)
};

// Reads one frame. v2: a coordinate packet. v3 (the server's default session info: time,
// coordinates, velocities, forces): up to and including the force packet.
bool read_frame(Receiver& r, Frame& f, bool v3, double timeout_s = 5) {
  f = Frame{};
  for (;;) {
    int32_t type, n;
    if (!r.header(type, n, timeout_s)) return false;
    if (type == 12) {   // TIME: float64 dt, float64 time, int64 step
      if (n != 1) return false;
      uint8_t b[24];
      if (!r.read_exact(b, 24)) return false;
      std::memcpy(&f.dt, b, 8);
      std::memcpy(&f.time, b + 8, 8);
      std::memcpy(&f.step, b + 16, 8);
      f.has_time = true;
    } else if (type == 2 || type == 14 || type == 15) {
      if (n < 0 || n > 1000000) return false;
      auto& dst = type == 2 ? f.x : type == 14 ? f.v : f.f;
      dst.resize(3 * static_cast<size_t>(n));
      if (!r.read_exact(dst.data(), 12 * static_cast<size_t>(n))) return false;
      if ((type == 2 && !v3) || type == 15) return true;
    } else {
      return false;   // nothing else is announced
    }
  }
}

}  // namespace
}  // namespace haptree
