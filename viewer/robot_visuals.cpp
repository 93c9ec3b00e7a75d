#include "viewer/robot_visuals.hpp"

#include <tinyxml.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>

namespace haptree {
namespace {

std::string lower_ext(const std::string& path) {
  const size_t dot = path.find_last_of('.');
  std::string e = dot == std::string::npos ? "" : path.substr(dot + 1);
  for (auto& c : e) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return e;
}

std::string slurp(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error(path + ": cannot open");
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

void check_finite(const TriMesh& m, const std::string& path) {
  for (const Vec3& v : m.v)
    if (!v.allFinite()) throw std::runtime_error(path + ": a vertex is not finite");
  for (const auto& f : m.f)
    for (uint32_t i : f)
      if (i >= m.v.size()) throw std::runtime_error(path + ": a face names vertex " + std::to_string(i) + " of " +
                                                    std::to_string(m.v.size()));
}

// STL: binary when 84 + 50 n bytes match its triangle count (an ASCII file may also begin with "solid").
TriMesh load_stl(const std::string& path) {
  const std::string b = slurp(path);
  TriMesh m;
  if (b.size() >= 84) {
    uint32_t n = 0;
    std::memcpy(&n, b.data() + 80, 4);
    if (static_cast<uint64_t>(n) * 50 + 84 == b.size()) {
      for (uint32_t t = 0; t < n; ++t) {
        const char* p = b.data() + 84 + 50 * static_cast<size_t>(t) + 12;
        for (int k = 0; k < 3; ++k) {
          float xyz[3];
          std::memcpy(xyz, p + 12 * k, 12);
          m.v.emplace_back(xyz[0], xyz[1], xyz[2]);
        }
        m.f.push_back({3 * t, 3 * t + 1, 3 * t + 2});
      }
      check_finite(m, path);
      return m;
    }
  }
  if (b.compare(0, 5, "solid") != 0) throw std::runtime_error(path + ": neither binary STL (size) nor ASCII STL");
  std::istringstream in(b);
  std::string w;
  int in_facet = 0;
  while (in >> w) {
    if (w == "vertex") {
      Vec3 v;
      if (!(in >> v.x() >> v.y() >> v.z())) throw std::runtime_error(path + ": a malformed vertex line");
      m.v.push_back(v);
      if (++in_facet == 3) {
        const auto k = static_cast<uint32_t>(m.v.size());
        m.f.push_back({k - 3, k - 2, k - 1});
      }
    } else if (w == "endloop") {
      if (in_facet != 3) throw std::runtime_error(path + ": a facet without 3 vertices");
      in_facet = 0;
    }
  }
  if (m.f.empty()) throw std::runtime_error(path + ": no facet");
  check_finite(m, path);
  return m;
}

// OBJ: v and f lines (f: v, v/t, v//n, v/t/n; negative = from the end; polygons as fans).
TriMesh load_obj(const std::string& path) {
  std::istringstream in(slurp(path));
  TriMesh m;
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream ls(line);
    std::string tag;
    ls >> tag;
    if (tag == "v") {
      Vec3 v;
      if (!(ls >> v.x() >> v.y() >> v.z())) throw std::runtime_error(path + ": a malformed v line");
      m.v.push_back(v);
    } else if (tag == "f") {
      std::vector<uint32_t> poly;
      std::string tok;
      while (ls >> tok) {
        long i = std::strtol(tok.c_str(), nullptr, 10);
        if (i < 0) i += static_cast<long>(m.v.size()) + 1;
        if (i < 1 || i > static_cast<long>(m.v.size())) throw std::runtime_error(path + ": a face names a missing vertex");
        poly.push_back(static_cast<uint32_t>(i - 1));
      }
      for (size_t k = 2; k < poly.size(); ++k) m.f.push_back({poly[0], poly[k - 1], poly[k]});
    }
  }
  if (m.f.empty()) throw std::runtime_error(path + ": no face");
  check_finite(m, path);
  return m;
}

std::vector<double> numbers(const char* text) {
  std::vector<double> out;
  if (!text) return out;
  std::istringstream in(text);
  double x;
  while (in >> x) out.push_back(x);
  return out;
}

const TiXmlElement* child(const TiXmlElement* e, const char* name) { return e ? e->FirstChildElement(name) : nullptr; }

// Collada: each <geometry>'s <mesh> (POSITION source; <triangles>, <polylist>, <polygons> with their <p>
// index lists and input offsets), placed by the <node> transforms (<matrix>, <translate>, <rotate>,
// <scale>) of the visual scene that instantiate it, in metres by <asset><unit meter>; Z_UP assumed
// (Y_UP rotated to Z up).
struct DaeLoader {
  std::string path;
  std::map<std::string, const TiXmlElement*> geometries;
  TriMesh out;

