// How the LCM fuzz targets read their input: [selector byte][message bytes after the 8-byte type
// fingerprint]. The harness puts the right fingerprint in front, so the fuzzer spends its time on the
// fields instead of guessing a 64-bit hash, and corpus/regression files stay valid when a type's
// fingerprint changes (a new field): they are replayed against the current layout.
#pragma once

#include <cstdint>
#include <cstring>
#include <vector>

namespace haptree::fuzz {

template <class T>
const std::vector<uint8_t>& with_fingerprint(const uint8_t* payload, size_t size) {
  thread_local std::vector<uint8_t> buf;
  buf.resize(8 + size);
  const uint64_t h = static_cast<uint64_t>(T::getHash());
  for (int i = 0; i < 8; ++i) buf[i] = static_cast<uint8_t>(h >> (56 - 8 * i));
  if (size) std::memcpy(buf.data() + 8, payload, size);
  return buf;
}

}  // namespace haptree::fuzz
