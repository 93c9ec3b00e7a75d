// Tests for haptree/bus/shm_channel.hpp: latest-value semantics within one process, across threads, across
// processes (fork), rejection of garbage, and the mirror onto an LCM bus.
#include "haptree/bus/shm_channel.hpp"

#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
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

  // A late reader gets nothing of what was written before it opened, then the newest message.
  ShmReader late(ch.name);
  lcmt_device_state m{};
  EXPECT_EQ(late.read_msg(m), ShmRead::kNothingNew);
  EXPECT_EQ(late.stale(), 1);
  ASSERT_TRUE(w.write_msg(state_with(42)));
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
  ShmReader r(ch.name);   // before the writer starts: a reader only takes messages of its own session
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {  // child: stream states, then answer one ping on the reply channel
    int code = 0;
    try {
      ShmReader ping(reply);
      ShmWriter w(ch.name);
      for (int64_t k = 1; k <= kWrites; ++k)
        if (!w.write_msg(state_with(k))) code = 2;
      lcmt_feedback f{};
      const auto deadline = std::chrono::steady_clock::now() + 10s;
      while (ping.read_msg(f) != ShmRead::kNew && std::chrono::steady_clock::now() < deadline) {}
      if (f.echo_device_seq != kWrites) code = 3;
      if (!w.write_msg(state_with(kWrites + 1))) code = 4;
      std::this_thread::sleep_for(300ms);   // a reader drops the messages of a writer that is gone
    } catch (...) {
      code = 5;
    }
    ::_exit(code);
  }
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

bool segment_exists(const std::string& channel) {
  return ::access(("/dev/shm" + shm_segment_name(channel)).c_str(), F_OK) == 0;
}

// Forks a writer that publishes one FEEDBACK of 2.5 N on `channel` and then dies by SIGKILL (no cleanup,
// as after `kill -9`). Returns once the child is reaped.
void write_feedback_and_die(const std::string& channel) {
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    ShmWriter w(channel);
    lcmt_feedback f{};
    stamp(f, 7);
    f.seq = 77;
    f.force_n[0] = 2.5;
    w.write_msg(f);
    ::raise(SIGKILL);
    ::_exit(3);
  }
  int st = 0;
  ASSERT_EQ(::waitpid(pid, &st, 0), pid);
  ASSERT_TRUE(WIFSIGNALED(st));
}

// A new reader (a new device_bridge) must not hand out the last FEEDBACK of a writer
// that was killed, and a reader that was already open must drop it as soon as the writer is gone.
TEST(ShmChannel, NewReaderNeverSeesADeadSessionsFeedback) {
  TempChannel ch("dead");
  write_feedback_and_die(ch.name);
  ShmReader r(ch.name);
  lcmt_feedback m{};
  const auto until = std::chrono::steady_clock::now() + 100ms;
  int64_t handed_out = 0;
  while (std::chrono::steady_clock::now() < until) {
    if (r.read_msg(m) == ShmRead::kNew) ++handed_out;
    std::this_thread::sleep_for(1ms);
  }
  EXPECT_EQ(handed_out, 0) << "read the dead writer's force " << m.force_n[0] << " N";
}

TEST(ShmChannel, OpenReaderDropsMessagesOfAWriterThatDied) {
  TempChannel ch("died");
  ShmReader r(ch.name);   // opened first: the message is of its own session, but its writer is dead
  write_feedback_and_die(ch.name);
  lcmt_feedback m{};
  EXPECT_EQ(r.read_msg(m), ShmRead::kNothingNew);
  EXPECT_EQ(r.writer_pid(), 0);
}

TEST(ShmChannel, MessagesOlderThanTheMaxAgeAreDropped) {
  TempChannel ch("age");
  ShmWriter w(ch.name);
  ShmReader r(ch.name, 0.010);   // the device_bridge's feedback timeout
  lcmt_feedback f{};
  stamp(f, 7);
  ASSERT_TRUE(w.write_msg(f));
  std::this_thread::sleep_for(30ms);   // 3x the max age: no scheduling delay makes it fresh
  lcmt_feedback m{};
  EXPECT_EQ(r.read_msg(m), ShmRead::kNothingNew);
  EXPECT_EQ(r.stale(), 1);
  ASSERT_TRUE(w.write_msg(f));
  EXPECT_EQ(r.read_msg(m), ShmRead::kNew);   // written just now
  EXPECT_EQ(r.writer_pid(), ::getpid());
}

// Segments do not outlive their writers.
TEST(ShmChannel, WriterUnlinksItsSegmentAndOneLiveWriterPerChannel) {
  TempChannel ch("unlink");
  {
    ShmWriter w(ch.name);
    EXPECT_TRUE(segment_exists(ch.name));
    try {
      ShmWriter second(ch.name);
      ADD_FAILURE() << "a second live writer was accepted";
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find("already has a live writer (pid " + std::to_string(::getpid())),
                std::string::npos)
          << e.what();
    }
  }
  EXPECT_FALSE(segment_exists(ch.name));
}

TEST(ShmChannel, DeadWritersSegmentIsReclaimed) {
  TempChannel a("reclaimA"), b("reclaimB"), c("reclaimC");
  write_feedback_and_die(a.name);
  ASSERT_TRUE(segment_exists(a.name));
  {
    ShmWriter w(a.name);   // a restarted writer takes the channel over
    EXPECT_TRUE(w.reclaimed());
  }
  // Any new writer reclaims every dead writer's segment of this user on the way ...
  write_feedback_and_die(b.name);
  ASSERT_TRUE(segment_exists(b.name));
  { ShmWriter w(c.name); }
  EXPECT_FALSE(segment_exists(b.name));
  // ... and so does reclaim_stale_shm_segments() (haptree_run at start).
  write_feedback_and_die(b.name);
  ASSERT_TRUE(segment_exists(b.name));
  const auto removed = reclaim_stale_shm_segments();
  bool found = false;
  for (const auto& n : removed) found |= n.find(shm_segment_name(b.name)) == 0;
  EXPECT_TRUE(found);
  EXPECT_FALSE(segment_exists(b.name));
}

TEST(ShmChannel, ReaderFollowsARestartedWriter) {
  TempChannel ch("follow");
  ShmReader r(ch.name);
  lcmt_device_state m{};
  {
    ShmWriter w(ch.name);
    ASSERT_TRUE(w.write_msg(state_with(1)));
    ASSERT_EQ(r.read_msg(m), ShmRead::kNew);
  }
  ShmWriter w2(ch.name);   // a new segment under the same name
  const auto until = std::chrono::steady_clock::now() + 2s;
  int64_t got = 0;
  while (got != 2 && std::chrono::steady_clock::now() < until) {
    ASSERT_TRUE(w2.write_msg(state_with(2)));
    if (r.read_msg(m) == ShmRead::kNew) got = m.seq;
    std::this_thread::sleep_for(1ms);
  }
  EXPECT_EQ(got, 2);
  EXPECT_EQ(r.reopened(), 2);
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
