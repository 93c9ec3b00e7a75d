#include "viewer/input.hpp"

#include <nlohmann/json.hpp>

#include <cctype>
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
    } else if (t == "ack") {
      if (!j.contains("n") || !j["n"].is_number_integer()) return c;
      const int64_t n = j["n"].get<int64_t>();
      if (n < 0) return c;
      c.frames = n;
      c.kind = ClientCommand::Kind::kAck;
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
  if (res == "/scene.meshes") return WebResource::kSceneMeshes;
  return WebResource::kNotFound;
}

std::string query_param(const std::string& resource, const std::string& key) noexcept {
  try {
    const size_t q = resource.find('?');
    if (q == std::string::npos || key.empty()) return "";
    const std::string query = resource.substr(q + 1, resource.find('#', q) - q - 1);
    for (size_t at = 0; at <= query.size();) {
      size_t end = query.find('&', at);
      if (end == std::string::npos) end = query.size();
      const std::string kv = query.substr(at, end - at);
      at = end + 1;
      if (kv.size() <= key.size() || kv.compare(0, key.size(), key) != 0 || kv[key.size()] != '=') continue;
      std::string v;
      const std::string raw = kv.substr(key.size() + 1);
      for (size_t i = 0; i < raw.size(); ++i) {
        if (raw[i] == '%') {
          if (i + 2 >= raw.size() || !std::isxdigit(static_cast<unsigned char>(raw[i + 1])) ||
              !std::isxdigit(static_cast<unsigned char>(raw[i + 2])))
            return "";
          v.push_back(static_cast<char>(std::stoi(raw.substr(i + 1, 2), nullptr, 16)));
          i += 2;
        } else {
          v.push_back(raw[i] == '+' ? ' ' : raw[i]);
        }
      }
      return v;
    }
  } catch (...) {
  }
  return "";
}

std::string cookie_value(const std::string& header, const std::string& name) noexcept {
  try {
    for (size_t at = 0; at < header.size();) {
      size_t end = header.find(';', at);
      if (end == std::string::npos) end = header.size();
      size_t b = at;
      while (b < end && header[b] == ' ') ++b;
      at = end + 1;
      const size_t eq = header.find('=', b);
      if (eq == std::string::npos || eq >= end) continue;
      if (header.compare(b, eq - b, name) == 0 && eq - b == name.size()) return header.substr(eq + 1, end - eq - 1);
    }
  } catch (...) {
  }
  return "";
}

bool same_origin(const std::string& origin, const std::string& host, bool tls) noexcept {
  if (origin.empty()) return true;
  const std::string scheme = tls ? "https://" : "http://";
  if (host.empty() || origin.size() != scheme.size() + host.size() || origin.compare(0, scheme.size(), scheme) != 0)
    return false;
  for (size_t i = 0; i < host.size(); ++i)
    if (std::tolower(static_cast<unsigned char>(origin[scheme.size() + i])) != std::tolower(static_cast<unsigned char>(host[i])))
      return false;
  return true;
}

}  // namespace haptree
