#pragma once
// TcpqHub: a minimal hub for LCM's tcpq:// provider (liblcm 1.3's lcm_tcpq.c client protocol), bound to
// 127.0.0.1 only, so processes on one host can share one LCM bus without any network interface or
// multicast route (no datagram can leave the machine). Used by `haptree_run --processes` and the
// real-process integration tests.
//
// Protocol (all integers 32-bit big-endian): client sends MAGIC_CLIENT, version; hub answers
// MAGIC_SERVER, version. Client -> hub: SUBSCRIBE/UNSUBSCRIBE (type, channel length, channel regex) and
// PUBLISH (type, channel length, channel, data length, data). Hub -> client: PUBLISH frames of every
// message whose channel fully matches one of the client's regexes (LCM semantics; the publisher gets
// its own messages too, as with udpm). Sockets are non-blocking: a client that does not read is not
// allowed to stall the others — above `max_queue_bytes` of pending output its new messages are dropped
// (counted), i.e. the same "newest wins" loss a full UDP socket buffer gives.
#include <atomic>
#include <cstdint>
#include <string>
#include <thread>

namespace haptree::launcher {

class TcpqHub {
 public:
  // port 0: the kernel picks a free port (see port()). Throws std::runtime_error when it cannot listen.
  explicit TcpqHub(int port = 0, size_t max_queue_bytes = 8u << 20);
  ~TcpqHub();
  TcpqHub(const TcpqHub&) = delete;
  TcpqHub& operator=(const TcpqHub&) = delete;

  int port() const noexcept { return port_; }
  std::string url() const { return "tcpq://127.0.0.1:" + std::to_string(port_); }
  void stop();  // idempotent; joins and closes every socket

  int64_t clients_accepted() const noexcept { return accepted_.load(); }
  int64_t clients_connected() const noexcept { return connected_.load(); }
  int64_t messages_in() const noexcept { return messages_in_.load(); }
  int64_t messages_out() const noexcept { return messages_out_.load(); }
  int64_t messages_dropped() const noexcept { return dropped_.load(); }
  int64_t protocol_errors() const noexcept { return protocol_errors_.load(); }

 private:
  void loop();
  int listen_fd_ = -1;
  int port_ = 0;
  size_t max_queue_bytes_;
  std::atomic<bool> stop_{false};
  std::atomic<int64_t> accepted_{0}, connected_{0}, messages_in_{0}, messages_out_{0}, dropped_{0},
      protocol_errors_{0};
  std::thread thread_;
};

}  // namespace haptree::launcher
