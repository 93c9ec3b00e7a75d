// Pacing of the processes' loops: sleeps that SIGTERM (the loop's stop flag) can cut short.
#pragma once

#include <algorithm>
#include <atomic>
#include <chrono>
#include <thread>

namespace haptree::bus {

// Sleeps until `deadline` in slices of at most 20 ms, returning early once `stop` is set, so SIGTERM stops
// a paced loop within 20 ms whatever its period.
template <class Clock, class Duration>
void sleep_until_or_stop(const std::chrono::time_point<Clock, Duration>& deadline, const std::atomic<bool>& stop) {
  constexpr auto kSlice = std::chrono::milliseconds(20);
  while (!stop.load(std::memory_order_relaxed)) {
    const auto now = Clock::now();
    if (now >= deadline) return;
    std::this_thread::sleep_until(std::min<std::chrono::time_point<Clock, Duration>>(
        deadline, std::chrono::time_point_cast<Duration>(now + kSlice)));
  }
}

}  // namespace haptree::bus
