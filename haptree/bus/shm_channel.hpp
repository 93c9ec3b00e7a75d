// Same-host shared-memory channel with latest-value semantics, carrying the same LCM-encoded bytes as
// the bus. One POSIX shared-memory segment per channel ("/haptree.<CHANNEL>"), four slots, each slot a
// seqlock: the writer never blocks or waits; a reader gets the newest complete message or nothing.
// One writer per channel; any number of readers, in any process. Messages up to kShmMaxMessageBytes.
// An all-zero segment is a valid empty channel, so whichever side opens first creates it.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
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

// Maps (creating if needed) the segment of a channel. Base of ShmWriter / ShmReader. Throws
// std::runtime_error with the segment name and the system's reason when it cannot.
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
  std::string channel_, name_;
  detail::ShmSegment* seg_ = nullptr;
  std::unique_ptr<Authenticator> auth_;
  size_t trailer_bytes() const noexcept { return auth_ ? kAuthTrailerBytes : 0; }
  size_t seal(uint8_t* msg, size_t size) noexcept { return auth_ ? auth_->seal(channel_, msg, size) : size; }
};

class ShmWriter : public ShmChannel {
 public:
  explicit ShmWriter(const std::string& channel);
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

 private:
  uint8_t* begin_write() noexcept;
  void end_write(uint32_t size) noexcept;
  uint64_t next_ = 0;
  uint64_t written_ = 0;
  void* slot_ = nullptr;
  uint64_t slot_seq_ = 0;
};

enum class ShmRead { kNothingNew, kNew, kRejected };

class ShmReader : public ShmChannel {
 public:
  explicit ShmReader(const std::string& channel);
  // Copies the newest message if it is newer than the last one read: returns its index (1, 2, ...) and
  // sets *size; returns 0 if nothing new (or the writer lapped four slots during every retry).
  // cap must be >= kShmMaxMessageBytes to be sure to fit.
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
  // Index of the newest message written so far (without reading it).
  uint64_t latest_index() const noexcept;

 private:
  std::vector<uint8_t> buf_;
  uint64_t last_ = 0;
  int64_t rejected_ = 0, skipped_ = 0, retries_ = 0;
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
