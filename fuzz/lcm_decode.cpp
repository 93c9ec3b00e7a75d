// Fuzz target: every LCM decoder, bus::decode_checked<T> for each lcmt type (the only way the processes
// read the wire). Input: [selector][bytes after the fingerprint] (lcm_input.hpp); the selector picks the
// type. Oracles: never crash or throw; a message accepted as kOk has exactly the encoded size of its
// bytes, re-encodes, and decodes again to the same encoding (the decode is a function of the bytes).
// The raw input is also offered to every decoder unchanged (wrong-type / too-short paths).
#include <vector>

#include "fuzz/fuzz_target.hpp"
#include "fuzz/lcm_input.hpp"
#include "haptree/bus/wire.hpp"

namespace {

template <class T>
void check(const uint8_t* payload, size_t size) {
  using haptree::bus::DecodeResult;
  static T msg{};   // reused, as a Subscription<T> reuses its message
  const std::vector<uint8_t>& buf = haptree::fuzz::with_fingerprint<T>(payload, size);
  if (haptree::bus::decode_checked(buf.data(), buf.size(), msg) != DecodeResult::kOk) return;
  const int n = msg.getEncodedSize();
  FUZZ_CHECK(n == static_cast<int>(buf.size()));
  std::vector<uint8_t> again(static_cast<size_t>(n));
  FUZZ_CHECK(msg.encode(again.data(), 0, n) == n);
  static T msg2{};
  FUZZ_CHECK(haptree::bus::decode_checked(again.data(), again.size(), msg2) == DecodeResult::kOk);
  std::vector<uint8_t> third(static_cast<size_t>(n));
  FUZZ_CHECK(msg2.encode(third.data(), 0, n) == n);
  FUZZ_CHECK(third == again);
}

template <class T>
void raw(const uint8_t* data, size_t size) {
  static T msg{};
  const auto r = haptree::bus::decode_checked(data, size, msg);
  (void)r;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace haptree;
  raw<lcmt_coupling_snapshot>(data, size);
  raw<lcmt_device_state>(data, size);
  raw<lcmt_feedback>(data, size);
  raw<lcmt_process_stats>(data, size);
  raw<lcmt_scene_state>(data, size);
  raw<lcmt_user_force>(data, size);
  if (size < 1) return 0;
  const uint8_t* p = data + 1;
  const size_t n = size - 1;
  switch (data[0] % 6) {
    case 0: check<lcmt_coupling_snapshot>(p, n); break;
    case 1: check<lcmt_device_state>(p, n); break;
    case 2: check<lcmt_feedback>(p, n); break;
    case 3: check<lcmt_process_stats>(p, n); break;
    case 4: check<lcmt_scene_state>(p, n); break;
    case 5: check<lcmt_user_force>(p, n); break;
  }
  return 0;
}
