// Tests for haptree/bus/latest_value.hpp.
#include "haptree/bus/latest_value.hpp"

#include <gtest/gtest.h>

#include <array>
#include <thread>

namespace haptree::bus {
namespace {

TEST(LatestValue, EmptyThenNewestOnly) {
  LatestValue<int> box;
  int v = -1;
  EXPECT_FALSE(box.update());
  EXPECT_EQ(box.read(v), 0u);
  box.write(1);
  box.write(2);
  box.write(3);
  EXPECT_EQ(box.published(), 3u);
  EXPECT_EQ(box.read(v), 3u);
  EXPECT_EQ(v, 3);
  EXPECT_FALSE(box.update());  // nothing newer: front stays
  EXPECT_EQ(box.front(), 3);
  box.back() = 7;
  EXPECT_EQ(box.publish(), 4u);
  EXPECT_TRUE(box.update());
  EXPECT_EQ(box.front(), 7);
  EXPECT_EQ(box.front_seq(), 4u);
}

// A value whose every word carries the same number: a torn read would mix two numbers.
struct Block {
  std::array<uint64_t, 64> w{};
};

TEST(LatestValue, ConcurrentWriterReaderNeverTears) {
  LatestValue<Block> box;
  constexpr uint64_t kWrites = 300000;
  std::thread writer([&] {
    for (uint64_t k = 1; k <= kWrites; ++k) {
      Block& b = box.back();
      for (auto& x : b.w) x = k;
      ASSERT_EQ(box.publish(), k);
    }
  });
  uint64_t last_seq = 0, reads = 0, torn = 0, mismatched = 0, backwards = 0;
  while (last_seq < kWrites) {
    if (!box.update()) continue;
    const Block& b = box.front();
    const uint64_t seq = box.front_seq();
    for (auto x : b.w) torn += (x != b.w[0]);
    mismatched += (b.w[0] != seq);  // value k was published with seq k
    backwards += (seq <= last_seq);
    last_seq = seq;
    ++reads;
  }
  writer.join();
  EXPECT_EQ(torn, 0u);
  EXPECT_EQ(mismatched, 0u);
  EXPECT_EQ(backwards, 0u);
  EXPECT_EQ(last_seq, kWrites);
  EXPECT_GT(reads, 0u);
}

}  // namespace
}  // namespace haptree::bus