  static std::string ref(const char* url) { return url && url[0] == '#' ? std::string(url + 1) : std::string(url ? url : ""); }

  void add_geometry(const TiXmlElement* geom, const Eigen::Matrix4d& T) {
    const TiXmlElement* mesh = child(geom, "mesh");
    if (!mesh) return;
    std::map<std::string, std::vector<double>> sources;
    for (auto* s = mesh->FirstChildElement("source"); s; s = s->NextSiblingElement("source"))
      if (s->Attribute("id")) sources[s->Attribute("id")] = numbers(child(s, "float_array") ? child(s, "float_array")->GetText() : nullptr);
    std::map<std::string, std::string> vertices_src;   // <vertices id> -> POSITION source
    for (auto* v = mesh->FirstChildElement("vertices"); v; v = v->NextSiblingElement("vertices"))
      for (auto* in = v->FirstChildElement("input"); in; in = in->NextSiblingElement("input"))
        if (in->Attribute("semantic") && std::string(in->Attribute("semantic")) == "POSITION" && v->Attribute("id"))
          vertices_src[v->Attribute("id")] = ref(in->Attribute("source"));
    for (const char* kind : {"triangles", "polylist", "polygons"}) {
      for (auto* prim = mesh->FirstChildElement(kind); prim; prim = prim->NextSiblingElement(kind)) {
        int stride = 0, voff = -1;
        std::string src;
        for (auto* in = prim->FirstChildElement("input"); in; in = in->NextSiblingElement("input")) {
          int off = 0;
          in->QueryIntAttribute("offset", &off);
          stride = std::max(stride, off + 1);
          if (in->Attribute("semantic") && std::string(in->Attribute("semantic")) == "VERTEX") {
            voff = off;
            const std::string s = ref(in->Attribute("source"));
            src = vertices_src.count(s) ? vertices_src[s] : s;
          }
        }
        if (voff < 0 || !sources.count(src)) throw std::runtime_error(path + ": a <" + std::string(kind) + "> without positions");
        const std::vector<double>& P = sources[src];
        const uint32_t base = static_cast<uint32_t>(out.v.size());
        for (size_t i = 0; i + 2 < P.size(); i += 3) {
          const Eigen::Vector4d x = T * Eigen::Vector4d(P[i], P[i + 1], P[i + 2], 1.0);
          out.v.emplace_back(x.x(), x.y(), x.z());
        }
        const uint32_t nv = static_cast<uint32_t>(P.size() / 3);
        auto fan = [&](const std::vector<double>& idx, size_t first, size_t count) {
          std::vector<uint32_t> poly;
          for (size_t k = 0; k < count; ++k) {
            const size_t at = (first + k) * static_cast<size_t>(stride) + static_cast<size_t>(voff);
            if (at >= idx.size() || idx[at] < 0 || idx[at] >= nv) throw std::runtime_error(path + ": an index out of range");
            poly.push_back(base + static_cast<uint32_t>(idx[at]));
          }
          for (size_t k = 2; k < poly.size(); ++k) out.f.push_back({poly[0], poly[k - 1], poly[k]});
        };
        const std::string k = kind;
        if (k == "triangles") {
          const std::vector<double> idx = numbers(child(prim, "p") ? child(prim, "p")->GetText() : nullptr);
          for (size_t t = 0; (t + 1) * 3 * static_cast<size_t>(stride) <= idx.size(); ++t) fan(idx, 3 * t, 3);
        } else if (k == "polylist") {
          const std::vector<double> idx = numbers(child(prim, "p") ? child(prim, "p")->GetText() : nullptr);
          const std::vector<double> vc = numbers(child(prim, "vcount") ? child(prim, "vcount")->GetText() : nullptr);
          size_t first = 0;
          for (double c : vc) {
            if (c < 3 || c > 1e6) throw std::runtime_error(path + ": a polygon of " + std::to_string(c) + " vertices");
            fan(idx, first, static_cast<size_t>(c));
            first += static_cast<size_t>(c);
          }
        } else {
          for (auto* p = prim->FirstChildElement("p"); p; p = p->NextSiblingElement("p")) {
            const std::vector<double> idx = numbers(p->GetText());
            fan(idx, 0, idx.size() / static_cast<size_t>(stride));
          }
        }
      }
    }
  }

