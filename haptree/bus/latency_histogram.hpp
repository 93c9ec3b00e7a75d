// LatencyHistogram: fixed, log-spaced bins (16 per octave, 3 ns .. ~50 s) for the p50/p99 figures of
// lcmt_process_stats. add() is noexcept, allocation-free and O(1), so it can sit in a 10 kHz loop;
// percentiles are read once a second (bin upper edges: within 4.4 % of the true value).
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <limits>

namespace haptree::bus {

class LatencyHistogram {
 public:
  static constexpr int kBinsPerOctave = 16;
  static constexpr double kMinUs = 1.0 / 256;  // 3.9 ns
  static constexpr int kOctaves = 34;           // up to kMinUs * 2^34 µs ≈ 67 s
  static constexpr int kBins = kBinsPerOctave * kOctaves;

  void add(double us) noexcept {
    if (!(us >= 0)) {  // NaN or negative: not a latency
      ++invalid_;
      return;
    }
    ++count_;
    sum_ += us;
    if (us > max_) max_ = us;
    ++bins_[static_cast<size_t>(bin_of(us))];
  }
  // Smallest bin upper edge below which a fraction q of the samples lie (q in [0, 1]); 0 if empty.
  double percentile(double q) const noexcept {
    if (count_ == 0) return 0;
    const double want = q * static_cast<double>(count_);
    uint64_t seen = 0;
    for (int b = 0; b < kBins; ++b) {
      seen += bins_[static_cast<size_t>(b)];
      if (static_cast<double>(seen) >= want && seen > 0)
        return b == kBins - 1 ? max_ : std::fmin(upper_edge(b), max_);  // last bin is open-ended
    }
    return max_;
  }
  uint64_t count() const noexcept { return count_; }
  uint64_t invalid() const noexcept { return invalid_; }
  double max() const noexcept { return max_; }
  double mean() const noexcept { return count_ ? sum_ / static_cast<double>(count_) : 0.0; }
  void reset() noexcept { *this = LatencyHistogram{}; }

  static int bin_of(double us) noexcept {
    if (us <= kMinUs) return 0;
    const int b = static_cast<int>(std::log2(us / kMinUs) * kBinsPerOctave);
    return b >= kBins ? kBins - 1 : b;
  }
  static double upper_edge(int b) noexcept { return kMinUs * std::exp2(static_cast<double>(b + 1) / kBinsPerOctave); }

 private:
  std::array<uint64_t, kBins> bins_{};
  uint64_t count_ = 0, invalid_ = 0;
  double sum_ = 0, max_ = 0;
};

}  // namespace haptree::bus
