// OriginLock: which producer a consumer of a latest-value channel listens to. Every haptree message
// carries the random `instance_id` of the component object that published it (wire.hpp). A consumer
// locks onto the first instance it hears; another instance is taken over only once the locked one has
// been silent for longer than `silence_s` (a restarted producer: by then the consumer's own watchdog has
// already taken the force away). While the locked instance is live, every other one is refused: a second
// writer, a foreign or replayed stream, a stray message. Header-only, noexcept, no allocation: it runs in
// handler threads and in the device loop. One lock per channel, used from one thread.
#pragma once

#include <cmath>
#include <cstdint>

namespace haptree::bus {

enum class Origin {
  kFirst,     // nothing was locked: now locked onto this instance
  kSame,      // the locked instance
  kTakeover,  // another instance after the locked one went silent: now locked onto it (a restart)
  kRefused,   // another instance while the locked one is live
  kPrevious,  // the instance before the last takeover while the new one is live (its late messages)
  kInvalid,   // instance id 0 (an unstamped message, or one from a build without instance ids)
};

inline bool accepted(Origin o) noexcept { return o == Origin::kFirst || o == Origin::kSame || o == Origin::kTakeover; }

class OriginLock {
 public:
  explicit OriginLock(double silence_s = 0.05) noexcept : silence_s_(silence_s) {}
  // Verdict for a message from `instance_id` arriving at now_s (any monotonic clock, seconds). Accepted
  // verdicts count as "heard" from the locked instance; refused ones are counted in refused().
  Origin check(int64_t instance_id, double now_s) noexcept {
    if (instance_id == 0) {
      ++refused_;
      return Origin::kInvalid;
    }
    if (locked_ == 0) {
      locked_ = instance_id;
      last_heard_s_ = now_s;
      return Origin::kFirst;
    }
    if (instance_id == locked_) {
      if (now_s > last_heard_s_) last_heard_s_ = now_s;
      return Origin::kSame;
    }
    if (!(now_s - last_heard_s_ <= silence_s_)) {   // NaN times count as silent
      previous_ = locked_;
      locked_ = instance_id;
      last_heard_s_ = now_s;
      ++takeovers_;
      return Origin::kTakeover;
    }
    ++refused_;
    if (instance_id == previous_) return Origin::kPrevious;
    last_refused_ = instance_id;
    return Origin::kRefused;
  }
  int64_t locked() const noexcept { return locked_; }
  int64_t previous() const noexcept { return previous_; }         // instance before the last takeover
  int64_t last_refused() const noexcept { return last_refused_; }
  int64_t refused() const noexcept { return refused_; }
  int64_t takeovers() const noexcept { return takeovers_; }
  double last_heard_s() const noexcept { return last_heard_s_; }
  double silence_s() const noexcept { return silence_s_; }

 private:
  double silence_s_;
  int64_t locked_ = 0, previous_ = 0, last_refused_ = 0;
  double last_heard_s_ = -INFINITY;
  int64_t refused_ = 0, takeovers_ = 0;
};

}  // namespace haptree::bus