  static Eigen::Matrix4d node_transform(const TiXmlElement* node) {
    Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
    for (auto* e = node->FirstChildElement(); e; e = e->NextSiblingElement()) {
      const std::string v = e->Value();
      const std::vector<double> n = numbers(e->GetText());
      Eigen::Matrix4d M = Eigen::Matrix4d::Identity();
      if (v == "matrix" && n.size() == 16) {
        for (int r = 0; r < 4; ++r)
          for (int c = 0; c < 4; ++c) M(r, c) = n[static_cast<size_t>(4 * r + c)];
      } else if (v == "translate" && n.size() == 3) {
        M.block<3, 1>(0, 3) = Vec3(n[0], n[1], n[2]);
      } else if (v == "rotate" && n.size() == 4 && Vec3(n[0], n[1], n[2]).norm() > 0) {
        M.block<3, 3>(0, 0) = Eigen::AngleAxisd(n[3] * M_PI / 180.0, Vec3(n[0], n[1], n[2]).normalized()).toRotationMatrix();
      } else if (v == "scale" && n.size() == 3) {
        M.diagonal().head<3>() = Vec3(n[0], n[1], n[2]);
      } else {
        continue;
      }
      T = T * M;
    }
    return T;
  }

  void walk(const TiXmlElement* node, const Eigen::Matrix4d& parent, int depth) {
    if (depth > 64) throw std::runtime_error(path + ": nodes nested deeper than 64");
    const Eigen::Matrix4d T = parent * node_transform(node);
    for (auto* ig = node->FirstChildElement("instance_geometry"); ig; ig = ig->NextSiblingElement("instance_geometry")) {
      const auto it = geometries.find(ref(ig->Attribute("url")));
      if (it != geometries.end()) add_geometry(it->second, T);
    }
    for (auto* n = node->FirstChildElement("node"); n; n = n->NextSiblingElement("node")) walk(n, T, depth + 1);
  }

