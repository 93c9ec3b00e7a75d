// OriginLock (haptree/bus/origin.hpp) against replays, found by tools/faults/chaos_soak: while the locked producer
// is down, a re-sent message of an earlier instance, or a recorded message stamped long ago, must not pass
// for a restarted producer; a real restart (a new id, a fresh stamp) still must.
#include <gtest/gtest.h>

#include <cmath>

#include "haptree/bus/origin.hpp"

namespace haptree::bus {
namespace {

constexpr int64_t kA = 11, kB = 22, kC = 33;

TEST(OriginLock, AReplayedInstanceNeverComesBackAfterItWasReplaced) {
  OriginLock lock(0.05);
  EXPECT_EQ(lock.check(kA, 0.00, 0.0), Origin::kFirst);
  EXPECT_EQ(lock.check(kA, 0.01, 0.0), Origin::kSame);
  EXPECT_EQ(lock.check(kB, 0.20, 0.0), Origin::kTakeover);   // A went silent: B is its restart
  // B is killed too; during the silence a recorded message of A is re-sent (fresh enough a stamp even):
  // before the fix this was a takeover back to A, i.e. a dead session's force at the device.
  EXPECT_EQ(lock.check(kA, 0.50, 0.0), Origin::kPrevious);
  EXPECT_EQ(lock.locked(), kB);
  EXPECT_EQ(lock.check(kC, 0.60, 0.0), Origin::kTakeover);   // the real restart
  EXPECT_EQ(lock.check(kB, 0.90, 0.0), Origin::kPrevious);
  EXPECT_EQ(lock.check(kA, 0.95, 0.0), Origin::kPrevious);
  EXPECT_EQ(lock.takeovers(), 2);
}

TEST(OriginLock, AStreamStartsOnlyWithAFreshMessage) {
  OriginLock lock(0.05, 1.0);
  EXPECT_EQ(lock.check(kA, 0.0, 3600.0), Origin::kTooOld);   // a recording: no first lock
  EXPECT_EQ(lock.check(kA, 0.0, NAN), Origin::kTooOld);
  EXPECT_EQ(lock.check(kA, 0.0, -5.0), Origin::kTooOld);     // stamped in the future by more than the bound
  EXPECT_EQ(lock.locked(), 0);
  EXPECT_EQ(lock.check(kA, 0.1, 0.002), Origin::kFirst);
  EXPECT_EQ(lock.check(kA, 0.2, 3600.0), Origin::kSame);     // the locked stream's own order is the seq's job
  EXPECT_EQ(lock.check(kB, 0.5, 3600.0), Origin::kTooOld);   // A silent, but B's message is an hour old
  EXPECT_EQ(lock.locked(), kA);
  EXPECT_EQ(lock.check(kB, 0.5, 0.003), Origin::kTakeover);
  EXPECT_EQ(lock.too_old(), 4);
  // The two-argument check (no stamp known) keeps the old rule.
  OriginLock plain(0.05);
  EXPECT_EQ(plain.check(kA, 0.0), Origin::kFirst);
  EXPECT_EQ(plain.check(kB, 0.01), Origin::kRefused);
}

TEST(OriginLock, RemembersTheLastSixteenReplacedInstances) {
  OriginLock lock(0.05);
  double t = 0;
  for (int64_t id = 1; id <= OriginLock::kRetired + 2; ++id, t += 1.0) EXPECT_TRUE(accepted(lock.check(id, t, 0.0)));
  // ids 1 .. kRetired+1 were replaced; the oldest one (1) dropped out of the ring.
  for (int64_t id = 2; id <= OriginLock::kRetired + 1; ++id) EXPECT_EQ(lock.check(id, t += 1.0, 0.0), Origin::kPrevious);
  EXPECT_EQ(lock.check(1, t += 1.0, 0.0), Origin::kTakeover);
}

}  // namespace
}  // namespace haptree::bus
