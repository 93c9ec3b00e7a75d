// Fuzz target: an HTTP request to the viewer. The bytes are read by websocketpp's request parser (what the
// viewer's server does with a new connection's first bytes), then the request's resource is routed as the
// viewer routes it (route_resource, viewer/input.hpp). Oracle: the parser either takes the bytes or throws
// websocketpp::http::exception (the server answers 400 and closes); nothing else escapes; a routed resource
// is one of the viewer's files or not-found.
#define ASIO_STANDALONE
#define _WEBSOCKETPP_CPP11_STL_
#include <websocketpp/http/request.hpp>

#include "fuzz/fuzz_target.hpp"
#include "viewer/input.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string raw(reinterpret_cast<const char*>(data), size);
  const haptree::WebResource direct = haptree::route_resource(raw);   // any bytes as a resource
  FUZZ_CHECK(haptree::query_param(raw, "token").size() <= raw.size());
  FUZZ_CHECK(direct >= haptree::WebResource::kNotFound && direct <= haptree::WebResource::kSceneMeshes);
  websocketpp::http::parser::request req;
  try {
    size_t at = 0;
    while (at < size && !req.ready()) {
      const size_t n = req.consume(raw.data() + at, size - at);
      FUZZ_CHECK(n <= size - at);
      if (n == 0) break;
      at += n;
    }
  } catch (const websocketpp::http::exception&) {
    return 0;
  }
  if (!req.ready()) return 0;
  (void)haptree::query_param(req.get_uri(), "token");   // access control's parsing: never throws, any bytes
  (void)haptree::cookie_value(req.get_header("Cookie"), "haptree_viewer_8080");
  (void)haptree::same_origin(req.get_header("Origin"), req.get_header("Host"), size % 2 == 0);
  const haptree::WebResource r = haptree::route_resource(req.get_uri());
  FUZZ_CHECK(r >= haptree::WebResource::kNotFound && r <= haptree::WebResource::kSceneMeshes);
  if (r == haptree::WebResource::kNotFound) return 0;
  const std::string path = req.get_uri().substr(0, req.get_uri().find('?'));
  FUZZ_CHECK(path == "/" || path == "/index.html" || path == "/viewer.js" || path == "/vendor/ngl.js" ||
             path == "/scene.pdb" || path == "/scene.json" || path == "/scene.meshes");
  return 0;
}
