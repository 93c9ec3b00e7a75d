// Tests for haptree/bus/latency_histogram.hpp.
#include "haptree/bus/latency_histogram.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <random>
#include <vector>

namespace haptree::bus {
namespace {

// Bin edges are 2^(1/16) apart: a percentile is within that factor of the exact order statistic.
constexpr double kBinRatio = 1.0442737824274138;  // 2^(1/16)

TEST(LatencyHistogram, PercentilesMatchSortedSamplesWithinOneBin) {
  std::mt19937 g(2);
  std::lognormal_distribution<double> d(1.0, 1.2);  // µs: median e ≈ 2.7, long tail
  std::vector<double> xs;
  LatencyHistogram h;
  for (int i = 0; i < 100000; ++i) {
    const double x = d(g);
    xs.push_back(x);
    h.add(x);
  }
  std::sort(xs.begin(), xs.end());
  for (double q : {0.5, 0.9, 0.99, 0.999}) {
    const double exact = xs[static_cast<size_t>(q * xs.size()) - 1];
    const double est = h.percentile(q);
    EXPECT_GE(est, exact / kBinRatio) << q;
    EXPECT_LE(est, exact * kBinRatio) << q;
  }
  EXPECT_EQ(h.count(), 100000u);
  EXPECT_EQ(h.max(), xs.back());
  EXPECT_EQ(h.percentile(1.0), xs.back());
}

TEST(LatencyHistogram, EdgesAndReset) {
  LatencyHistogram h;
  EXPECT_EQ(h.percentile(0.5), 0.0);
  h.add(-1);
  h.add(std::numeric_limits<double>::quiet_NaN());
  EXPECT_EQ(h.invalid(), 2u);
  EXPECT_EQ(h.count(), 0u);
  h.add(0.0);
  h.add(1e12);  // beyond the last bin: counted there, max exact
  EXPECT_EQ(h.count(), 2u);
  EXPECT_EQ(h.max(), 1e12);
  EXPECT_EQ(h.percentile(1.0), 1e12);
  h.reset();
  EXPECT_EQ(h.count(), 0u);
  EXPECT_EQ(h.max(), 0.0);
}

}  // namespace
}  // namespace haptree::bus
