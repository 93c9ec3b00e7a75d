// LatestValue<T>: a single-writer, single-reader mailbox that keeps only the newest value.
// Lock-free triple buffer with one atomic index: the writer never blocks and never waits for the reader,
// the reader always gets the newest *complete* value. No allocation after construction (T's own copy
// assignment permitting).
#pragma once

#include <atomic>
#include <cstdint>
#include <utility>

namespace haptree::bus {

template <class T>
class LatestValue {
 public:
  LatestValue() = default;
  explicit LatestValue(const T& initial) : slots_{Slot{initial, 0}, Slot{initial, 0}, Slot{initial, 0}} {}
  LatestValue(const LatestValue&) = delete;
  LatestValue& operator=(const LatestValue&) = delete;

  // ---- writer side (one thread) ----
  // Slot the writer owns; fill it, then publish(). Contents are whatever was there two publishes ago.
  T& back() noexcept { return slots_[back_].value; }
  // Makes back() visible to the reader as the newest value; returns its sequence number (1, 2, ...).
  uint64_t publish() noexcept {
    const uint64_t seq = ++write_seq_;
    slots_[back_].seq = seq;
    const uint32_t old = middle_.exchange(back_ | kFresh, std::memory_order_acq_rel);
    back_ = old & kIndexMask;
    return seq;
  }
  uint64_t write(const T& value) {
    back() = value;
    return publish();
  }
  // Number of values published so far (writer side).
  uint64_t published() const noexcept { return write_seq_; }

  // ---- reader side (one thread) ----
  // Takes the newest published value if there is one; returns true if front() changed.
  bool update() noexcept {
    if ((middle_.load(std::memory_order_relaxed) & kFresh) == 0) return false;
    const uint32_t old = middle_.exchange(front_, std::memory_order_acq_rel);
    front_ = old & kIndexMask;
    return true;
  }
  // Newest value taken by update(); default-constructed (seq 0) until the first publish.
  const T& front() const noexcept { return slots_[front_].value; }
  // Sequence number of front(): 0 = nothing received yet.
  uint64_t front_seq() const noexcept { return slots_[front_].seq; }
  // update() then copy front() into out; returns front_seq() (0 if nothing was ever published).
  uint64_t read(T& out) {
    update();
    out = front();
    return front_seq();
  }

 private:
  static constexpr uint32_t kFresh = 4u;  // set by the writer, cleared when the reader swaps
  static constexpr uint32_t kIndexMask = 3u;
  struct Slot {
    T value{};
    uint64_t seq = 0;
  };
  alignas(64) Slot slots_[3];
  alignas(64) std::atomic<uint32_t> middle_{1};  // index of the shared slot (+ kFresh)
  alignas(64) uint32_t back_ = 0;                // writer-owned
  uint64_t write_seq_ = 0;                       // writer-owned
  alignas(64) uint32_t front_ = 2;               // reader-owned
};

}  // namespace haptree::bus
