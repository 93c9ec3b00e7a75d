// Fuzz target: the IMD server's packet parser (haptree/imd/protocol.hpp, parse_client_message) driven as
// imd_bridge drives it: the input is a receiver's byte stream, parsed packet after packet until it needs
// more bytes or is refused. The first byte picks max_atoms (the session's atom count, 0..255). Oracle:
// consumed bytes are within the stream and at most max_client_message_bytes; a message has its type's
// content (MDCOMM: at most max_atoms unique indices in range, 3 finite forces each); an error says why.
#include <cmath>
#include <set>

#include "fuzz/fuzz_target.hpp"
#include "haptree/imd/protocol.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  namespace imd = haptree::imd;
  const int32_t max_atoms = data[0];
  ++data;
  --size;
  imd::ClientMessage m;
  size_t at = 0;
  for (;;) {
    const imd::ParseResult r = imd::parse_client_message(data + at, size - at, max_atoms, m);
    if (r.status == imd::ParseStatus::kError) {
      FUZZ_CHECK(!r.error.empty());
      FUZZ_CHECK(r.consumed == 0);
      break;
    }
    if (r.status == imd::ParseStatus::kNeedMore) {
      FUZZ_CHECK(r.consumed == 0);
      // a valid prefix never asks the server to buffer more than the largest packet
      FUZZ_CHECK(size - at < imd::max_client_message_bytes(max_atoms));
      break;
    }
    FUZZ_CHECK(r.consumed >= imd::kHeaderBytes && r.consumed <= size - at);
    FUZZ_CHECK(r.consumed <= imd::max_client_message_bytes(max_atoms) || m.type != imd::Type::kMdcomm);
    if (m.type == imd::Type::kMdcomm) {
      FUZZ_CHECK(m.indices.size() <= static_cast<size_t>(max_atoms));
      FUZZ_CHECK(m.forces.size() == 3 * m.indices.size());
      FUZZ_CHECK(r.consumed == imd::kHeaderBytes + 16 * m.indices.size());
      std::set<int32_t> seen;
      for (int32_t i : m.indices) {
        FUZZ_CHECK(i >= 0 && i < max_atoms);
        FUZZ_CHECK(seen.insert(i).second);
      }
      for (float f : m.forces) FUZZ_CHECK(std::isfinite(f));
    }
    at += r.consumed;
  }
  return 0;
}
