#include "viewer/input.hpp"

#include <nlohmann/json.hpp>

#include <cstdint>

namespace haptree {

using json = nlohmann::json;

ClientCommand parse_client_message(const char* data, size_t size) noexcept {
  ClientCommand c;
  if (data == nullptr || size == 0 || size > kMaxClientMessageBytes) return c;
  try {
    const json j = json::parse(data, data + size, nullptr, /*allow_exceptions=*/false);
    if (!j.is_object() || !j.contains("t") || !j["t"].is_string()) return c;
    const std::string t = j["t"].get<std::string>();
    auto read_p = [&](Vec3& p) {
      if (!j.contains("p") || !j["p"].is_array() || j["p"].size() != 3) return false;
      for (int i = 0; i < 3; ++i) {
        if (!j["p"][i].is_number()) return false;
        p[i] = j["p"][i].get<double>();
      }
      return p.allFinite() && p.cwiseAbs().maxCoeff() < 1e6;
    };
    if (t == "down") {
      if (!j.contains("i") || !j["i"].is_number_integer() || !read_p(c.p)) return c;
      const int64_t i = j["i"].get<int64_t>();
      if (i < 0 || i > (1 << 30)) return c;
      c.atom = static_cast<int>(i);
      c.kind = ClientCommand::Kind::kDown;
    } else if (t == "move") {
      if (read_p(c.p)) c.kind = ClientCommand::Kind::kMove;
    } else if (t == "up") {
      c.kind = ClientCommand::Kind::kUp;
    }
  } catch (...) {
    c = ClientCommand{};
  }
  return c;
}

WebResource route_resource(const std::string& resource) noexcept {
  const std::string res = resource.substr(0, resource.find('?'));
  if (res == "/" || res == "/index.html") return WebResource::kIndex;
  if (res == "/viewer.js") return WebResource::kViewerJs;
  if (res == "/vendor/ngl.js") return WebResource::kNglJs;
  if (res == "/scene.pdb") return WebResource::kScenePdb;
  if (res == "/scene.json") return WebResource::kSceneJson;
  return WebResource::kNotFound;
}

}  // namespace haptree
