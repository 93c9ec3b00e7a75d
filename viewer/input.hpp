#pragma once
// What the viewer accepts from a browser, parsed without trusting it: the WebSocket text messages of the
// page's pointer (parse_client_message) and the HTTP resource of a request (route_resource). Pure
// functions on bytes, in their own small library (haptree_viewer_input) so the fuzz targets
// (fuzz/viewer_ws.cpp, fuzz/viewer_http.cpp) call exactly what the viewer calls.
#include <cstddef>
#include <cstdint>
#include <string>

#include "haptree/spatial.hpp"

namespace haptree {

// Largest message a page sends (its pointer JSON is < 100 bytes); the viewer's WebSocket and HTTP body
// limits too, so a client cannot make the server buffer more (websocketpp's default is 32 MB).
constexpr size_t kMaxClientMessageBytes = 4096;

// One message from a page (fuzz target: any bytes); longer than kMaxClientMessageBytes: refused unread.
// Never throws.
struct ClientCommand {
  enum class Kind { kInvalid, kDown, kMove, kUp, kAck };
  Kind kind = Kind::kInvalid;
  int atom = -1;                    // kDown: display point picked (atom, or body for body scenes)
  Vec3 p = Vec3::Zero();            // kDown/kMove: pointer target, display coordinates (finite)
  int64_t frames = 0;               // kAck: binary messages the page has received on this socket (>= 0)
};
ClientCommand parse_client_message(const char* data, size_t size) noexcept;

// The files the viewer serves; kNotFound for anything else. The query string is ignored.
enum class WebResource { kNotFound, kIndex, kViewerJs, kNglJs, kScenePdb, kSceneJson, kSceneMeshes };
WebResource route_resource(const std::string& resource) noexcept;

// Access control's parsing (any bytes; never throws). The value of `key` in a resource's query string
// (`/ws?token=abc`: "abc", percent-escapes decoded; "" if absent or malformed).
std::string query_param(const std::string& resource, const std::string& key) noexcept;
// The value of cookie `name` in a Cookie header (`a=1; name=v`: "v"; "" if absent).
std::string cookie_value(const std::string& header, const std::string& name) noexcept;
// True when a WebSocket upgrade's Origin header names the page the viewer served: scheme http (https
// with TLS) and host[:port] equal (case-insensitive) to the request's Host header. An absent Origin
// (a client that is not a browser) is allowed; "null" or any other origin is not.
bool same_origin(const std::string& origin, const std::string& host, bool tls) noexcept;

}  // namespace haptree
