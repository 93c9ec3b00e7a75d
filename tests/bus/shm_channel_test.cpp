// Tests for haptree/bus/shm_channel.hpp: latest-value semantics within one process, across threads, across
// processes (fork), rejection of garbage, and the mirror onto an LCM bus.
#include "haptree/bus/shm_channel.hpp"

#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <random>
#include <thread>

#include "haptree/bus/bus.hpp"

namespace haptree::bus {
namespace {

using namespace std::chrono_literals;

// A channel name unique to this process and test; the segment is removed at the end.
struct TempChannel {
  std::string name;
  explicit TempChannel(const std::string& tag) : name("HAPTREE_TEST_" + tag + "_" + std::to_string(::getpid())) {
    ShmChannel::remove(name);
  }
  ~TempChannel() { ShmChannel::remove(name); }
};

lcmt_device_state state_with(int64_t k) {
  lcmt_device_state m{};
  stamp(m, 7, k);
  m.seq = k;
  for (auto& x : m.position_m) x = static_cast<double>(k);
  for (auto& x : m.orientation) x = static_cast<double>(k);
  for (auto& x : m.linear_velocity_mps) x = static_cast<double>(k);
  m.buttons = static_cast<int32_t>(k);
  return m;
}
// Every field carries the same k: a mix of two writes would show.
bool consistent(const lcmt_device_state& m) {
  const double k = static_cast<double>(m.seq);
  bool ok = m.utime == m.seq && m.buttons == static_cast<int32_t>(m.seq);
  for (auto x : m.position_m) ok = ok && x == k;
  for (auto x : m.orientation) ok = ok && x == k;
  for (auto x : m.linear_velocity_mps) ok = ok && x == k;
  return ok;
}

TEST(ShmChannel, LatestValueWithinOneProcess) {
  TempChannel ch("one");
  ShmWriter w(ch.name);
  ShmReader r(ch.name);
  std::vector<uint8_t> out(kShmMaxMessageBytes);
  size_t n = 0;
  EXPECT_EQ(r.read(out.data(), out.size(), &n), 0u);  // empty channel
  const std::string a = "first", b = "second", c = "third";
  ASSERT_TRUE(w.write(a.data(), a.size()));
  ASSERT_EQ(r.read(out.data(), out.size(), &n), 1u);
  EXPECT_EQ(std::string(out.begin(), out.begin() + n), a);
  EXPECT_EQ(r.read(out.data(), out.size(), &n), 0u);  // nothing new
  ASSERT_TRUE(w.write(b.data(), b.size()));
  ASSERT_TRUE(w.write(c.data(), c.size()));
  ASSERT_EQ(r.read(out.data(), out.size(), &n), 3u);  // only the newest
  EXPECT_EQ(std::string(out.begin(), out.begin() + n), c);
  EXPECT_EQ(r.skipped(), 1);
  std::vector<uint8_t> big(kShmMaxMessageBytes + 1, 1);
  EXPECT_FALSE(w.write(big.data(), big.size()));
  EXPECT_TRUE(w.write(big.data(), kShmMaxMessageBytes));  // exactly the maximum fits
  ASSERT_EQ(r.read(out.data(), out.size(), &n), 4u);
  EXPECT_EQ(n, kShmMaxMessageBytes);

  // A second writer (e.g. a restarted process) continues the index; a late reader sees the newest.
  ShmWriter w2(ch.name);
  ASSERT_TRUE(w2.write_msg(state_with(42)));
  ShmReader late(ch.name);
  lcmt_device_state m{};
  ASSERT_EQ(late.read_msg(m), ShmRead::kNew);
  EXPECT_EQ(late.last_index(), 5u);
  EXPECT_EQ(m.seq, 42);
  EXPECT_TRUE(consistent(m));
}

TEST(ShmChannel, GarbageIsRejectedAndCounted) {
  TempChannel ch("garbage");
  ShmWriter w(ch.name);
  ShmReader r(ch.name);
  std::mt19937 g(3);
  lcmt_feedback m{};
  for (int k = 0; k < 500; ++k) {
    std::vector<uint8_t> b(1 + g() % 2000);
    for (auto& x : b) x = static_cast<uint8_t>(g());
    ASSERT_TRUE(w.write(b.data(), b.size()));
    EXPECT_EQ(r.read_msg(m), ShmRead::kRejected);
  }
  EXPECT_EQ(r.rejected(), 500);
  lcmt_feedback good{};
  stamp(good, 7);
  good.seq = 9;
  ASSERT_TRUE(w.write_msg(good));
  ASSERT_EQ(r.read_msg(m), ShmRead::kNew);
  EXPECT_EQ(m.seq, 9);
}

TEST(ShmChannel, ConcurrentThreadsNeverSeeATornMessage) {
  TempChannel ch("threads");
  ShmWriter w(ch.name);
  ShmReader r(ch.name);
  constexpr int64_t kWrites = 200000;
  std::thread writer([&] {
    for (int64_t k = 1; k <= kWrites; ++k) ASSERT_TRUE(w.write_msg(state_with(k)));
  });
  lcmt_device_state m{};
  int64_t last = 0, reads = 0, bad = 0, backwards = 0;
  while (last < kWrites) {
    const ShmRead res = r.read_msg(m);
    if (res == ShmRead::kNothingNew) continue;
    ASSERT_EQ(res, ShmRead::kNew);
    bad += !consistent(m);
    backwards += m.seq <= last;
    last = m.seq;
    ++reads;
  }
  writer.join();
  EXPECT_EQ(bad, 0);
  EXPECT_EQ(backwards, 0);
  EXPECT_EQ(r.rejected(), 0);
  EXPECT_EQ(last, kWrites);
  EXPECT_GT(reads, 0);
}

TEST(ShmChannel, BetweenTwoProcesses) {
  TempChannel ch("fork");
  const std::string reply = ch.name + "_R";
  ShmChannel::remove(reply);
  constexpr int64_t kWrites = 100000;
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {  // child: stream states, then answer one ping on the reply channel
    int code = 0;
    try {
      ShmWriter w(ch.name);
      for (int64_t k = 1; k <= kWrites; ++k)
        if (!w.write_msg(state_with(k))) code = 2;
      ShmReader ping(reply);
      lcmt_feedback f{};
      const auto deadline = std::chrono::steady_clock::now() + 10s;
      while (ping.read_msg(f) != ShmRead::kNew && std::chrono::steady_clock::now() < deadline) {}
      if (f.echo_device_seq != kWrites) code = 3;
      if (!w.write_msg(state_with(kWrites + 1))) code = 4;
    } catch (...) {
      code = 5;
    }
    ::_exit(code);
  }
  ShmReader r(ch.name);
  ShmWriter back(reply);
  lcmt_device_state m{};
  int64_t last = 0, bad = 0, backwards = 0;
  auto deadline = std::chrono::steady_clock::now() + 20s;
  while (last < kWrites && std::chrono::steady_clock::now() < deadline) {
    if (r.read_msg(m) != ShmRead::kNew) continue;
    bad += !consistent(m);
    backwards += m.seq <= last;
    last = m.seq;
  }
  EXPECT_EQ(last, kWrites);
  lcmt_feedback f{};
  stamp(f, 7);
  f.echo_device_seq = last;
  ASSERT_TRUE(back.write_msg(f));
  deadline = std::chrono::steady_clock::now() + 10s;
  while (last == kWrites && std::chrono::steady_clock::now() < deadline)
    if (r.read_msg(m) == ShmRead::kNew) last = m.seq;
  EXPECT_EQ(last, kWrites + 1);
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
  EXPECT_EQ(bad, 0);
  EXPECT_EQ(backwards, 0);
  EXPECT_EQ(r.rejected(), 0);
  ShmChannel::remove(reply);
}

TEST(ShmMirror, RepublishesNewestOntoTheBus) {
  TempChannel ch("mirror");
  Bus bus("memq://");
  LatestValue<lcmt_device_state> box;
  auto& sub = bus.subscribe_latest<lcmt_device_state>("HAPTREE_DEVICE_STATE_0", box);
  ShmWriter w(ch.name);
  ShmMirror mirror(bus, ch.name, "HAPTREE_DEVICE_STATE_0", 200.0);
  lcmt_device_state got{};
  const auto deadline = std::chrono::steady_clock::now() + 10s;
  int64_t k = 0;
  // The writer runs much faster than the mirror; the bus sees a thinned stream of whole messages.
  while (box.read(got) == 0 || got.seq < 1000) {
    ASSERT_LT(std::chrono::steady_clock::now(), deadline);
    ASSERT_TRUE(w.write_msg(state_with(++k)));
    std::this_thread::sleep_for(50us);
    bus.handle_timeout(0);
  }
  mirror.stop();
  EXPECT_TRUE(consistent(got));
  EXPECT_GT(mirror.mirrored(), 0);
  EXPECT_LT(mirror.mirrored(), k);  // thinned
  EXPECT_EQ(sub.stats().rejected(), 0);
}

}  // namespace
}  // namespace haptree::bus
