#include "haptree/bus/shm_channel.hpp"

#include <dirent.h>
#include <fcntl.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/random.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <algorithm>
#include <cstring>
#include <ctime>
#include <stdexcept>

#include "haptree/bus/bus.hpp"

namespace haptree::bus {
namespace detail {

constexpr uint64_t kShmMagic = 0x6861707472656532ull;  // "haptree2": header with the writer's identity
constexpr int kShmSlots = 4;

struct ShmHeader {
  std::atomic<uint64_t> magic;              // stored last by the creating writer (release)
  std::atomic<uint64_t> max_message_bytes;
  std::atomic<int64_t> writer_pid;
  std::atomic<uint64_t> writer_proc_start;  // field 22 of /proc/<pid>/stat: tells a reused pid apart
  std::atomic<uint64_t> writer_instance;    // random, nonzero
  std::atomic<int64_t> writer_start_ns;     // CLOCK_MONOTONIC
  std::atomic<uint32_t> writer_closed;      // 1 once the writer closed (it also unlinks the name)
};

struct alignas(64) ShmSlot {
  std::atomic<uint64_t> seq;    // odd while the writer is inside
  std::atomic<uint64_t> index;  // message index held (1, 2, ...)
  std::atomic<uint32_t> size;
  std::atomic<int64_t> write_ns;  // CLOCK_MONOTONIC at the end of the write
  alignas(64) uint8_t data[kShmMaxMessageBytes];
};

struct ShmSegment {
  ShmHeader header;
  alignas(64) std::atomic<uint64_t> latest;  // index of the newest complete message; 0 = none
  alignas(64) ShmSlot slots[kShmSlots];
};
static_assert(std::atomic<uint64_t>::is_always_lock_free, "shared-memory channel needs lock-free atomics");

}  // namespace detail

using detail::ShmSegment;

namespace {

constexpr int64_t kLivenessCheckNs = 5'000'000;   // a reader re-checks its writer's pid every 5 ms (kill 0)
// ... and the pid's start time (pid reuse, zombie) every second: reading /proc/PID/stat took 68 µs median,
// 146 µs p99 on the 2-core host, inside a pose's path to its force every 5 ms.
constexpr int64_t kStartTimeCheckNs = 1'000'000'000;
constexpr int64_t kReopenEveryNs = 20'000'000;    // and looks for a (new) segment every 20 ms when it has none
constexpr int64_t kYoungSegmentNs = 5'000'000'000;
constexpr int64_t kForeignLayoutAgeNs = 3600'000'000'000;

std::string uid_suffix() { return "." + std::to_string(::getuid()); }

// Start time of process pid (clock ticks since boot) if it exists and is not a zombie; 0 otherwise.
// No allocation (called from readers' loops).
uint64_t proc_start_ticks(int64_t pid) noexcept {
  if (pid <= 0) return 0;
  char path[64];
  std::snprintf(path, sizeof path, "/proc/%lld/stat", static_cast<long long>(pid));
  const int fd = ::open(path, O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    if (errno == ENOENT) return 0;
    return (::kill(static_cast<pid_t>(pid), 0) == 0 || errno == EPERM) ? 1 : 0;  // /proc hidden: pid only
  }
  char buf[1024];
  const ssize_t n = ::read(fd, buf, sizeof buf - 1);
  ::close(fd);
  if (n <= 0) return 0;
  buf[n] = 0;
  const char* p = std::strrchr(buf, ')');   // the command name may contain spaces and parentheses
  if (!p || p[1] != ' ') return 0;
  p += 2;
  if (*p == 'Z' || *p == 'X' || *p == 'x') return 0;   // state (field 3)
  for (int field = 3; field < 22 && *p; ++p)
    if (*p == ' ') ++field;
  const unsigned long long ticks = std::strtoull(p, nullptr, 10);
  return ticks == 0 ? 1 : ticks;
}

bool process_alive(int64_t pid, uint64_t start_ticks) noexcept {
  const uint64_t now = proc_start_ticks(pid);
  if (now == 0) return false;
  return start_ticks <= 1 || now <= 1 || now == start_ticks;
}

uint64_t random_instance() noexcept {
  uint64_t v = 0;
  if (::getrandom(&v, sizeof v, 0) != static_cast<ssize_t>(sizeof v))
    v = static_cast<uint64_t>(shm_now_ns()) ^ (static_cast<uint64_t>(::getpid()) << 32);
  return v ? v : 1;
}

// Whose segment is this? "" if it has a live, open writer; otherwise why it may be reclaimed.
std::string stale_reason(const detail::ShmHeader& h, int64_t age_ns) {
  const uint64_t magic = h.magic.load(std::memory_order_acquire);
  if (magic == 0) return age_ns < kYoungSegmentNs ? "" : "never initialised";
  // Another layout: an older haptree build. Its segments carry no writer identity, so only ones untouched
  // for an hour are taken for leftovers (a live older session on the same host keeps its own).
  if (magic != detail::kShmMagic) return age_ns > kForeignLayoutAgeNs ? "another layout, over an hour old" : "";
  if (h.writer_closed.load(std::memory_order_acquire)) return "writer closed";
  const int64_t pid = h.writer_pid.load();
  if (!process_alive(pid, h.writer_proc_start.load())) return "writer pid " + std::to_string(pid) + " is gone";
  return "";
}

int64_t file_age_ns(const struct stat& st) {
  timespec now{};
  ::clock_gettime(CLOCK_REALTIME, &now);
  return (static_cast<int64_t>(now.tv_sec) - st.st_mtim.tv_sec) * 1'000'000'000 + (now.tv_nsec - st.st_mtim.tv_nsec);
}

}  // namespace

int64_t shm_now_ns() noexcept {
  timespec t{};
  ::clock_gettime(CLOCK_MONOTONIC, &t);
  return static_cast<int64_t>(t.tv_sec) * 1'000'000'000 + t.tv_nsec;
}

std::string shm_segment_name(const std::string& channel) { return "/haptree." + channel + uid_suffix(); }

std::vector<std::string> reclaim_stale_shm_segments() {
  std::vector<std::string> removed;
  DIR* dir = ::opendir("/dev/shm");
  if (!dir) return removed;
  const std::string tail = uid_suffix();
  while (const dirent* e = ::readdir(dir)) {
    const std::string name = e->d_name;
    if (name.rfind("haptree.", 0) != 0 || name.size() <= tail.size() ||
        name.compare(name.size() - tail.size(), tail.size(), tail) != 0)
      continue;
    const std::string shm_name = "/" + name;
    const int fd = ::shm_open(shm_name.c_str(), O_RDONLY, 0);
    if (fd < 0) continue;
    struct stat st {};
    std::string why;
    if (::fstat(fd, &st) == 0 && st.st_uid == ::getuid()) {
      if (static_cast<size_t>(st.st_size) < sizeof(detail::ShmHeader)) {
        if (file_age_ns(st) >= kYoungSegmentNs) why = "too small";
      } else if (void* p = ::mmap(nullptr, sizeof(detail::ShmHeader), PROT_READ, MAP_SHARED, fd, 0);
                 p != MAP_FAILED) {
        why = stale_reason(*static_cast<const detail::ShmHeader*>(p), file_age_ns(st));
        ::munmap(p, sizeof(detail::ShmHeader));
      }
    }
    ::close(fd);
    if (!why.empty() && ::shm_unlink(shm_name.c_str()) == 0) removed.push_back(shm_name + " (" + why + ")");
  }
  ::closedir(dir);
  return removed;
}

ShmChannel::ShmChannel(const std::string& channel) : channel_(channel), name_(shm_segment_name(channel)) {
  set_session_key(process_session_key());   // keyed session (auth.hpp): nullptr = none
}

void ShmChannel::set_session_key(std::shared_ptr<const SessionKey> key) {
  auth_ = key ? std::make_unique<Authenticator>(std::move(key)) : nullptr;
}

ShmChannel::~ShmChannel() { unmap(); }

void ShmChannel::unmap() noexcept {
  if (seg_) ::munmap(seg_, sizeof(ShmSegment));
  seg_ = nullptr;
  inode_ = 0;
}

bool ShmChannel::remove(const std::string& channel) {
  return ::shm_unlink(shm_segment_name(channel).c_str()) == 0;
}

namespace {
// Names of this process's writer segments, in fixed buffers, so a signal handler can unlink them
// (shm_unlink is an unlink(2) of /dev/shm/NAME): a child stuck on its bus at SIGTERM leaves nothing.
constexpr int kMaxOwnedSegments = 64;
char g_owned[kMaxOwnedSegments][256];
std::atomic<int> g_owned_count{0};
void own_segment(const std::string& name) noexcept {
  const int i = g_owned_count.fetch_add(1);
  if (i >= kMaxOwnedSegments || name.size() >= sizeof g_owned[0]) return;
  std::memcpy(g_owned[i], name.c_str(), name.size() + 1);
}
void disown_segment(const std::string& name) noexcept {
  const int n = std::min(g_owned_count.load(), kMaxOwnedSegments);
  for (int i = 0; i < n; ++i)
    if (name == g_owned[i]) g_owned[i][0] = 0;
}
}  // namespace

void unlink_own_shm_segments() noexcept {
  const int n = std::min(g_owned_count.load(), kMaxOwnedSegments);
  for (int i = 0; i < n; ++i)
    if (g_owned[i][0] != 0) ::shm_unlink(g_owned[i]);
}

ShmWriter::ShmWriter(const std::string& channel) : ShmChannel(channel) {
  for (const auto& r : reclaim_stale_shm_segments()) reclaimed_ |= r.rfind(name_ + " (", 0) == 0;
  const size_t bytes = sizeof(ShmSegment);
  for (int attempt = 0; attempt < 3 && !seg_; ++attempt) {
    int fd = ::shm_open(name_.c_str(), O_RDWR | O_CREAT | O_EXCL, 0600);
    if (fd < 0 && errno == EEXIST) {
      // Someone's segment: refuse a live writer, reclaim anything else.
      const int ofd = ::shm_open(name_.c_str(), O_RDONLY, 0);
      if (ofd < 0) continue;   // vanished meanwhile: try again
      struct stat st {};
      std::string why = "unreadable";
      if (::fstat(ofd, &st) == 0) {
        why = "too small";
        if (static_cast<size_t>(st.st_size) >= sizeof(detail::ShmHeader)) {
          void* p = ::mmap(nullptr, sizeof(detail::ShmHeader), PROT_READ, MAP_SHARED, ofd, 0);
          if (p != MAP_FAILED) {
            const auto& h = *static_cast<const detail::ShmHeader*>(p);
            why = stale_reason(h, file_age_ns(st));
            const uint64_t magic = h.magic.load(std::memory_order_acquire);
            if (why.empty() && magic != 0 && magic != detail::kShmMagic) why = "another layout";   // our name: take it
            const long long pid = h.writer_pid.load();
            ::munmap(p, sizeof(detail::ShmHeader));
            if (why.empty()) {
              ::close(ofd);
              throw std::runtime_error("shared-memory channel " + channel + ": " + name_ +
                                       " already has a live writer (pid " + std::to_string(pid) +
                                       "); one writer per channel: is another process already serving this "
                                       "device? Stop it, or use another --device / --channel-suffix");
            }
          }
        }
      }
      ::close(ofd);
      ::shm_unlink(name_.c_str());
      reclaimed_ = true;
      continue;
    }
    if (fd < 0)
      throw std::runtime_error("shared-memory channel " + channel + ": shm_open(" + name_ + ") failed: " +
                               std::strerror(errno) + " (is /dev/shm mounted and writable?)");
    struct stat st {};
    if (::ftruncate(fd, static_cast<off_t>(bytes)) != 0 || ::fstat(fd, &st) != 0) {
      const int e = errno;
      ::close(fd);
      ::shm_unlink(name_.c_str());
      throw std::runtime_error("shared-memory channel " + channel + ": cannot size " + name_ + " to " +
                               std::to_string(bytes) + " bytes: " + std::strerror(e));
    }
    void* p = ::mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    const int e = errno;
    ::close(fd);
    if (p == MAP_FAILED) {
      ::shm_unlink(name_.c_str());
      throw std::runtime_error("shared-memory channel " + channel + ": mmap of " + name_ +
                               " failed: " + std::strerror(e));
    }
    seg_ = static_cast<ShmSegment*>(p);
    inode_ = static_cast<uint64_t>(st.st_ino);
  }
  if (!seg_)
    throw std::runtime_error("shared-memory channel " + channel + ": could not create " + name_ +
                             " (another writer keeps re-creating it?)");
  instance_ = random_instance();
  auto& h = seg_->header;
  h.max_message_bytes.store(kShmMaxMessageBytes);
  h.writer_pid.store(::getpid());
  h.writer_proc_start.store(proc_start_ticks(::getpid()));
  h.writer_instance.store(instance_);
  h.writer_start_ns.store(shm_now_ns());
  h.writer_closed.store(0);
  h.magic.store(detail::kShmMagic, std::memory_order_release);
  own_segment(name_);
}

ShmWriter::~ShmWriter() {
  if (!seg_) return;
  disown_segment(name_);
  seg_->header.writer_closed.store(1, std::memory_order_release);
  // Unlink only our own segment: a successor may already have replaced the name.
  struct stat st {};
  const std::string path = "/dev/shm" + name_;
  if (::stat(path.c_str(), &st) == 0 && static_cast<uint64_t>(st.st_ino) == inode_) ::shm_unlink(name_.c_str());
}

uint8_t* ShmWriter::begin_write() noexcept {
  auto& s = seg_->slots[next_ % detail::kShmSlots];
  const uint64_t q = s.seq.load(std::memory_order_relaxed);   // even: this writer is the only one
  slot_seq_ = q;
  s.seq.store(q + 1, std::memory_order_relaxed);
  std::atomic_thread_fence(std::memory_order_release);
  slot_ = &s;
  return s.data;
}

void ShmWriter::end_write(uint32_t size) noexcept {
  auto& s = *static_cast<detail::ShmSlot*>(slot_);
  if (size == 0) {  // failed encode: leave the slot's old content marked consistent but do not publish
    s.index.store(0, std::memory_order_relaxed);
    s.seq.store(slot_seq_ + 2, std::memory_order_release);
    return;
  }
  s.size.store(size, std::memory_order_relaxed);
  s.index.store(next_, std::memory_order_relaxed);
  s.write_ns.store(shm_now_ns(), std::memory_order_relaxed);
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

ShmReader::ShmReader(const std::string& channel, double max_age_s)
    : ShmChannel(channel), buf_(kShmMaxMessageBytes), opened_ns_(shm_now_ns()) {
  set_max_age_s(max_age_s);
  try_open();
}

void ShmReader::set_max_age_s(double s) noexcept {
  max_age_ns_ = !(s >= 0) ? 0 : s >= 9e9 ? std::numeric_limits<int64_t>::max() : static_cast<int64_t>(s * 1e9);
}

// Maps the channel's current segment if it is not the one mapped already. False if there is none.
bool ShmReader::try_open() noexcept {
  const int fd = ::shm_open(name_.c_str(), O_RDONLY, 0);
  if (fd < 0) return false;
  struct stat st {};
  if (::fstat(fd, &st) != 0 || static_cast<size_t>(st.st_size) < sizeof(ShmSegment)) {
    ::close(fd);
    return false;
  }
  if (seg_ && static_cast<uint64_t>(st.st_ino) == inode_) {
    ::close(fd);
    return true;
  }
  void* p = ::mmap(nullptr, sizeof(ShmSegment), PROT_READ, MAP_SHARED, fd, 0);
  ::close(fd);
  if (p == MAP_FAILED) return false;
  auto* seg = static_cast<ShmSegment*>(p);
  if (seg->header.magic.load(std::memory_order_acquire) != detail::kShmMagic) {  // other layout / mid-creation
    ::munmap(p, sizeof(ShmSegment));
    return false;
  }
  unmap();
  seg_ = seg;
  inode_ = static_cast<uint64_t>(st.st_ino);
  last_ = 0;   // a new writer numbers from 1
  checked_instance_ = 0;
  ++reopened_;
  return true;
}

bool ShmReader::writer_ok(int64_t now_ns) noexcept {
  const auto& h = seg_->header;
  if (h.writer_closed.load(std::memory_order_acquire)) return false;
  const uint64_t inst = h.writer_instance.load(std::memory_order_relaxed);
  if (inst != checked_instance_ || now_ns - full_checked_ns_ >= kStartTimeCheckNs) {
    writer_alive_ = process_alive(h.writer_pid.load(), h.writer_proc_start.load());
    checked_instance_ = inst;
    checked_ns_ = full_checked_ns_ = now_ns;
  } else if (writer_alive_ && now_ns - checked_ns_ >= kLivenessCheckNs) {
    const pid_t pid = static_cast<pid_t>(h.writer_pid.load());   // one syscall: gone (ESRCH) or there
    writer_alive_ = pid > 0 && (::kill(pid, 0) == 0 || errno == EPERM);
    checked_ns_ = now_ns;
  }
  return writer_alive_;
}

int64_t ShmReader::writer_pid() noexcept {
  if (!seg_ || !writer_ok(shm_now_ns())) return 0;
  return seg_->header.writer_pid.load();
}

uint64_t ShmReader::latest_index() const noexcept {
  return seg_ ? seg_->latest.load(std::memory_order_acquire) : 0;
}

uint64_t ShmReader::read(void* out, size_t cap, size_t* size) noexcept {
  int64_t now = shm_now_ns();
  if (!seg_ || !writer_ok(now)) {
    // No segment, or its writer is gone: look (rate-limited) for a new writer's segment.
    if (now < next_open_ns_) return 0;
    next_open_ns_ = now + kReopenEveryNs;
    if (!try_open() || !writer_ok(now)) return 0;
  }
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
    const int64_t written_ns = s.write_ns.load(std::memory_order_relaxed);
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
    now = shm_now_ns();
    // Age and origin: written in this reader's session, recently enough (the writer is alive: above).
    if (written_ns < opened_ns_ || now - written_ns > max_age_ns_) {
      ++stale_;
      return 0;
    }
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
