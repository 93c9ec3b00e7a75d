// haptree::bus::Bus — one lcm::LCM instance, typed subscriptions that decode raw bytes themselves
// (never throw out of a handler, count what they reject), plain-words set-up errors, and a handler thread.
// LCM 1.3.1 offers member-function subscriptions only; Subscription<T> is that member.
#pragma once

#include <lcm/lcm-cpp.hpp>

#include <atomic>
#include <cstdint>
#include <cstring>
#include <functional>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "haptree/bus/auth.hpp"
#include "haptree/bus/latest_value.hpp"
#include "haptree/bus/wire.hpp"

namespace haptree::bus {

// Set-up failure of the bus, with the fix in the message (e.g. the missing multicast route).
class BusError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Looks at an LCM URL and this machine's network set-up; returns "" if nothing is wrong, otherwise one
// paragraph in plain words that ends with the command that fixes it. Only udpm:// is examined.
std::string diagnose_lcm_url(const std::string& url);

// Counters of one subscription. Written by the handling thread, readable from any thread.
struct ChannelStats {
  std::atomic<int64_t> received{0};        // messages that reached the handler
  std::atomic<int64_t> accepted{0};        // decoded, right schema, handed to the callback
  std::atomic<int64_t> decode_errors{0};   // fingerprint/size mismatch, implausible counts, random bytes
  std::atomic<int64_t> schema_rejects{0};  // decoded but schema_version != this build's
  std::atomic<int64_t> handler_errors{0};  // the callback threw (caught here)
  std::atomic<int32_t> last_peer_schema{-1};  // schema_version read at byte 8 of the last rejected message
  std::atomic<int64_t> auth_rejects{0};    // keyed session: no/wrong trailer, bad MAC, replay (auth.hpp)
  int64_t rejected() const noexcept { return decode_errors.load() + schema_rejects.load() + auth_rejects.load(); }
};

class SubscriptionBase {
 public:
  explicit SubscriptionBase(std::string channel) : channel_(std::move(channel)) {}
  virtual ~SubscriptionBase() = default;
  const std::string& channel() const noexcept { return channel_; }
  const ChannelStats& stats() const noexcept { return stats_; }
  lcm::Subscription* lcm_subscription = nullptr;   // typed subscriptions (never unsubscribed)
  // Raw subscriptions go through LCM's C API: lcm_unsubscribe keeps a handler that a dispatch on
  // another thread is running until it returns, and the userdata (this object) lives as long as the
  // Bus. lcm::LCM::unsubscribe instead deletes its C++ wrapper at once, which that dispatch then
  // reads (ASan: heap-buffer-overflow in RawSubscription::on_raw from the coupler's delivery toggle).
  lcm_subscription_t* c_subscription = nullptr;
  Authenticator* auth = nullptr;   // the Bus's, in a keyed session: messages are verified and stripped

  // Stops delivery for good: waits for a callback running on a handler thread to return; none runs
  // after. The Subscription lives as long as the Bus, but its callback usually captures its owner (a
  // SimServer, a Coupler): an owner destroyed while the Bus dispatches must close first, or the next
  // message calls into freed memory (embedded_test's second SimServer, destroyed with the coupler
  // still publishing: SIGSEGV). Not from inside this subscription's own callback.
  void close() noexcept {
    for (int e = 0; !gate_.compare_exchange_weak(e, kClosed, std::memory_order_acq_rel); e = 0) {
      if (e == kClosed) return;
      std::this_thread::yield();
    }
  }
  bool closed() const noexcept { return gate_.load(std::memory_order_acquire) == kClosed; }

 protected:
  // One callback at a time, and none once closed: a lock-free gate (no mutex on the handler thread).
  struct Entry {
    explicit Entry(std::atomic<int>& g) noexcept : gate(g) {
      int e = kOpen;
      ok = gate.compare_exchange_strong(e, kBusy, std::memory_order_acquire);
    }
    ~Entry() {
      if (ok) gate.store(kOpen, std::memory_order_release);
    }
    std::atomic<int>& gate;
    bool ok = false;
  };
  static constexpr int kOpen = 0, kBusy = 1, kClosed = 2;
  std::string channel_;
  ChannelStats stats_;
  std::atomic<int> gate_{kOpen};
};

// The subscriptions an object made, closed when it is destroyed: call close_all() first thing in its
// destructor (its callbacks capture it), or make this its last member.
class SubscriptionGuard {
 public:
  SubscriptionGuard() = default;
  SubscriptionGuard(const SubscriptionGuard&) = delete;
  SubscriptionGuard& operator=(const SubscriptionGuard&) = delete;
  ~SubscriptionGuard() { close_all(); }
  template <class S>
  S& operator()(S& sub) {
    subs_.push_back(&sub);
    return sub;
  }
  void close_all() noexcept {
    for (SubscriptionBase* s : subs_) s->close();
    subs_.clear();
  }

