// Same-host shared-memory channel with latest-value semantics, carrying the same LCM-encoded bytes as
// the bus. One POSIX shared-memory segment per channel ("/haptree.<CHANNEL>.<uid>"), four slots, each
// slot a seqlock: the writer never blocks or waits; a reader gets the newest complete message or nothing.
// One writer per channel; any number of readers, in any process. Messages up to kShmMaxMessageBytes.
//
// Age and origin (a latest-value message outlives its writer, so it must say who wrote it and when):
//  * the segment header records its writer: pid, the process's start time (guards pid reuse), a random
//    instance id and the writer's start (CLOCK_MONOTONIC, the same clock in every process of a host);
//  * every slot records the instance id and the monotonic time of its write;
//  * a reader hands out a message only if it was written by the segment's current writer, that writer is
//    alive (checked every few ms), it was written after the reader opened, and it is no older than the
//    reader's max age. Everything else is dropped and counted (stale()).
// Lifetime: only the writer creates the segment, and unlinks it when it closes (normal end, SIGTERM/SIGINT
// handled by the process). A writer that finds a segment of a dead or closed writer reclaims it (unlinks it
// and starts a new one); a live one is refused (one writer per channel). reclaim_stale_shm_segments() also
// removes every leftover haptree segment of this user whose writer is gone (kill -9, power loss). Readers
// never create: they open the segment when it appears and re-open it when its writer is replaced.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "haptree/bus/auth.hpp"
#include "haptree/bus/wire.hpp"

namespace haptree::bus {

class Bus;

constexpr size_t kShmMaxMessageBytes = 65536;

namespace detail {
struct ShmSegment;
}

// Segment name for a channel: "/haptree." + channel (+ "." + uid, so users on one host do not collide).
std::string shm_segment_name(const std::string& channel);

// CLOCK_MONOTONIC in nanoseconds: the time base of the slots' write times.
int64_t shm_now_ns() noexcept;

// Unlinks every /dev/shm segment of this user named "haptree.*" whose writer is dead or closed, or whose
// layout is an older build's and which is over an hour old (a segment still being created, younger than 5 s,
// is left alone). Returns the names removed, each with the reason. Called by every ShmWriter and by
// haptree_run at start.
std::vector<std::string> reclaim_stale_shm_segments();

// A mapped segment of a channel. Base of ShmWriter / ShmReader. Throws std::runtime_error with the
// segment name and the system's reason when it cannot map it.
class ShmChannel {
 public:
  explicit ShmChannel(const std::string& channel);
  ~ShmChannel();
  ShmChannel(const ShmChannel&) = delete;
  ShmChannel& operator=(const ShmChannel&) = delete;
  const std::string& channel() const noexcept { return channel_; }
  const std::string& segment_name() const noexcept { return name_; }
  // Removes the segment name (mapped segments stay valid until unmapped). False if it did not exist.
  static bool remove(const std::string& channel);
  // Keyed session (auth.hpp): writes are sealed, reads verified and stripped (a rejected message counts
  // in ShmReader::rejected()). Default: the process key. nullptr: unkeyed.
  void set_session_key(std::shared_ptr<const SessionKey> key);
  const Authenticator* authenticator() const noexcept { return auth_.get(); }

 protected:
  void unmap() noexcept;
  std::string channel_, name_;
  detail::ShmSegment* seg_ = nullptr;
  uint64_t inode_ = 0;   // of the mapped segment: tells a successor's segment of the same name apart
  std::unique_ptr<Authenticator> auth_;
  size_t trailer_bytes() const noexcept { return auth_ ? kAuthTrailerBytes : 0; }
  size_t seal(uint8_t* msg, size_t size) noexcept { return auth_ ? auth_->seal(channel_, msg, size) : size; }
};

// Unlinks the segments of this process's live writers; async-signal-safe (the processes' SIGTERM/SIGINT
// handler calls it, so a child that cannot stop promptly still leaves no segment behind).
void unlink_own_shm_segments() noexcept;

class ShmWriter : public ShmChannel {
 public:
  // Creates the segment (reclaiming one whose writer is dead or closed). Throws std::runtime_error if a
  // live process already writes this channel.
  explicit ShmWriter(const std::string& channel);
  // Marks the segment closed and unlinks it (if the name still is this writer's segment).
  ~ShmWriter();
  // Publishes bytes as the newest message. False (and nothing written) if size > kShmMaxMessageBytes.
  bool write(const void* data, size_t size) noexcept;
  // Encodes msg directly into the shared slot (no allocation, no copy). False if encoding fails.
  template <class T>
  bool write_msg(const T& msg) noexcept {
    const int n = msg.getEncodedSize();
    if (n < 0 || static_cast<size_t>(n) + trailer_bytes() > kShmMaxMessageBytes) return false;
    uint8_t* slot = begin_write();
    const bool ok = msg.encode(slot, 0, n) == n;
    end_write(ok ? static_cast<uint32_t>(seal(slot, static_cast<size_t>(n))) : 0u);
    return ok;
  }
  uint64_t written() const noexcept { return written_; }
  uint64_t instance_id() const noexcept { return instance_; }
  // True if the constructor found a segment of a dead/closed writer (or another layout) and replaced it.
  bool reclaimed() const noexcept { return reclaimed_; }

