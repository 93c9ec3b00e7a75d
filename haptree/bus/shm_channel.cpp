#include "haptree/bus/shm_channel.hpp"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <stdexcept>

#include "haptree/bus/bus.hpp"

namespace haptree::bus {
namespace detail {

constexpr uint64_t kShmMagic = 0x6861707472656531ull;  // "haptree1"
constexpr int kShmSlots = 4;

struct alignas(64) ShmSlot {
  std::atomic<uint64_t> seq;    // odd while the writer is inside
  std::atomic<uint64_t> index;  // message index held (1, 2, ...)
  std::atomic<uint32_t> size;
  alignas(64) uint8_t data[kShmMaxMessageBytes];
};

struct ShmSegment {
  std::atomic<uint64_t> magic;
  std::atomic<uint64_t> max_message_bytes;
  alignas(64) std::atomic<uint64_t> latest;  // index of the newest complete message; 0 = none
  alignas(64) ShmSlot slots[kShmSlots];
};
static_assert(std::atomic<uint64_t>::is_always_lock_free, "shared-memory channel needs lock-free atomics");

}  // namespace detail

using detail::ShmSegment;

std::string shm_segment_name(const std::string& channel) {
  return "/haptree." + channel + "." + std::to_string(::getuid());
}

ShmChannel::ShmChannel(const std::string& channel) : channel_(channel), name_(shm_segment_name(channel)) {
  const int fd = ::shm_open(name_.c_str(), O_RDWR | O_CREAT, 0600);
  if (fd < 0)
    throw std::runtime_error("shared-memory channel " + channel + ": shm_open(" + name_ + ") failed: " +
                             std::strerror(errno) + " (is /dev/shm mounted and writable?)");
  struct stat st {};
  const size_t bytes = sizeof(ShmSegment);
  if (::fstat(fd, &st) != 0 || (static_cast<size_t>(st.st_size) < bytes && ::ftruncate(fd, bytes) != 0)) {
    const int e = errno;
    ::close(fd);
    throw std::runtime_error("shared-memory channel " + channel + ": cannot size " + name_ + " to " +
                             std::to_string(bytes) + " bytes: " + std::strerror(e));
  }
  void* p = ::mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  const int e = errno;
  ::close(fd);
  if (p == MAP_FAILED)
    throw std::runtime_error("shared-memory channel " + channel + ": mmap of " + name_ +
                             " failed: " + std::strerror(e));
  seg_ = static_cast<ShmSegment*>(p);
  uint64_t expected = 0;
  if (!seg_->magic.compare_exchange_strong(expected, detail::kShmMagic) && expected != detail::kShmMagic) {
    ::munmap(p, bytes);
    seg_ = nullptr;
    throw std::runtime_error("shared-memory channel " + channel + ": " + name_ +
                             " exists but was made by another program or layout; remove /dev/shm" + name_);
  }
  seg_->max_message_bytes.store(kShmMaxMessageBytes);
  set_session_key(process_session_key());   // keyed session (auth.hpp): nullptr = none
}

void ShmChannel::set_session_key(std::shared_ptr<const SessionKey> key) {
  auth_ = key ? std::make_unique<Authenticator>(std::move(key)) : nullptr;
}

ShmChannel::~ShmChannel() {
  if (seg_) ::munmap(seg_, sizeof(ShmSegment));
}

bool ShmChannel::remove(const std::string& channel) {
  return ::shm_unlink(shm_segment_name(channel).c_str()) == 0;
}

ShmWriter::ShmWriter(const std::string& channel) : ShmChannel(channel) {
  next_ = seg_->latest.load(std::memory_order_acquire) + 1;  // continue the index of a previous writer
}

uint8_t* ShmWriter::begin_write() noexcept {
  auto& s = seg_->slots[next_ % detail::kShmSlots];
  uint64_t q = s.seq.load(std::memory_order_relaxed);
  if (q & 1) ++q;  // a previous writer died inside this slot
  slot_seq_ = q;
  s.seq.store(q + 1, std::memory_order_relaxed);
  std::atomic_thread_fence(std::memory_order_release);
  slot_ = &s;
  return s.data;
}

void ShmWriter::end_write(uint32_t size) noexcept {
  auto& s = *static_cast<detail::ShmSlot*>(slot_);
  if (size == 0) {  // failed encode: leave the slot's old content marked consistent but do not publish
    s.seq.store(slot_seq_ + 2, std::memory_order_release);
    s.index.store(0, std::memory_order_relaxed);
    return;
  }
  s.size.store(size, std::memory_order_relaxed);
  s.index.store(next_, std::memory_order_relaxed);
  s.seq.store(slot_seq_ + 2, std::memory_order_release);
  seg_->latest.store(next_, std::memory_order_release);
  ++next_;
  ++written_;
}

bool ShmWriter::write(const void* data, size_t size) noexcept {
  if (size == 0 || size + trailer_bytes() > kShmMaxMessageBytes) return false;
  uint8_t* slot = begin_write();
  std::memcpy(slot, data, size);
  end_write(static_cast<uint32_t>(seal(slot, size)));
  return true;
}

ShmReader::ShmReader(const std::string& channel) : ShmChannel(channel), buf_(kShmMaxMessageBytes) {}

uint64_t ShmReader::latest_index() const noexcept { return seg_->latest.load(std::memory_order_acquire); }

uint64_t ShmReader::read(void* out, size_t cap, size_t* size) noexcept {
  for (int attempt = 0; attempt < 16; ++attempt) {
    const uint64_t n = seg_->latest.load(std::memory_order_acquire);
    if (n == 0 || n == last_) return 0;
    auto& s = seg_->slots[n % detail::kShmSlots];
    const uint64_t q1 = s.seq.load(std::memory_order_acquire);
    if (q1 & 1) {
      ++retries_;
      continue;
    }
    const uint64_t idx = s.index.load(std::memory_order_relaxed);
    const uint32_t sz = s.size.load(std::memory_order_relaxed);
    if (sz == 0 || sz > kShmMaxMessageBytes || sz > cap) {
      ++retries_;
      continue;
    }
    std::memcpy(out, s.data, sz);
    std::atomic_thread_fence(std::memory_order_acquire);
    if (s.seq.load(std::memory_order_relaxed) != q1 || idx < n) {
      ++retries_;
      continue;
    }
    if (last_ != 0 && idx > last_ + 1) skipped_ += static_cast<int64_t>(idx - last_ - 1);
    last_ = idx;
    size_t payload = sz;
    if (auth_ && auth_->open(channel_, out, sz, &payload) != AuthVerdict::kOk) {   // keyed: verify, strip
      ++rejected_;
      return 0;
    }
    *size = payload;
    return idx;
  }
  return 0;
}

ShmMirror::ShmMirror(Bus& bus, const std::string& shm_channel, const std::string& lcm_channel,
                     double rate_hz)
    : bus_(bus), reader_(shm_channel), lcm_channel_(lcm_channel), period_s_(1.0 / rate_hz) {
  if (!(rate_hz > 0)) throw std::invalid_argument("ShmMirror: rate_hz must be > 0");
  thread_ = std::thread([this] {
    std::vector<uint8_t> buf(kShmMaxMessageBytes);
    auto next = std::chrono::steady_clock::now();
    const auto period = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
        std::chrono::duration<double>(period_s_));
    while (!stop_.load(std::memory_order_relaxed)) {
      size_t n = 0;
      if (reader_.read(buf.data(), buf.size(), &n) != 0 &&
          bus_.publish_raw(lcm_channel_, buf.data(), static_cast<int>(n)) == 0)
        mirrored_.fetch_add(1, std::memory_order_relaxed);
      next += period;
      const auto now = std::chrono::steady_clock::now();
      if (next < now) next = now;
      std::this_thread::sleep_until(next);
    }
  });
}

ShmMirror::~ShmMirror() { stop(); }

void ShmMirror::stop() {
  stop_.store(true);
  if (thread_.joinable()) thread_.join();
}

}  // namespace haptree::bus