 private:
  std::vector<SubscriptionBase*> subs_;
};

// Keyed session: verifies and strips the trailer (*size becomes the payload size); counts a rejection.
inline bool authentic(Authenticator* a, const std::string& channel, const void* data, size_t* size,
                      ChannelStats& stats) noexcept {
  if (a == nullptr) return true;
  if (a->open(channel, data, *size, size) == AuthVerdict::kOk) return true;
  stats.auth_rejects.fetch_add(1, std::memory_order_relaxed);
  return false;
}

// Typed subscription: decodes into one reused T (no allocation once T reached its largest size), checks
// schema_version, calls the callback with the message. on_raw never throws.
template <class T>
class Subscription final : public SubscriptionBase {
 public:
  using Callback = std::function<void(const T& msg, const std::string& channel)>;
  Subscription(std::string channel, Callback cb) : SubscriptionBase(std::move(channel)), cb_(std::move(cb)) {}

  void on_raw(const lcm::ReceiveBuffer* rbuf, const std::string& channel) noexcept {
    const Entry entry(gate_);
    if (!entry.ok) return;
    stats_.received.fetch_add(1, std::memory_order_relaxed);
    size_t size = rbuf->data_size;
    if (!authentic(auth, channel, rbuf->data, &size, stats_)) return;
    const DecodeResult r = decode_checked(rbuf->data, size, msg_);
    if (r != DecodeResult::kOk) {
      (r == DecodeResult::kSchemaMismatch ? stats_.schema_rejects : stats_.decode_errors)
          .fetch_add(1, std::memory_order_relaxed);
      int32_t peer = -1;
      if (peek_schema_version(rbuf->data, size, &peer)) stats_.last_peer_schema.store(peer);
      return;
    }
    stats_.accepted.fetch_add(1, std::memory_order_relaxed);
    try {
      cb_(msg_, channel);
    } catch (...) {
      stats_.handler_errors.fetch_add(1, std::memory_order_relaxed);
    }
  }

 private:
  Callback cb_;
  T msg_{};
};

// Raw subscription: bytes as they came (for mirrors, loggers, fuzz counters).
class RawSubscription final : public SubscriptionBase {
 public:
  using Callback = std::function<void(const void* data, uint32_t size, const std::string& channel)>;
  RawSubscription(std::string channel, Callback cb) : SubscriptionBase(std::move(channel)), cb_(std::move(cb)) {}
  // LCM's C callback (userdata = this).
  static void dispatch(const lcm_recv_buf_t* rbuf, const char* channel, void* self) {
    const lcm::ReceiveBuffer rb{rbuf->data, rbuf->data_size, rbuf->recv_utime};
    static_cast<RawSubscription*>(self)->on_raw(&rb, std::string(channel));
  }
  void on_raw(const lcm::ReceiveBuffer* rbuf, const std::string& channel) noexcept {
    const Entry entry(gate_);
    if (!entry.ok) return;
    stats_.received.fetch_add(1, std::memory_order_relaxed);
    size_t size = rbuf->data_size;
    if (!authentic(auth, channel, rbuf->data, &size, stats_)) return;
    stats_.accepted.fetch_add(1, std::memory_order_relaxed);
    try {
      cb_(rbuf->data, static_cast<uint32_t>(size), channel);
    } catch (...) {
      stats_.handler_errors.fetch_add(1, std::memory_order_relaxed);
    }
  }

 private:
  Callback cb_;
};

// Serialises every change of lcm::LCM's list of subscriptions (subscribe, subscribe_raw,
// set_delivery in delivery.hpp): that list is not thread-safe.
std::mutex& delivery_mutex();

class Bus {
 public:
  // url: any LCM URL. "memq://" keeps everything in this process (all components must share this Bus);
  // "udpm://239.255.76.67:7667?ttl=0" between processes/hosts; "" = $LCM_DEFAULT_URL or LCM's default.
  // Throws BusError in plain words (with the fix) when the transport cannot be set up.
  // key: the session key (auth.hpp): every message published is sealed, every message received must
  // verify. Default: the process's key (--session-key-file / HAPTREE_SESSION_KEY_FILE), none if unset.
  explicit Bus(const std::string& url = "memq://", std::shared_ptr<const SessionKey> key = process_session_key());
  ~Bus();
  Bus(const Bus&) = delete;
  Bus& operator=(const Bus&) = delete;

