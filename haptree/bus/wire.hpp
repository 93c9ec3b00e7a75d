// Wire-level helpers for haptree LCM messages: schema version at byte 8, checked decoding that never
// throws and never allocates absurd sizes from corrupted counts, and stamping of outgoing messages.
#pragma once

#include <chrono>
#include <cstdint>
#include <cstring>
#include <random>
#include <string>

#include "haptree/lcmt_coupling_snapshot.hpp"
#include "haptree/lcmt_device_state.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "haptree/lcmt_process_stats.hpp"
#include "haptree/lcmt_scene_state.hpp"
#include "haptree/lcmt_user_force.hpp"

namespace haptree::bus {

// Microseconds since the epoch (system clock): the `utime` of every message.
inline int64_t now_utime() noexcept {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// Age of a message stamped `utime`, by this host's clock, in seconds (OriginLock's start check).
inline double message_age_s(int64_t utime) noexcept { return 1e-6 * static_cast<double>(now_utime() - utime); }

// The origin of an encoded message of type T without decoding it: the header every haptree message starts
// with (LCM type hash at byte 0, schema_version at 8, utime at 12, instance_id at 20, big-endian). False if
// it is too short or not a T.
template <class T>
bool peek_origin(const void* data, size_t size, int64_t* utime, int64_t* instance_id) noexcept {
  if (data == nullptr || size < 28) return false;
  const auto* b = static_cast<const uint8_t*>(data);
  auto be64 = [b](size_t at) {
    uint64_t v = 0;
    for (size_t i = 0; i < 8; ++i) v = (v << 8) | b[at + i];
    return static_cast<int64_t>(v);
  };
  if (be64(0) != T::getHash()) return false;
  *utime = be64(12);
  *instance_id = be64(20);
  return true;
}

// Big-endian int32 at byte 8: the schema_version of any haptree message (after LCM's 8-byte fingerprint).
inline bool peek_schema_version(const void* data, size_t size, int32_t* out) noexcept {
  if (data == nullptr || size < 12) return false;
  const auto* b = static_cast<const uint8_t*>(data) + 8;
  *out = static_cast<int32_t>((uint32_t(b[0]) << 24) | (uint32_t(b[1]) << 16) | (uint32_t(b[2]) << 8) |
                              uint32_t(b[3]));
  return true;
}
// LCM type fingerprint (first 8 bytes, big-endian).
inline bool peek_fingerprint(const void* data, size_t size, int64_t* out) noexcept {
  if (data == nullptr || size < 8) return false;
  const auto* b = static_cast<const uint8_t*>(data);
  uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | b[i];
  std::memcpy(out, &v, 8);
  return true;
}

// A random nonzero 64-bit id, drawn once per publishing component object (SimServer, Coupler,
// DeviceBridge, ...): the `instance_id` of everything it publishes. Several components live in one process
// in the embedded launcher, so the id belongs to the object, not the process. Consumers lock onto one
// producer instance (haptree/bus/origin.hpp): a new id tells a restart from a reordered or replayed message.
inline int64_t new_instance_id() {
  std::random_device rd;
  uint64_t v = 0;
  while (v == 0) v = (uint64_t(rd()) << 32) ^ uint64_t(rd());
  int64_t id;
  std::memcpy(&id, &v, 8);
  return id;
}

// Big-endian int64 at byte 20: the instance_id of any haptree message (fingerprint 8, schema 4, utime 8).
inline bool peek_instance_id(const void* data, size_t size, int64_t* out) noexcept {
  if (data == nullptr || size < 28) return false;
  const auto* b = static_cast<const uint8_t*>(data) + 20;
  uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | b[i];
  std::memcpy(out, &v, 8);
  return true;
}

// Sets schema_version from the type's constant, the publisher's instance id and utime (default now).
// Every publisher calls it (or sets the three fields itself). Returns msg.
template <class T>
T& stamp(T& msg, int64_t instance_id, int64_t utime = now_utime()) noexcept {
  msg.schema_version = T::SCHEMA_VERSION;
  msg.utime = utime;
  msg.instance_id = instance_id;
  return msg;
}

namespace detail {
// Reads a big-endian int32 at `off` if it lies inside [0, size).
inline bool read_i32(const uint8_t* d, size_t size, size_t off, int32_t* v) {
  if (off + 4 > size) return false;
  *v = static_cast<int32_t>((uint32_t(d[off]) << 24) | (uint32_t(d[off + 1]) << 16) |
                            (uint32_t(d[off + 2]) << 8) | uint32_t(d[off + 3]));
  return true;
}
// A variable-length count must be >= 0 and fit the bytes left (each element takes >= min_bytes).
inline bool count_fits(int32_t n, size_t size, size_t off, size_t min_bytes) {
  return n >= 0 && off <= size && static_cast<size_t>(n) * min_bytes <= size - off;
}

// The generated decode() resize()s vectors from counts read off the wire before it checks the length;
// these guards reject counts that cannot fit the message, so a corrupted message cannot ask for gigabytes.
// Offsets follow the field order of the .lcm files (8-byte fingerprint first).
template <class T>
inline bool counts_plausible(const T*, const uint8_t*, size_t) { return true; }

inline bool counts_plausible(const lcmt_coupling_snapshot*, const uint8_t* d, size_t size) {
  // hash 8, schema 4, utime 8, instance 8, fingerprint 8, version 8, sim_time 8, user_id 4 -> n_grabs at 56
  int32_t n = 0;
  size_t off = 56;
  if (!read_i32(d, size, off, &n) || !count_fits(n, size, off + 4, 4 + 24 + 24)) return false;
  off += 4 + static_cast<size_t>(n) * 52;
  if (!read_i32(d, size, off, &n) || !count_fits(n, size, off + 4, 4)) return false;
  off += 4 + static_cast<size_t>(n) * 4;
  return read_i32(d, size, off, &n) && count_fits(n, size, off + 4, 8);
}
inline bool counts_plausible(const lcmt_scene_state*, const uint8_t* d, size_t size) {
  // hash 8, schema 4, utime 8, instance 8, version 8, sim_time 8 -> nbodies at 44
  int32_t n = 0;
  return read_i32(d, size, 44, &n) && count_fits(n, size, 48, 24 + 32);
}
inline bool counts_plausible(const lcmt_process_stats*, const uint8_t* d, size_t size) {
  // hash 8, schema 4, utime 8, instance 8, seq 8 -> process_name (int32 length incl. NUL, bytes) at 36
  int32_t len = 0;
  if (!read_i32(d, size, 36, &len) || len < 1 || !count_fits(len, size, 40, 1)) return false;
  // then process_id 4, 4 doubles 32, 7 int64 56 -> n_extra
  const size_t off = 40 + static_cast<size_t>(len) + 4 + 32 + 56;
  int32_t n = 0;
  // each extra: name (4-byte length + at least NUL) and a double
  if (!read_i32(d, size, off, &n) || !count_fits(n, size, off + 4, 5 + 8)) return false;
  // Each name's length must be >= 1 and fit: the generated decode computes `length - 1` first, which
  // overflows for INT32_MIN (undefined behaviour, found by fuzz/lcm_decode).
  size_t pos = off + 4;
  for (int32_t i = 0; i < n; ++i) {
    int32_t l = 0;
    if (!read_i32(d, size, pos, &l) || l < 1 || !count_fits(l, size, pos + 4, 1)) return false;
    pos += 4 + static_cast<size_t>(l);
  }
  return true;
}

// LCM strings are NUL-terminated on the wire. The generated decode keeps a NUL inside the string, but
// encode writes strlen() bytes while getEncodedSize() counts size(): such a message would re-encode
// shorter than it claims (found by fuzz/lcm_decode). A string with an embedded NUL is malformed.
inline bool no_nul(const std::string& s) { return s.find('\0') == std::string::npos; }
template <class T>
inline bool strings_plausible(const T&) { return true; }
inline bool strings_plausible(const lcmt_process_stats& m) {
  if (!no_nul(m.process_name)) return false;
  for (const auto& n : m.extra_names)
    if (!no_nul(n)) return false;
  return true;
}
}  // namespace detail

enum class DecodeResult { kOk, kTooShort, kWrongType, kMalformed, kSchemaMismatch };

// Decodes `size` bytes into msg (reused: no allocation once msg reached its largest size). Never throws.
// kWrongType = fingerprint differs (another type, or another layout of this type).
template <class T>
DecodeResult decode_checked(const void* data, size_t size, T& msg) noexcept {
  if (data == nullptr || size < 12 || size > static_cast<size_t>(INT32_MAX)) return DecodeResult::kTooShort;
  int64_t fp = 0;
  peek_fingerprint(data, size, &fp);
  if (fp != T::getHash()) return DecodeResult::kWrongType;
  const auto* d = static_cast<const uint8_t*>(data);
  if (!detail::counts_plausible(&msg, d, size)) return DecodeResult::kMalformed;
  try {
    const int n = msg.decode(data, 0, static_cast<int>(size));
    if (n < 0 || static_cast<size_t>(n) != size) return DecodeResult::kMalformed;
    if (!detail::strings_plausible(msg)) return DecodeResult::kMalformed;
  } catch (...) {  // e.g. a negative string length turned into a huge assign()
    return DecodeResult::kMalformed;
  }
  if (msg.schema_version != T::SCHEMA_VERSION) return DecodeResult::kSchemaMismatch;
  return DecodeResult::kOk;
}

const char* to_string(DecodeResult r) noexcept;

}  // namespace haptree::bus