 private:
  uint8_t* begin_write() noexcept;
  void end_write(uint32_t size) noexcept;
  uint64_t next_ = 1;
  uint64_t written_ = 0;
  uint64_t instance_ = 0;
  bool reclaimed_ = false;
  void* slot_ = nullptr;
  uint64_t slot_seq_ = 0;
};

enum class ShmRead { kNothingNew, kNew, kRejected };

class ShmReader : public ShmChannel {
 public:
  // max_age_s: a message older than this (write time to read time) is never handed out; set it to the
  // consumer's staleness timeout. The segment need not exist yet.
  explicit ShmReader(const std::string& channel,
                     double max_age_s = std::numeric_limits<double>::infinity());
  // Copies the newest message if it is newer than the last one read and passes the age and origin checks
  // (see the file comment): returns its index (1, 2, ...) and sets *size; returns 0 if nothing new (or
  // the writer lapped four slots during every retry). cap must be >= kShmMaxMessageBytes to be sure to fit.
  uint64_t read(void* out, size_t cap, size_t* size) noexcept;
  // read() + decode_checked into msg (reused). kRejected counts in rejected().
  template <class T>
  ShmRead read_msg(T& msg) noexcept {
    size_t n = 0;
    if (read(buf_.data(), buf_.size(), &n) == 0) return ShmRead::kNothingNew;
    if (decode_checked(buf_.data(), n, msg) != DecodeResult::kOk) {
      ++rejected_;
      return ShmRead::kRejected;
    }
    return ShmRead::kNew;
  }
  uint64_t last_index() const noexcept { return last_; }
  int64_t rejected() const noexcept { return rejected_; }
  int64_t skipped() const noexcept { return skipped_; }    // messages overwritten before this reader saw them
  int64_t retries() const noexcept { return retries_; }    // seqlock retries (writer was mid-write)
  int64_t stale() const noexcept { return stale_; }        // dropped: too old, before this reader, dead writer
  int64_t reopened() const noexcept { return reopened_; }  // segments (re)opened (a new writer's segment)
  // Index of the newest message written so far (without reading it); 0 if the segment is not there.
  uint64_t latest_index() const noexcept;
  // Pid of the segment's current live writer, 0 if none.
  int64_t writer_pid() noexcept;
  void set_max_age_s(double s) noexcept;

 private:
  bool try_open() noexcept;
  bool writer_ok(int64_t now_ns) noexcept;
  std::vector<uint8_t> buf_;
  int64_t max_age_ns_;
  int64_t opened_ns_;            // this reader's start: older messages belong to another session
  int64_t next_open_ns_ = 0;     // rate limit of (re)open attempts
  uint64_t checked_instance_ = 0;
  int64_t checked_ns_ = 0;
  int64_t full_checked_ns_ = 0;   // last /proc start-time check (writer_ok)
  bool writer_alive_ = false;
  uint64_t last_ = 0;
  int64_t rejected_ = 0, skipped_ = 0, retries_ = 0, stale_ = 0, reopened_ = 0;
};

// Republishes the newest message of a shared-memory channel onto an LCM bus at most rate_hz times per
// second, from its own thread, so lcm-logger records the shared-memory link. Only new messages are sent.
class ShmMirror {
 public:
  ShmMirror(Bus& bus, const std::string& shm_channel, const std::string& lcm_channel, double rate_hz);
  ~ShmMirror();
  ShmMirror(const ShmMirror&) = delete;
  ShmMirror& operator=(const ShmMirror&) = delete;
  void stop();
  int64_t mirrored() const noexcept { return mirrored_.load(); }

 private:
  Bus& bus_;
  ShmReader reader_;
  std::string lcm_channel_;
  double period_s_;
  std::atomic<bool> stop_{false};
  std::atomic<int64_t> mirrored_{0};
  std::thread thread_;
};

}  // namespace haptree::bus