  TriMesh load() {
    const std::string text = slurp(path);
    TiXmlDocument doc;
    doc.Parse(text.c_str());
    if (doc.Error()) throw std::runtime_error(path + ": XML: " + doc.ErrorDesc());
    const TiXmlElement* root = doc.RootElement();
    if (!root || std::string(root->Value()) != "COLLADA") throw std::runtime_error(path + ": not a COLLADA file");
    double unit = 1.0;
    Eigen::Matrix4d up = Eigen::Matrix4d::Identity();
    if (const TiXmlElement* asset = child(root, "asset")) {
      if (const TiXmlElement* u = child(asset, "unit")) u->QueryDoubleAttribute("meter", &unit);
      if (const TiXmlElement* a = child(asset, "up_axis"); a && a->GetText() && std::string(a->GetText()) == "Y_UP")
        up.block<3, 3>(0, 0) = Eigen::AngleAxisd(M_PI / 2, Vec3::UnitX()).toRotationMatrix();
    }
    if (!(unit > 0 && std::isfinite(unit))) throw std::runtime_error(path + ": unit meter must be positive");
    for (auto* lib = root->FirstChildElement("library_geometries"); lib; lib = lib->NextSiblingElement("library_geometries"))
      for (auto* g = lib->FirstChildElement("geometry"); g; g = g->NextSiblingElement("geometry"))
        if (g->Attribute("id")) geometries[g->Attribute("id")] = g;
    Eigen::Matrix4d S = up;
    S.block<3, 3>(0, 0) *= unit;
    bool scene = false;
    for (auto* lib = root->FirstChildElement("library_visual_scenes"); lib; lib = lib->NextSiblingElement("library_visual_scenes"))
      for (auto* vs = lib->FirstChildElement("visual_scene"); vs; vs = vs->NextSiblingElement("visual_scene"))
        for (auto* n = vs->FirstChildElement("node"); n; n = n->NextSiblingElement("node")) walk(n, S, 0), scene = true;
    if (!scene)   // no scene: every geometry as it is
      for (const auto& kv : geometries) add_geometry(kv.second, S);
    if (out.f.empty()) throw std::runtime_error(path + ": no triangles");
    check_finite(out, path);
    return out;
  }
};

Vec3 parse_vec3(const char* s, const Vec3& fallback) {
  const std::vector<double> n = numbers(s);
  return n.size() == 3 ? Vec3(n[0], n[1], n[2]) : fallback;
}

struct Pose {
  Mat3 R = Mat3::Identity();
  Vec3 p = Vec3::Zero();
  Pose operator*(const Pose& o) const { return {R * o.R, R * o.p + p}; }
};

Pose parse_origin(const TiXmlElement* parent) {
  Pose P;
  const TiXmlElement* o = child(parent, "origin");
  if (!o) return P;
  P.p = parse_vec3(o->Attribute("xyz"), Vec3::Zero());
  const Vec3 rpy = parse_vec3(o->Attribute("rpy"), Vec3::Zero());
  P.R = (Eigen::AngleAxisd(rpy.z(), Vec3::UnitZ()) * Eigen::AngleAxisd(rpy.y(), Vec3::UnitY()) *
         Eigen::AngleAxisd(rpy.x(), Vec3::UnitX())).toRotationMatrix();
  return P;
}

bool parse_rgba(const TiXmlElement* material, Vec3& rgb) {
  const TiXmlElement* c = child(material, "color");
  if (!c) return false;
  const std::vector<double> n = numbers(c->Attribute("rgba"));
  if (n.size() < 3) return false;
  rgb = Vec3(n[0], n[1], n[2]).cwiseMax(0.0).cwiseMin(1.0);
  return rgb.allFinite();
}

// Unit primitives as triangle lists.
TriMesh box(const Vec3& size) {
  TriMesh m;
  const Vec3 h = size / 2;
  for (int i = 0; i < 8; ++i) m.v.emplace_back((i & 1 ? 1 : -1) * h.x(), (i & 2 ? 1 : -1) * h.y(), (i & 4 ? 1 : -1) * h.z());
  const uint32_t q[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4}, {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
  for (const auto& f : q) m.f.push_back({f[0], f[1], f[2]}), m.f.push_back({f[0], f[2], f[3]});
  return m;
}

TriMesh cylinder(double r, double len, int seg = 24) {
  TriMesh m;
  for (int i = 0; i < seg; ++i) {
    const double a = 2 * M_PI * i / seg;
    m.v.emplace_back(r * std::cos(a), r * std::sin(a), -len / 2);
    m.v.emplace_back(r * std::cos(a), r * std::sin(a), len / 2);
  }
  const auto c0 = static_cast<uint32_t>(m.v.size());
  m.v.emplace_back(0, 0, -len / 2);
  m.v.emplace_back(0, 0, len / 2);
  for (int i = 0; i < seg; ++i) {
    const uint32_t a = static_cast<uint32_t>(2 * i), b = static_cast<uint32_t>(2 * ((i + 1) % seg));
    m.f.push_back({a, b, b + 1});
    m.f.push_back({a, b + 1, a + 1});
    m.f.push_back({c0, b, a});
    m.f.push_back({c0 + 1, a + 1, b + 1});
  }
  return m;
}

TriMesh sphere(double r, int rings = 12, int seg = 20) {
  TriMesh m;
  for (int i = 0; i <= rings; ++i) {
    const double t = M_PI * i / rings;
    for (int j = 0; j < seg; ++j) {
      const double p = 2 * M_PI * j / seg;
      m.v.emplace_back(r * std::sin(t) * std::cos(p), r * std::sin(t) * std::sin(p), r * std::cos(t));
    }
  }
  for (int i = 0; i < rings; ++i)
    for (int j = 0; j < seg; ++j) {
      const auto a = static_cast<uint32_t>(i * seg + j), b = static_cast<uint32_t>(i * seg + (j + 1) % seg);
      m.f.push_back({a, a + static_cast<uint32_t>(seg), b + static_cast<uint32_t>(seg)});
      m.f.push_back({a, b + static_cast<uint32_t>(seg), b});
    }
  return m;
}

void append(BodyVisual& out, const TriMesh& m, const Pose& P, const Vec3& scale, const Vec3& rgb) {
  const bool mirrored = scale.prod() < 0;   // a negative scale turns the faces inside out
  for (const auto& f : m.f) {
    Vec3 x[3];
    for (int k = 0; k < 3; ++k) x[k] = P.R * m.v[f[static_cast<size_t>(mirrored ? 2 - k : k)]].cwiseProduct(scale) + P.p;
    Vec3 n = (x[1] - x[0]).cross(x[2] - x[0]);
    n = n.norm() > 0 ? Vec3(n.normalized()) : Vec3::UnitZ();
    for (int k = 0; k < 3; ++k)
      for (int a = 0; a < 3; ++a) {
        out.position.push_back(static_cast<float>(x[k][a]));
        out.normal.push_back(static_cast<float>(n[a]));
        out.color.push_back(static_cast<float>(rgb[a]));
      }
  }
}

std::string resolve_mesh(const std::string& name, const std::string& urdf_dir, const std::vector<std::string>& dirs) {
  auto exists = [](const std::string& p) { return std::ifstream(p).good(); };
  std::string rel = name;
  std::vector<std::string> tries;
  if (rel.rfind("file://", 0) == 0) return rel.substr(7);
  if (rel.rfind("package://", 0) == 0) {
    rel = rel.substr(10);   // PKG/path: try PKG/path, then path, in each directory
    const size_t slash = rel.find('/');
    for (const auto& d : dirs) {
      tries.push_back(d + "/" + rel);
      if (slash != std::string::npos) tries.push_back(d + "/" + rel.substr(slash + 1));
    }
    if (slash != std::string::npos) tries.push_back(urdf_dir + "/" + rel.substr(slash + 1));
  } else if (!rel.empty() && rel[0] == '/') {
    return rel;
  } else {
    for (const auto& d : dirs) tries.push_back(d + "/" + rel);
    tries.push_back(urdf_dir + "/" + rel);
  }
  for (const auto& t : tries)
    if (exists(t)) return t;
  return "";
}

}  // namespace

TriMesh load_mesh_file(const std::string& path) {
  const std::string e = lower_ext(path);
  if (e == "stl") return load_stl(path);
  if (e == "obj") return load_obj(path);
  if (e == "dae") return DaeLoader{path, {}, {}}.load();
  throw std::runtime_error(path + ": unknown mesh format ." + e + " (STL, OBJ, DAE)");
}

RobotVisuals load_robot_visuals(const std::string& urdf_path, const Model& model,
                                const std::vector<std::string>& mesh_paths) {
  const std::string text = slurp(urdf_path);
  TiXmlDocument doc;
  doc.Parse(text.c_str());
  if (doc.Error()) throw std::runtime_error(urdf_path + ": XML: " + doc.ErrorDesc());
  const TiXmlElement* robot = doc.RootElement();
  if (!robot) throw std::runtime_error(urdf_path + ": empty");
  const size_t slash = urdf_path.find_last_of('/');
  const std::string dir = slash == std::string::npos ? "." : urdf_path.substr(0, slash);
  std::map<std::string, Vec3> materials;   // <robot>-level named colours
  for (auto* m = robot->FirstChildElement("material"); m; m = m->NextSiblingElement("material")) {
    Vec3 c;
    if (m->Attribute("name") && parse_rgba(m, c)) materials[m->Attribute("name")] = c;
  }
  // child link -> (parent link, joint origin): links missing from the model were lumped into an ancestor
  std::map<std::string, std::pair<std::string, Pose>> up;
  for (auto* j = robot->FirstChildElement("joint"); j; j = j->NextSiblingElement("joint")) {
    const TiXmlElement *p = child(j, "parent"), *c = child(j, "child");
    if (p && c && p->Attribute("link") && c->Attribute("link")) up[c->Attribute("link")] = {p->Attribute("link"), parse_origin(j)};
  }
  RobotVisuals out;
  std::map<int, size_t> slot;
  std::set<std::string> warned;
  for (auto* link = robot->FirstChildElement("link"); link; link = link->NextSiblingElement("link")) {
    if (!link->Attribute("name") || !child(link, "visual")) continue;
    // the body carrying this link and the link's pose in that body's frame
    std::string name = link->Attribute("name");
    Pose in_body;
    int body = -1;
    for (int hops = 0; hops < 1000; ++hops) {
      body = name == "world" ? 0 : model.body_index(name);
      if (body >= 0) break;
      const auto it = up.find(name);
      if (it == up.end()) break;
      in_body = it->second.second * in_body;
      name = it->second.first;
    }
    if (body < 0) body = 0;   // a root that is not a body: the ground
    if (!slot.count(body)) {
      slot[body] = out.bodies.size();
      out.bodies.push_back(BodyVisual{});
      out.bodies.back().body = body;
    }
    BodyVisual& bv = out.bodies[slot[body]];
    for (auto* vis = link->FirstChildElement("visual"); vis; vis = vis->NextSiblingElement("visual")) {
      const Pose P = in_body * parse_origin(vis);
      Vec3 rgb(0.72, 0.74, 0.78);
      if (const TiXmlElement* mat = child(vis, "material")) {
        Vec3 c;
        if (parse_rgba(mat, c)) rgb = c;
        else if (mat->Attribute("name") && materials.count(mat->Attribute("name"))) rgb = materials[mat->Attribute("name")];
      }
      const TiXmlElement* g = child(vis, "geometry");
      if (!g) continue;
      if (const TiXmlElement* e = child(g, "box")) {
        append(bv, box(parse_vec3(e->Attribute("size"), Vec3::Constant(0.1)).cwiseAbs()), P, Vec3::Ones(), rgb);
        ++out.primitives;
      } else if (const TiXmlElement* e = child(g, "cylinder")) {
        double r = 0.05, l = 0.1;
        e->QueryDoubleAttribute("radius", &r);
        e->QueryDoubleAttribute("length", &l);
        append(bv, cylinder(std::abs(r), std::abs(l)), P, Vec3::Ones(), rgb);
        ++out.primitives;
      } else if (const TiXmlElement* e = child(g, "sphere")) {
        double r = 0.05;
        e->QueryDoubleAttribute("radius", &r);
        append(bv, sphere(std::abs(r)), P, Vec3::Ones(), rgb);
        ++out.primitives;
      } else if (const TiXmlElement* e = child(g, "mesh")) {
        const std::string file = e->Attribute("filename") ? e->Attribute("filename") : "";
        const Vec3 scale = parse_vec3(e->Attribute("scale"), Vec3::Ones());
        std::string why;
        const std::string found = resolve_mesh(file, dir, mesh_paths);
        if (found.empty()) {
          why = "not found (give its folder with --mesh-path)";
        } else {
          try {
            append(bv, load_mesh_file(found), P, scale, rgb);
            ++out.meshes;
            continue;
          } catch (const std::exception& ex) {
            why = ex.what();
          }
        }
        // drawn as the body's sphere: the solid sphere with its mass and trace of inertia
        const double m = model.mass[static_cast<size_t>(body)];
        const double tr = model.inertia[static_cast<size_t>(body)].trace();
        const double r = m > 0 && tr > 0 ? std::sqrt(5 * tr / (6 * m)) : 0.05;
        append(bv, sphere(r), P, Vec3::Ones(), rgb);
        ++out.missing;
        if (warned.insert(file).second)
          out.warnings.push_back("mesh '" + file + "' of link '" + std::string(link->Attribute("name")) + "': " + why +
                                 "; drawn as a sphere of radius " + std::to_string(r) + " m");
      }
    }
  }
  out.bodies.erase(std::remove_if(out.bodies.begin(), out.bodies.end(), [](const BodyVisual& b) { return b.position.empty(); }),
                   out.bodies.end());
  return out;
}

}  // namespace haptree
