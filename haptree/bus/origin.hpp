// OriginLock: which producer a consumer of a latest-value channel listens to. Every haptree message
// carries the random `instance_id` of the component object that published it (wire.hpp). A consumer
// locks onto the first instance it hears; another instance is taken over only once the locked one has
// been silent for longer than `silence_s` (a restarted producer: by then the consumer's own watchdog has
// already taken the force away). While the locked instance is live, every other one is refused: a second
// writer, a foreign or replayed stream, a stray message. Header-only, noexcept, no allocation: it runs in
// handler threads and in the device loop. One lock per channel, used from one thread.
//
// Replays (found by tools/faults/chaos_soak): a recorded message of an earlier instance, re-sent while the locked
// producer is down (silent), would be taken over as a restart and render a dead session's force. So
//  * an instance once replaced never comes back (the last kRetired replaced ids are remembered: a real
//    restart always draws a new random id), and
//  * a stream can only start (first lock or takeover) with a message whose utime is within max_start_age_s
//    of this host's clock (the check() overload with the message's age): a recording is older. Hosts of one
//    session therefore need clocks within that bound (NTP; one host: the same clock).
#pragma once

#include <array>
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
  kTooOld,    // would start a stream, but its utime is more than max_start_age_s off this host's clock (a replay)
};

inline bool accepted(Origin o) noexcept { return o == Origin::kFirst || o == Origin::kSame || o == Origin::kTakeover; }

class OriginLock {
 public:
  static constexpr int kRetired = 16;
  static constexpr double kDefaultMaxStartAgeS = 1.0;
  explicit OriginLock(double silence_s = 0.05, double max_start_age_s = kDefaultMaxStartAgeS) noexcept
      : silence_s_(silence_s), max_start_age_s_(max_start_age_s) {}
  // As check() below, and a message that would start a stream (first lock, takeover) must be fresh:
  // message_age_s = this host's clock minus the message's utime, in seconds (NaN: too old).
  Origin check(int64_t instance_id, double now_s, double message_age_s) noexcept {
    if (instance_id != 0 && instance_id != locked_ && !(std::fabs(message_age_s) <= max_start_age_s_) &&
        !retired(instance_id)) {
      ++refused_;
      ++too_old_;
      return Origin::kTooOld;
    }
    return check(instance_id, now_s);
  }
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
    if (retired(instance_id)) {   // an instance once replaced (its late messages, or a replay of them)
      ++refused_;
      return Origin::kPrevious;
    }
    if (!(now_s - last_heard_s_ <= silence_s_)) {   // NaN times count as silent
      retired_[static_cast<size_t>(n_retired_++ % kRetired)] = locked_;
      previous_ = locked_;
      locked_ = instance_id;
      last_heard_s_ = now_s;
      ++takeovers_;
      return Origin::kTakeover;
    }
    ++refused_;
    last_refused_ = instance_id;
    return Origin::kRefused;
  }
  int64_t locked() const noexcept { return locked_; }
  int64_t previous() const noexcept { return previous_; }         // instance before the last takeover
  int64_t last_refused() const noexcept { return last_refused_; }
  int64_t refused() const noexcept { return refused_; }
  int64_t takeovers() const noexcept { return takeovers_; }
  int64_t too_old() const noexcept { return too_old_; }            // kTooOld verdicts
  bool retired(int64_t instance_id) const noexcept {
    for (int i = 0; i < kRetired && i < n_retired_; ++i)
      if (retired_[static_cast<size_t>(i)] == instance_id) return true;
    return false;
  }
  double last_heard_s() const noexcept { return last_heard_s_; }
  double silence_s() const noexcept { return silence_s_; }

 private:
  double silence_s_, max_start_age_s_;
  int64_t locked_ = 0, previous_ = 0, last_refused_ = 0;
  std::array<int64_t, kRetired> retired_{};
  int n_retired_ = 0;
  int64_t too_old_ = 0;
  double last_heard_s_ = -INFINITY;
  int64_t refused_ = 0, takeovers_ = 0;
};

}  // namespace haptree::bus