  const std::string& url() const noexcept { return url_; }
  lcm::LCM& lcm() noexcept { return *lcm_; }

  // Encodes msg into a per-thread buffer (no allocation once grown) and publishes it. Returns 0 on
  // success, -1 on failure (counted in publish_errors()). Never throws.
  template <class T>
  int publish(const std::string& channel, const T& msg) noexcept {
    thread_local std::vector<uint8_t> buf;
    const int n = msg.getEncodedSize();
    if (n < 0) return fail_publish();
    try {
      if (buf.size() < static_cast<size_t>(n)) buf.resize(static_cast<size_t>(n));
    } catch (...) {
      return fail_publish();
    }
    if (msg.encode(buf.data(), 0, n) != n) return fail_publish();
    return publish_raw(channel, buf.data(), n);
  }
  int publish_raw(const std::string& channel, const void* data, int size) noexcept;
  // Keyed session: the authenticator (sender id, counters), nullptr without a key.
  const Authenticator* authenticator() const noexcept { return auth_.get(); }

  // Typed subscription. The callback runs on the thread that handles the bus (see HandlerThread);
  // keep it short (copy into a LatestValue). The Subscription lives as long as the Bus.
  template <class T>
  Subscription<T>& subscribe(const std::string& channel, typename Subscription<T>::Callback cb) {
    auto sub = std::make_unique<Subscription<T>>(channel, std::move(cb));
    auto* raw = sub.get();
    raw->auth = auth_.get();   // before the first message can arrive
    {
      // lcm::LCM's own list of subscriptions is unguarded: two threads subscribing at once (a
      // component constructed while another starts) would race on it.
      std::lock_guard<std::mutex> lock(delivery_mutex());
      raw->lcm_subscription = lcm_->subscribe(channel, &Subscription<T>::on_raw, raw);
    }
    add(std::move(sub));
    return *raw;
  }
  // Decoded messages go straight into a mailbox (the handler thread is its only writer).
  template <class T>
  Subscription<T>& subscribe_latest(const std::string& channel, LatestValue<T>& box) {
    return subscribe<T>(channel, [&box](const T& m, const std::string&) { box.write(m); });
  }
  RawSubscription& subscribe_raw(const std::string& channel, RawSubscription::Callback cb);

  // Handles at most one message, waiting up to timeout_ms. >0 handled, 0 timeout, <0 error.
  int handle_timeout(int timeout_ms) noexcept;

  // Sum over all subscriptions of rejected() (decode errors + schema mismatches).
  int64_t rejected_total() const;
  int64_t publish_errors() const noexcept { return publish_errors_.load(); }
  // Snapshot of every subscription's channel and counters (pointers live as long as the Bus).
  std::vector<const SubscriptionBase*> subscriptions() const;

 private:
  void add(std::unique_ptr<SubscriptionBase> sub);
  int fail_publish() noexcept {
    publish_errors_.fetch_add(1, std::memory_order_relaxed);
    return -1;
  }
  std::string url_;
  std::unique_ptr<lcm::LCM> lcm_;
  std::unique_ptr<Authenticator> auth_;   // keyed session only
  mutable std::mutex subs_mutex_;  // guards subs_ (subscribe/list only; never taken in a handler)
  std::vector<std::unique_ptr<SubscriptionBase>> subs_;
  std::atomic<int64_t> publish_errors_{0};
};

// Runs bus.handle_timeout(timeout_ms) in a loop on its own thread until stop() or destruction.
class HandlerThread {
 public:
  explicit HandlerThread(Bus& bus, int timeout_ms = 20);
  ~HandlerThread();
  HandlerThread(const HandlerThread&) = delete;
  HandlerThread& operator=(const HandlerThread&) = delete;
  void stop();  // idempotent; joins
  int64_t handled() const noexcept { return handled_.load(); }
  int64_t errors() const noexcept { return errors_.load(); }  // handle() returned <0
  std::thread::native_handle_type native_handle() { return thread_.native_handle(); }   // realtime.hpp

 private:
  Bus& bus_;
  int timeout_ms_;
  std::atomic<bool> stop_{false};
  std::atomic<int64_t> handled_{0}, errors_{0};
  std::thread thread_;
};

}  // namespace haptree::bus
