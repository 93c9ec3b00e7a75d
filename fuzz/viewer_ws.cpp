// Fuzz target: what a page can send the viewer over its WebSocket. The bytes are a client-to-server frame
// stream read by websocketpp's RFC 6455 processor (hybi13, as the viewer's server runs it, with the
// viewer's message size limit); every complete message goes through parse_client_message (viewer/input.hpp).
// Oracle: no crash, no sanitizer report, no exception escaping; a parsed command is one of the page's three
// pointer commands with a finite pointer position below 1e6 and a non-negative atom index, or its
// acknowledgement of frames with a non-negative count.
#define ASIO_STANDALONE
#define _WEBSOCKETPP_CPP11_STL_
#include <websocketpp/config/core.hpp>
#include <websocketpp/processors/hybi13.hpp>

#include <vector>

#include "fuzz/fuzz_target.hpp"
#include "viewer/input.hpp"

namespace {
void check(const haptree::ClientCommand& c) {
  using K = haptree::ClientCommand::Kind;
  if (c.kind == K::kInvalid) return;
  FUZZ_CHECK(c.kind == K::kDown || c.kind == K::kMove || c.kind == K::kUp || c.kind == K::kAck);
  if (c.kind == K::kAck) {
    FUZZ_CHECK(c.frames >= 0);
    return;
  }
  if (c.kind != K::kUp) FUZZ_CHECK(c.p.allFinite() && c.p.cwiseAbs().maxCoeff() < 1e6);
  if (c.kind == K::kDown) FUZZ_CHECK(c.atom >= 0);
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using config = websocketpp::config::core;
  using processor = websocketpp::processor::hybi13<config>;
  // The raw bytes as one message too (the parser alone, whatever the framing).
  check(haptree::parse_client_message(reinterpret_cast<const char*>(data), size));
  auto manager = websocketpp::lib::make_shared<config::con_msg_manager_type>();
  config::rng_type rng;
  processor p(false, true, manager, rng);
  p.set_max_message_size(haptree::kMaxClientMessageBytes);
  std::vector<uint8_t> buf(data, data + size);   // consume() takes a mutable buffer (it unmasks in place)
  size_t at = 0;
  while (at < buf.size()) {
    websocketpp::lib::error_code ec;
    const size_t n = p.consume(buf.data() + at, buf.size() - at, ec);
    FUZZ_CHECK(n <= buf.size() - at);
    if (ec) break;   // the connection would be failed and closed
    at += n;
    if (p.ready()) {
      const auto msg = p.get_message();
      FUZZ_CHECK(msg != nullptr);
      FUZZ_CHECK(msg->get_payload().size() <= haptree::kMaxClientMessageBytes);
      const std::string& pl = msg->get_payload();
      check(haptree::parse_client_message(pl.data(), pl.size()));
    }
    if (n == 0) break;
  }
  return 0;
}
