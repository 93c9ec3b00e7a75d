#include "viewer/viewer.hpp"
#include "viewer/robot_visuals.hpp"

#define ASIO_STANDALONE
#define _WEBSOCKETPP_CPP11_STL_
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>
#include <sodium.h>
#include <websocketpp/config/asio.hpp>
#include <websocketpp/config/asio_no_tls.hpp>
#include <websocketpp/server.hpp>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <array>
#include <limits>
#include <map>
#include <mutex>
#include <set>
#include <sstream>
#include <stdexcept>
#include <unistd.h>
#include <vector>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/dca.hpp"
#include "haptree/io/urdf.hpp"
#include "haptree/lcmt_device_state.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "haptree/lcmt_pointer.hpp"
#include "haptree/lcmt_process_stats.hpp"
#include "haptree/lcmt_scene_state.hpp"
#include "haptree/lcmt_user_force.hpp"
#include "haptree/molecule/scene.hpp"
#include "haptree/scenes.hpp"

#ifndef HAPTREE_VIEWER_WEB_DIR
#define HAPTREE_VIEWER_WEB_DIR ""
#endif

namespace haptree {

using json = nlohmann::json;
using WsServer = websocketpp::server<websocketpp::config::asio>;
using WssServer = websocketpp::server<websocketpp::config::asio_tls>;
using Hdl = websocketpp::connection_hdl;
using Clock = std::chrono::steady_clock;

namespace {

bool is_procedural(const std::string& s) {
  return s == "chain" || s == "binary_tree" || s == "random_tree" || s == "star" || s == "protein_like";
}

std::string read_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error("viewer: cannot read " + path);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

std::string find_web_dir(const std::string& given) {
  std::vector<std::string> tried;
  auto ok = [&](const std::string& d) {
    tried.push_back(d);
    return !d.empty() && std::ifstream(d + "/index.html").good();
  };
  if (!given.empty()) {
    if (ok(given)) return given;
  } else {
    if (const char* e = std::getenv("HAPTREE_VIEWER_WEB_DIR"); e && ok(e)) return e;
    char exe[4096];
    const ssize_t n = readlink("/proc/self/exe", exe, sizeof(exe) - 1);
    if (n > 0) {
      std::string dir(exe, static_cast<size_t>(n));
      dir = dir.substr(0, dir.find_last_of('/'));
      for (const std::string& d : {dir + "/web", dir + "/../share/haptree/viewer/web"})
        if (ok(d)) return d;
    }
    if (ok(HAPTREE_VIEWER_WEB_DIR)) return HAPTREE_VIEWER_WEB_DIR;
  }
  std::string list;
  for (const auto& t : tried) list += (list.empty() ? "" : ", ") + t;
  throw std::runtime_error("viewer: no web page (index.html) in " + list + "; give --web-dir");
}

struct UserSlot {
  // from the bus (under Impl::mutex)
  bool uf_active = false;
  int uf_body = 0;
  Vec3 uf_point = Vec3::Zero();
  bool have_device = false;
  Vec3 device_m = Vec3::Zero();
  int buttons = 0, device_grab_body = 0, device_grab_seq = 0;
  bool have_feedback = false;
  Vec3 force_n = Vec3::Zero();
  int flags = 0;
  bool have_mapping = false;
  double position_scale = 1, force_scale = 1, max_force_n = 0;
  Vec3 offset = Vec3::Zero();
  double rate_hz = 0, p99_us = 0, snapshot_age_ms = -1;
  int64_t watchdog_events = 0, clamp_events = 0;
  // handler-thread state: next time a high-rate channel is decoded (steady clock, s)
  double next_feedback_s = 0, next_device_s = 0, next_user_force_s = 0;
  // frame-thread state: the grab's material point in the body frame
  int track_body = 0;
  Vec3 track_key = Vec3::Constant(std::nan("")), track_local = Vec3::Zero();
};

// One frame, one binary WebSocket message: "HTF1", the JSON's length (uint32, little-endian, a multiple of
// 4), the JSON (overlays + HUD) padded with spaces, then x y z per display point as float32 (none when
// the scene did not move since this tab's last frame).
void encode_frame(const std::string& json_text, const float* pos, size_t nfloats, std::string& out) {
  const size_t padded = (json_text.size() + 3) & ~size_t{3};
  out.assign(8 + padded + 4 * nfloats, ' ');
  std::memcpy(out.data(), "HTF1", 4);
  const uint32_t n = static_cast<uint32_t>(padded);
  const unsigned char le[4] = {static_cast<unsigned char>(n), static_cast<unsigned char>(n >> 8),
                               static_cast<unsigned char>(n >> 16), static_cast<unsigned char>(n >> 24)};
  std::memcpy(out.data() + 4, le, 4);
  std::memcpy(out.data() + 8, json_text.data(), json_text.size());
  if (nfloats) std::memcpy(out.data() + 8 + padded, pos, 4 * nfloats);   // x86/ARM: little-endian floats
}

enum class Role { kNone, kWatch, kPull };
enum class Refusal { kNoToken, kWrongToken, kForeignOrigin, kWatchPull };
const char* refusal_text(Refusal r) {
  switch (r) {
    case Refusal::kNoToken: return "no token (open the URL the viewer printed, with ?token=)";
    case Refusal::kWrongToken: return "wrong token";
    case Refusal::kForeignOrigin: return "WebSocket from a page of another origin";
    case Refusal::kWatchPull: return "a watch-only token tried to pull";
  }
  return "";
}

using TokenHash = std::array<unsigned char, crypto_generichash_BYTES>;
TokenHash hash_token(const std::string& t) {
  TokenHash h{};
  crypto_generichash(h.data(), h.size(), reinterpret_cast<const unsigned char*>(t.data()), t.size(), nullptr, 0);
  return h;
}

struct Client {
  int64_t id = 0;
  Role role = Role::kPull;
  int user = -1;            // -1: spectator (watch token, or no free user)
  std::string address;
  bool down = false;
  int body = 0;
  Vec3 target_scene = Vec3::Zero();
  bool have_target = false;
  int64_t mask_sent = -1;   // active-mask version this client has
  int64_t updates_sent = -1, scene_sent = -1;   // Impl::updates and scene_msgs of its last frame
  Clock::time_point last_frame{};
  bool due = false;
  int64_t frames_sent = 0;     // frames sent on this socket
  int64_t frames_acked = -1;   // frames the page said it received; -1: it never acknowledges (no window)
};

}  // namespace

struct Viewer::Impl {
  bus::Bus& bus;
  ViewerOptions opt;
  std::shared_ptr<const Model> model;
  std::unique_ptr<mol::MolecularScene> mol;
  // display points: atoms (molecules) or bodies (procedural, URDF); point i sits on body point_body[i]
  std::vector<int> point_body;
  std::vector<Vec3> point_local;
  double disp_scale = 10;        // display unit (Å) per scene unit
  Vec3 disp_center = Vec3::Zero();
  std::string pdb, index_html, viewer_js, ngl_js, ngl_license, scene_json;
  std::string meshes_bin;   // /scene.meshes: the robot's visuals per body (robot_visuals.hpp), display units
  bool with_quats = false;  // frames carry each body's orientation after the points (robots with visuals)
  // bus slots
  std::mutex mutex;
  std::vector<Vec3> r;
  std::vector<Quat> q;
  std::vector<char> active;
  int64_t scene_utime = 0;
  int64_t mask_version = 0, scene_version = -1, scene_msgs = 0, wrong_size = 0;
  double sim_time = 0, step_ms = 0, neglected = 0, sim_rate = 0, sim_resets = 0;
  int active_dofs = 0;
  std::vector<UserSlot> users;
  // access: tokens compared as fixed-size hashes in constant time (sodium_memcmp)
  bool open_access = false, tls = false;
  std::string pull_token, watch_token, cookie_name;
  TokenHash pull_hash{}, watch_hash{};
  std::array<std::atomic<int64_t>, 4> refused{};
  std::set<std::pair<std::string, int>> refusals_logged;   // (client address, reason): logged once
  // server thread: one of the two servers (plain or TLS), the same handlers on either
  std::unique_ptr<WsServer> plain;
  std::unique_ptr<WssServer> secure;
  std::shared_ptr<asio::ssl::context> tls_context;
  template <class F>
  void net(F&& f) {
    if (secure) f(*secure);
    else f(*plain);
  }
  std::unique_ptr<asio::steady_timer> timer;
  std::map<Hdl, Client, std::owner_less<Hdl>> clients;
  int64_t next_client = 1, pointer_seq = 0;
  const int64_t instance_id = bus::new_instance_id();
  std::vector<float> frame_pos;
  std::string msg_buf;
  int64_t updates = 0;   // under mutex: +1 per bus message that changes what a frame shows
  std::vector<Vec3> x_scene;
  std::atomic<int64_t> frames_sent{0}, frames_dropped{0}, pointer_msgs{0}, frame_bytes{0};
  std::atomic<int> nclients{0};
  int bound_port = 0;
  Clock::time_point next_keepalive = Clock::now(), next_stats = Clock::now() + std::chrono::seconds(1);
  int64_t frames_at_stats = 0, seq_stats = 0, frame_seq = 0;

  Impl(bus::Bus& b, const ViewerOptions& o) : bus(b), opt(o) {}

  // Handler thread: true at most once per 4 ms per channel (250 Hz, above any display rate).
  static bool due(double& next_s) {
    const double now = std::chrono::duration<double>(Clock::now().time_since_epoch()).count();
    if (now < next_s) return false;
    next_s = now + 0.004;
    return true;
  }

  void load_scene();
  void subscribe();
  void setup_access();
  void start_server();
  template <class S>
  void start_on(S& srv);
  Vec3 to_disp(const Vec3& x) const { return (x - disp_center) * disp_scale; }
  Vec3 from_disp(const Vec3& p) const { return p / disp_scale + disp_center; }
  Role role_of(const std::string& token) const;
  void refuse(Refusal r, const std::string& who, const std::string& what);
  // The role a request's token gives (query ?token= first, else the cookie); kNone is counted and logged
  // when count is true. from_query: the token came in the URL (the page then sets the cookie).
  template <class Con>
  Role authorize(Con& con, bool count, bool* from_query = nullptr);
  template <class S>
  void on_http(S& srv, Hdl h);
  template <class S>
  bool on_validate(S& srv, Hdl h);
  template <class S>
  void on_open(S& srv, Hdl h);
  void on_close(Hdl h);
  void on_message(Hdl h, const std::string& payload);
  void publish_pointer(const Client& c, bool button);
  void tick();
  void schedule();
  // Last member: destroyed first, so no bus callback (they capture this) runs into freed members.
  bus::SubscriptionGuard subs;
};

void Viewer::Impl::load_scene() {
  if (!opt.urdf.empty()) {
    model = io::load_urdf(opt.urdf, {});
  } else if (is_procedural(opt.scene)) {
    SceneOptions so;
    so.n = opt.n;
    if (opt.scene == "random_tree") so.seed = 1;   // as sim_server
    model = make_scene(opt.scene, so);
  } else {
    mol::SceneOptions mo;
    mo.with_force_field = false;   // only the torsion model: where each atom sits on its body
    mol = std::make_unique<mol::MolecularScene>(mol::load_molecular_scene(opt.scene, mo));
    model = mol->model;
  }
  Data d(*model);
  State s(*model);
  forward_kinematics(*model, d, s.q);
  const int nb = model->nbodies;
  if (mol) {
    const int na = mol->natoms();
    point_body = mol->torsion.atom_model_body;
    point_local = mol->torsion.atom_local;
    disp_scale = 10;   // nm -> Å
    std::vector<Vec3> x;
    mol->atom_positions(d, x);
    char tmpl[] = "/tmp/haptree_viewer_XXXXXX";
    const int fd = mkstemp(tmpl);
    if (fd < 0) throw std::runtime_error("viewer: mkstemp failed");
    close(fd);
    mol::write_pdb(tmpl, mol->structure, x);
    pdb = read_file(tmpl);
    std::remove(tmpl);
    (void)na;
  } else {
    // one point per body origin (body 0 = the ground), bonds parent -> child
    point_body.resize(nb);
    point_local.assign(nb, Vec3::Zero());
    Vec3 c = Vec3::Zero();
    for (int k = 0; k < nb; ++k) point_body[k] = k, c += d.r[k];
    c /= nb;
    double ext = 0;
    for (int k = 0; k < nb; ++k) ext = std::max(ext, (d.r[k] - c).norm());
    disp_center = c;
    disp_scale = ext > 0 ? 40.0 / ext : 1.0;   // the scene spans ~80 Å: NGL's default camera and PDB columns
    std::string out;
    char line[128];
    for (int k = 0; k < nb; ++k) {
      const Vec3 p = to_disp(d.r[k]);
      std::snprintf(line, sizeof line, "HETATM%5d  B%-2d BOD A%4d    %8.3f%8.3f%8.3f  1.00  0.00           C\n",
                    (k + 1) % 100000, 0, (k + 1) % 10000, p.x(), p.y(), p.z());
      out += line;
    }
    for (int k = 1; k < nb; ++k) {
      std::snprintf(line, sizeof line, "CONECT%5d%5d\n", (model->parent[k] + 1) % 100000, (k + 1) % 100000);
      out += line;
    }
    out += "END\n";
    pdb = out;
  }
  if (!opt.urdf.empty()) {
    const RobotVisuals vis = load_robot_visuals(opt.urdf, *model, opt.mesh_paths);
    for (const auto& w : vis.warnings) spdlog::warn("viewer: {}", w);
    if (!vis.bodies.empty()) {
      // a frame's layout: "HTF1", uint32 JSON length, JSON [{body, tris}], then per body float32 position, normal, colour
      // (9 floats per triangle each; positions in the body frame, display units)
      json list = json::array();
      std::string data;
      for (const auto& b : vis.bodies) {
        list.push_back({{"body", b.body}, {"tris", b.position.size() / 9}});
        std::vector<float> p = b.position;
        for (float& x : p) x = static_cast<float>(x * disp_scale);
        for (const std::vector<float>* v : {static_cast<const std::vector<float>*>(&p), &b.normal, &b.color})
          data.append(reinterpret_cast<const char*>(v->data()), v->size() * sizeof(float));
      }
      encode_frame(list.dump(), nullptr, 0, meshes_bin);
      meshes_bin += data;
      with_quats = true;
      spdlog::info("viewer: {} visuals drawn on {} bodies ({} meshes, {} shapes, {} missing meshes as spheres)",
                   vis.meshes + vis.primitives + vis.missing, vis.bodies.size(), vis.meshes, vis.primitives, vis.missing);
    }
  }
  json sj;
  sj["kind"] = mol ? "molecule" : "bodies";
  sj["meshes"] = !meshes_bin.empty();
  sj["quats"] = with_quats;
  sj["scene"] = opt.urdf.empty() ? opt.scene : opt.urdf;
  sj["points"] = static_cast<int>(point_body.size());
  sj["bodies"] = nb - 1;
  sj["dof"] = model->nv;
  sj["users"] = opt.users;
  sj["disp_per_scene_unit"] = disp_scale;
  sj["scene_unit"] = mol ? "nm" : "m";
  sj["point_body"] = point_body;
  scene_json = sj.dump();
  r.assign(nb, Vec3::Zero());
  q.assign(nb, Quat::Identity());
  for (int k = 0; k < nb; ++k) r[k] = d.r[k], q[k] = Quat(d.R[k]);
  active.assign(nb, 0);
  users.assign(static_cast<size_t>(opt.users), UserSlot{});
  x_scene.resize(point_body.size());
  frame_pos.resize(3 * point_body.size() + (with_quats ? 4 * static_cast<size_t>(nb) : 0));
}

void Viewer::Impl::subscribe() {
  const std::string& sfx = opt.channel_suffix;
  subs(bus.subscribe<lcmt_scene_state>(bus::channel::scene_state(sfx), [this](const lcmt_scene_state& m, const std::string&) {
    std::lock_guard<std::mutex> lock(mutex);
    if (m.total_bodies != model->nbodies || m.first_body < 0 || m.first_body + m.nbodies > m.total_bodies) {
      if (wrong_size++ == 0)
        spdlog::warn("viewer: scene state with {} bodies, but the viewer's scene has {} (started with another "
                     "--scene/--n?): ignored", m.total_bodies, model->nbodies);
      return;
    }
    bool mask_changed = false;
    for (int i = 0; i < m.nbodies; ++i) {
      const int k = m.first_body + i;
      const auto& p = m.body_position[i];
      const auto& o = m.body_orientation[i];
      const Vec3 x(p[0], p[1], p[2]);
      Quat qk(o[0], o[1], o[2], o[3]);
      if (!x.allFinite() || !qk.coeffs().allFinite() || qk.norm() < 0.5) continue;
      r[k] = x;
      q[k] = qk.normalized();
      const char a = m.body_active[i] ? 1 : 0;
      if (active[k] != a) active[k] = a, mask_changed = true;
    }
    if (mask_changed) ++mask_version;
    scene_version = m.version;
    scene_utime = m.utime;
    sim_time = m.sim_time;
    step_ms = m.step_ms;
    neglected = m.neglected_metric;
    active_dofs = m.active_dofs;
    ++scene_msgs;
    ++updates;
  }));
  for (int u = 0; u < opt.users; ++u) {
    subs(bus.subscribe_raw(bus::channel::user_force(u, sfx), [this, u](const void* d, uint32_t n, const std::string&) {
      if (!due(users[u].next_user_force_s)) return;
      thread_local lcmt_user_force m;
      if (bus::decode_checked(d, n, m) != bus::DecodeResult::kOk) return;
      std::lock_guard<std::mutex> lock(mutex);
      UserSlot& s = users[u];
      s.uf_active = m.active && m.grab_body >= 1 && m.grab_body < model->nbodies;
      s.uf_body = s.uf_active ? m.grab_body : 0;
      s.uf_point = Vec3(m.grab_point[0], m.grab_point[1], m.grab_point[2]);
      if (!s.uf_point.allFinite()) s.uf_active = false;
      ++updates;
    }));
    subs(bus.subscribe_raw(bus::channel::device_state(u, sfx), [this, u](const void* d, uint32_t n, const std::string&) {
      if (!due(users[u].next_device_s)) return;
      thread_local lcmt_device_state m;
      if (bus::decode_checked(d, n, m) != bus::DecodeResult::kOk) return;
      const Vec3 x(m.position_m[0], m.position_m[1], m.position_m[2]);
      if (!x.allFinite()) return;
      std::lock_guard<std::mutex> lock(mutex);
      users[u].have_device = true;
      users[u].device_m = x;
      users[u].buttons = m.buttons;
      users[u].device_grab_body = m.grab_body;
      users[u].device_grab_seq = m.grab_seq;
      ++updates;
    }));
    subs(bus.subscribe_raw(bus::channel::feedback(u, sfx), [this, u](const void* d, uint32_t n, const std::string&) {
      if (!due(users[u].next_feedback_s)) return;
      thread_local lcmt_feedback m;
      if (bus::decode_checked(d, n, m) != bus::DecodeResult::kOk) return;
      const Vec3 f(m.force_n[0], m.force_n[1], m.force_n[2]);
      std::lock_guard<std::mutex> lock(mutex);
      users[u].have_feedback = true;
      users[u].force_n = f.allFinite() ? f : Vec3::Zero();
      users[u].flags = m.flags;
      ++updates;
    }));
    subs(bus.subscribe<lcmt_process_stats>(bus::channel::stats("coupler_" + std::to_string(u), sfx),
                                      [this, u](const lcmt_process_stats& m, const std::string&) {
      std::lock_guard<std::mutex> lock(mutex);
      UserSlot& s = users[u];
      s.rate_hz = m.loop_rate_hz;
      s.p99_us = m.latency_p99_us;
      s.snapshot_age_ms = m.snapshot_age_ms;
      s.watchdog_events = m.watchdog_events;
      s.clamp_events = m.clamp_events;
      ++updates;
      std::map<std::string, double> ex;
      for (int i = 0; i < m.n_extra && i < static_cast<int>(m.extra_names.size()); ++i) ex[m.extra_names[i]] = m.extra_values[i];
      if (ex.count("position_scale") && ex.count("offset_x") && ex.count("offset_y") && ex.count("offset_z")) {
        const Vec3 off(ex["offset_x"], ex["offset_y"], ex["offset_z"]);
        const double ps = ex["position_scale"];
        if (off.allFinite() && std::isfinite(ps) && ps > 0) {
          s.have_mapping = true;
          s.position_scale = ps;
          s.offset = off;
          s.force_scale = ex.count("force_scale") ? ex["force_scale"] : 1.0;
          s.max_force_n = ex.count("max_force_n") ? ex["max_force_n"] : 0.0;
        }
      }
    }));
  }
  subs(bus.subscribe<lcmt_process_stats>(bus::channel::stats("sim_server", sfx), [this](const lcmt_process_stats& m, const std::string&) {
    std::lock_guard<std::mutex> lock(mutex);
    sim_rate = m.loop_rate_hz;
    ++updates;
    for (int i = 0; i < m.n_extra && i < static_cast<int>(m.extra_names.size()); ++i)
      if (m.extra_names[i] == "resets") sim_resets = m.extra_values[i];
  }));
}

std::string random_viewer_token() {
  if (sodium_init() < 0) throw std::runtime_error("viewer: libsodium failed to initialise");
  unsigned char b[24];
  randombytes_buf(b, sizeof b);
  char hex[2 * sizeof b + 1];
  sodium_bin2hex(hex, sizeof hex, b, sizeof b);
  return hex;
}

std::string read_viewer_token_file(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("viewer: cannot read the token file " + path);
  std::string line;
  std::getline(in, line);
  const size_t b = line.find_first_not_of(" \t\r\n");
  const size_t e = line.find_last_not_of(" \t\r\n");
  line = b == std::string::npos ? "" : line.substr(b, e - b + 1);
  if (line.size() < 16 || line.size() > 256)
    throw std::runtime_error("viewer: the token in " + path + " must be 16 to 256 characters on its first line");
  for (const char ch : line)
    if (!(std::isalnum(static_cast<unsigned char>(ch)) || ch == '-' || ch == '_' || ch == '.' || ch == '~'))
      throw std::runtime_error("viewer: the token in " + path + " may hold only letters, digits and -_.~");
  return line;
}

void Viewer::Impl::setup_access() {
  if (sodium_init() < 0) throw std::runtime_error("viewer: libsodium failed to initialise");
  asio::error_code aec;
  const asio::ip::address addr = asio::ip::make_address(opt.bind, aec);
  if (aec) throw std::runtime_error("viewer: --viewer-bind '" + opt.bind + "' is not an IP address");
  open_access = opt.no_token;
  if (open_access && !addr.is_loopback())
    throw std::runtime_error("viewer: binding " + opt.bind + " (off this machine) needs a token: drop --viewer-no-token");
  if (open_access && !(opt.token.empty() && opt.token_file.empty() && opt.watch_token_file.empty()))
    throw std::runtime_error("viewer: --viewer-no-token together with a token or token file");
  if (!open_access) {
    pull_token = !opt.token.empty() ? opt.token
                 : !opt.token_file.empty() ? read_viewer_token_file(opt.token_file) : random_viewer_token();
    pull_hash = hash_token(pull_token);
    if (!opt.watch_token_file.empty()) {
      watch_token = read_viewer_token_file(opt.watch_token_file);
      if (watch_token == pull_token) throw std::runtime_error("viewer: the watch token is the pull token");
      watch_hash = hash_token(watch_token);
    }
  }
  if (opt.tls_cert.empty() != opt.tls_key.empty())
    throw std::runtime_error("viewer: TLS needs both a certificate and a key file");
  tls = !opt.tls_cert.empty();
  if (tls) {
    tls_context = std::make_shared<asio::ssl::context>(asio::ssl::context::tls_server);
    tls_context->set_options(asio::ssl::context::default_workarounds | asio::ssl::context::no_sslv2 |
                             asio::ssl::context::no_sslv3 | asio::ssl::context::no_tlsv1 |
                             asio::ssl::context::no_tlsv1_1);
    asio::error_code ec;
    tls_context->use_certificate_chain_file(opt.tls_cert, ec);
    if (ec) throw std::runtime_error("viewer: TLS certificate " + opt.tls_cert + ": " + ec.message());
    tls_context->use_private_key_file(opt.tls_key, asio::ssl::context::pem, ec);
    if (ec) throw std::runtime_error("viewer: TLS key " + opt.tls_key + ": " + ec.message());
  }
}

Role Viewer::Impl::role_of(const std::string& token) const {
  if (open_access) return Role::kPull;
  if (token.empty() || token.size() > 256) return Role::kNone;
  const TokenHash h = hash_token(token);
  const bool pull = sodium_memcmp(h.data(), pull_hash.data(), h.size()) == 0;
  const bool watch = !watch_token.empty() && sodium_memcmp(h.data(), watch_hash.data(), h.size()) == 0;
  return pull ? Role::kPull : watch ? Role::kWatch : Role::kNone;
}

void Viewer::Impl::refuse(Refusal r, const std::string& who, const std::string& what) {
  refused[static_cast<size_t>(r)].fetch_add(1, std::memory_order_relaxed);
  if (refusals_logged.size() < 4096 && refusals_logged.insert({who, static_cast<int>(r)}).second)
    spdlog::warn("viewer: refused {} ({}): {} (logged once per client and reason)", who, what, refusal_text(r));
}

template <class Con>
Role Viewer::Impl::authorize(Con& con, bool count, bool* from_query) {
  if (open_access) return Role::kPull;
  std::string t = query_param(con->get_resource(), "token");
  if (from_query) *from_query = !t.empty();
  if (t.empty()) t = cookie_value(con->get_request_header("Cookie"), cookie_name);
  const Role role = role_of(t);
  if (role == Role::kNone && count) {
    asio::error_code ec;
    const auto ep = con->get_raw_socket().remote_endpoint(ec);
    const std::string who = ec ? std::string("?") : ep.address().to_string();
    const std::string res = con->get_resource().substr(0, con->get_resource().find('?')).substr(0, 64);
    refuse(t.empty() ? Refusal::kNoToken : Refusal::kWrongToken, who, "GET " + res);
  }
  return role;
}

void Viewer::Impl::start_server() {
  const std::string dir = find_web_dir(opt.web_dir);
  index_html = read_file(dir + "/index.html");
  viewer_js = read_file(dir + "/viewer.js");
  ngl_js = read_file(dir + "/vendor/ngl.js");
  if (tls) {
    secure = std::make_unique<WssServer>();
    secure->set_tls_init_handler([this](Hdl) { return tls_context; });
  } else {
    plain = std::make_unique<WsServer>();
  }
  net([&](auto& srv) { start_on(srv); });
  cookie_name = "haptree_viewer_" + std::to_string(bound_port);
  spdlog::info("viewer: {} ({} display points, web files from {}{})",
               std::string(tls ? "https://" : "http://") + opt.bind + ":" + std::to_string(bound_port) + "/",
               point_body.size(), dir, open_access ? "; NO TOKEN: anyone on this machine can pull" : "");
}

template <class S>
void Viewer::Impl::start_on(S& srv) {
  srv.clear_access_channels(websocketpp::log::alevel::all);
  srv.clear_error_channels(websocketpp::log::elevel::all);
  srv.init_asio();
  srv.set_reuse_addr(true);
  srv.set_max_message_size(kMaxClientMessageBytes);     // a page's messages are tiny (input.hpp)
  srv.set_max_http_body_size(kMaxClientMessageBytes);
  srv.set_http_handler([this, &srv](Hdl h) { on_http(srv, h); });
  srv.set_validate_handler([this, &srv](Hdl h) { return on_validate(srv, h); });
  srv.set_open_handler([this, &srv](Hdl h) { on_open(srv, h); });
  srv.set_close_handler([this](Hdl h) { on_close(h); });
  srv.set_fail_handler([](Hdl) {});
  srv.set_message_handler([this](Hdl h, typename S::message_ptr m) { on_message(h, m->get_payload()); });
  asio::error_code aec;
  const asio::ip::address addr = asio::ip::make_address(opt.bind, aec);
  websocketpp::lib::error_code ec;
  srv.listen(asio::ip::tcp::endpoint(addr, static_cast<unsigned short>(opt.port)), ec);
  if (ec)
    throw std::runtime_error("viewer: cannot listen on " + opt.bind + ":" + std::to_string(opt.port) + ": " +
                             ec.message() + (opt.port ? " (another viewer running? pick another port)" : ""));
  srv.start_accept(ec);
  if (ec) throw std::runtime_error("viewer: accept failed: " + ec.message());
  bound_port = srv.get_local_endpoint(aec).port();
  timer = std::make_unique<asio::steady_timer>(srv.get_io_service());
}

template <class S>
void Viewer::Impl::on_http(S& srv, Hdl h) {
  auto con = srv.get_con_from_hdl(h);
  con->append_header("Cache-Control", "no-store");
  con->append_header("Referrer-Policy", "no-referrer");   // the token in the URL never leaves in a Referer
  con->append_header("X-Content-Type-Options", "nosniff");
  bool from_query = false;
  const Role role = authorize(con, true, &from_query);
  if (role == Role::kNone) {
    con->set_status(websocketpp::http::status_code::forbidden);
    con->append_header("Content-Type", "text/plain; charset=utf-8");
    con->set_body("haptree viewer: this page needs its token: open the URL the viewer printed "
                  "(http://HOST:PORT/?token=...)\n");
    return;
  }
  if (from_query && !open_access)   // the page's own requests and its reloads carry the token as a cookie
    con->append_header("Set-Cookie", cookie_name + "=" + query_param(con->get_resource(), "token") +
                                         "; Path=/; HttpOnly; SameSite=Strict" + (tls ? "; Secure" : ""));
  const std::string* body = nullptr;
  std::string type;
  switch (route_resource(con->get_resource())) {
    case WebResource::kIndex: body = &index_html, type = "text/html; charset=utf-8"; break;
    case WebResource::kViewerJs: body = &viewer_js, type = "text/javascript; charset=utf-8"; break;
    case WebResource::kNglJs: body = &ngl_js, type = "text/javascript; charset=utf-8"; break;
    case WebResource::kScenePdb: body = &pdb, type = "chemical/x-pdb"; break;
    case WebResource::kSceneJson: body = &scene_json, type = "application/json"; break;
    case WebResource::kSceneMeshes: body = &meshes_bin, type = "application/octet-stream"; break;
    case WebResource::kNotFound: break;
  }
  if (!body) {
    con->set_status(websocketpp::http::status_code::not_found);
    con->set_body("not found\n");
    return;
  }
  con->set_status(websocketpp::http::status_code::ok);
  con->append_header("Content-Type", type);
  con->set_body(*body);
}

// A WebSocket upgrade: from the page's own origin (a browser always says which page opens the socket;
// another site's page must not read or pull the session) and with a token.
template <class S>
bool Viewer::Impl::on_validate(S& srv, Hdl h) {
  auto con = srv.get_con_from_hdl(h);
  if (!same_origin(con->get_request_header("Origin"), con->get_request_header("Host"), tls)) {
    asio::error_code ec;
    const auto ep = con->get_raw_socket().remote_endpoint(ec);
    refuse(Refusal::kForeignOrigin, ec ? std::string("?") : ep.address().to_string(),
           "Origin " + con->get_request_header("Origin").substr(0, 80));
    con->set_status(websocketpp::http::status_code::forbidden);
    return false;
  }
  if (authorize(con, true) == Role::kNone) {
    con->set_status(websocketpp::http::status_code::forbidden);
    return false;
  }
  return true;
}

template <class S>
void Viewer::Impl::on_open(S& srv, Hdl h) {
  auto con = srv.get_con_from_hdl(h);
  Client c;
  c.id = next_client++;
  c.role = authorize(con, false);
  asio::error_code aec;
  const auto ep = con->get_raw_socket().remote_endpoint(aec);
  c.address = aec ? std::string("?") : ep.address().to_string();
  std::vector<bool> taken(static_cast<size_t>(opt.users), false);
  for (const auto& kv : clients)
    if (kv.second.user >= 0) taken[static_cast<size_t>(kv.second.user)] = true;
  for (int u = 0; u < opt.users && c.role == Role::kPull; ++u)
    if (!taken[static_cast<size_t>(u)]) {
      c.user = u;
      break;
    }
  clients[h] = c;
  nclients = static_cast<int>(clients.size());
  json hello = json::parse(scene_json);
  hello["t"] = "hello";
  hello["user"] = c.user;
  hello["client"] = c.id;
  hello["role"] = c.role == Role::kPull ? "pull" : "watch";
  websocketpp::lib::error_code ec;
  srv.send(h, hello.dump(), websocketpp::frame::opcode::text, ec);
  spdlog::info("viewer: client {} ({}) connected as {}", c.id, c.address,
               c.user >= 0 ? "user " + std::to_string(c.user) : c.role == Role::kWatch ? "watcher (watch token)" : "spectator");
}

void Viewer::Impl::on_close(Hdl h) {
  auto it = clients.find(h);
  if (it == clients.end()) return;
  if (it->second.user >= 0) publish_pointer(it->second, false);   // a dropped socket releases at once
  spdlog::info("viewer: client {} left", it->second.id);
  clients.erase(it);
  nclients = static_cast<int>(clients.size());
}

// Scene point -> device metres with the user's coupler mapping; nothing non-finite leaves.
void Viewer::Impl::publish_pointer(const Client& c, bool button) {
  if (c.user < 0) return;
  lcmt_pointer m{};
  bus::stamp(m, instance_id);
  m.seq = ++pointer_seq;
  m.user_id = c.user;
  m.client_id = c.id;
  Vec3 x_m = Vec3::Zero();
  {
    std::lock_guard<std::mutex> lock(mutex);
    const UserSlot& s = users[static_cast<size_t>(c.user)];
    if (c.have_target && s.have_mapping) x_m = (c.target_scene - s.offset) / s.position_scale;
    else if (s.have_device) x_m = s.device_m;
  }
  if (!x_m.allFinite()) return;
  for (int i = 0; i < 3; ++i) m.position_m[i] = x_m[i];
  m.buttons = button ? 1 : 0;
  m.grab_body = button ? c.body : 0;
  bus.publish(bus::channel::pointer(c.user, opt.channel_suffix), m);
  pointer_msgs.fetch_add(1, std::memory_order_relaxed);
}

void Viewer::Impl::on_message(Hdl h, const std::string& pl) {
  auto it = clients.find(h);
  if (it == clients.end()) return;
  Client& c = it->second;
  const ClientCommand cmd = parse_client_message(pl.data(), pl.size());
  if (cmd.kind == ClientCommand::Kind::kAck) {   // from any role: it only paces this socket's frames
    c.frames_acked = std::max(c.frames_acked, std::min(cmd.frames, c.frames_sent));
    return;
  }
  if (c.role == Role::kWatch && cmd.kind == ClientCommand::Kind::kDown)
    refuse(Refusal::kWatchPull, c.address, "client " + std::to_string(c.id));
  if (c.user < 0) return;
  bool mapped;
  {
    std::lock_guard<std::mutex> lock(mutex);
    mapped = users[static_cast<size_t>(c.user)].have_mapping;
  }
  switch (cmd.kind) {
    case ClientCommand::Kind::kDown: {
      // A press grabs the picked atom's body at the atom itself; the ground, an unknown point or a user
      // whose coupler has not told its mapping yet grabs nothing.
      if (cmd.atom >= static_cast<int>(point_body.size())) return;
      const int b = point_body[static_cast<size_t>(cmd.atom)];
      if (!mapped || b < 1) {
        spdlog::info("viewer: client {} (user {}) pressed on point {}: {}", c.id, c.user, cmd.atom,
                     b < 1 ? "the ground, nothing to grab" : "the coupler has not sent its mapping yet");
        return;
      }
      spdlog::info("viewer: client {} (user {}) grabs body {} at point {}", c.id, c.user, b, cmd.atom);
      {
        std::lock_guard<std::mutex> lock(mutex);
        c.target_scene = r[b] + q[b] * point_local[static_cast<size_t>(cmd.atom)];
      }
      c.body = b;
      c.down = true;
      c.have_target = true;
      publish_pointer(c, true);
      break;
    }
    case ClientCommand::Kind::kMove:
      if (!c.down) return;
      c.target_scene = from_disp(cmd.p);
      publish_pointer(c, true);
      break;
    case ClientCommand::Kind::kUp:
      if (!c.down) return;
      c.down = false;
      publish_pointer(c, false);
      break;
    case ClientCommand::Kind::kAck:   // handled above
    case ClientCommand::Kind::kInvalid:
      break;
  }
}

void Viewer::Impl::tick() {
  const auto now = Clock::now();
  if (now >= next_keepalive) {   // the browser device releases if the pointer goes quiet
    for (auto& kv : clients)
      if (kv.second.user >= 0 && kv.second.have_target) publish_pointer(kv.second, kv.second.down);
    next_keepalive = now + std::chrono::milliseconds(50);
  }
  if (now >= next_stats) {
    lcmt_process_stats s{};
    bus::stamp(s, instance_id);
    s.seq = ++seq_stats;
    s.process_name = "viewer";
    s.loop_rate_hz = static_cast<double>(frames_sent.load() - frames_at_stats);
    frames_at_stats = frames_sent.load();
    s.snapshot_age_ms = -1;
    s.messages_out = pointer_msgs.load();
    s.extra_names = {"clients", "frames_dropped", "refused_no_token", "refused_wrong_token", "refused_origin",
                     "refused_watch_pull"};
    s.extra_values = {static_cast<double>(nclients.load()), static_cast<double>(frames_dropped.load())};
    for (const auto& n : refused) s.extra_values.push_back(static_cast<double>(n.load()));
    s.n_extra = static_cast<int>(s.extra_names.size());
    {
      std::lock_guard<std::mutex> lock(mutex);
      s.messages_in = scene_msgs;
    }
    bus.publish(bus::channel::stats("viewer", opt.channel_suffix), s);
    next_stats += std::chrono::seconds(1);
  }
  if (clients.empty()) return;
  // A frame goes to a tab only when something it shows changed (a scene state, a device, a force, a
  // coupler's stats) or once a second (the HUD's ages); the positions only when a new scene state came.
  int64_t upd, sm;
  {
    std::lock_guard<std::mutex> lock(mutex);
    upd = updates;
    sm = scene_msgs;
  }
  bool any = false, any_positions = false;
  for (auto& kv : clients) {
    kv.second.due = kv.second.updates_sent != upd || now - kv.second.last_frame >= std::chrono::seconds(1);
    any = any || kv.second.due;
    any_positions = any_positions || (kv.second.due && kv.second.scene_sent != sm);
  }
  if (!any) return;
  // Build the frame from the slots (copy out under the lock, compute outside it).
  json f;
  std::string mask;
  int64_t mv;
  {
    std::lock_guard<std::mutex> lock(mutex);
    if (any_positions)
      for (size_t i = 0; i < point_body.size(); ++i) {
        const int b = point_body[i];
        x_scene[i] = r[b] + q[b] * point_local[i];
      }
    mv = mask_version;
    mask.resize(active.size());
    for (size_t k = 0; k < active.size(); ++k) mask[k] = active[k] ? '1' : '0';
    f["t"] = "frame";
    f["seq"] = ++frame_seq;
    f["utime"] = bus::now_utime();   // when built: the page's measure of how late it reads (same clock on one host)
    f["version"] = scene_version;
    f["scene_age_ms"] = scene_utime > 0 ? 1e-3 * static_cast<double>(bus::now_utime() - scene_utime) : -1.0;
    f["sim_time"] = sim_time;
    f["step_ms"] = step_ms;
    f["active_dofs"] = active_dofs;
    f["dof"] = model->nv;
    f["sim_rate"] = sim_rate;
    f["resets"] = sim_resets;
    json us = json::array();
    for (int u = 0; u < opt.users; ++u) {
      UserSlot& s = users[static_cast<size_t>(u)];
      json j;
      j["id"] = u;
      j["rate_hz"] = s.rate_hz;
      j["p99_us"] = s.p99_us;
      j["age_ms"] = s.snapshot_age_ms;
      j["watchdog"] = (s.flags & lcmt_feedback::FLAG_WATCHDOG) != 0;
      j["stale"] = (s.flags & lcmt_feedback::FLAG_STALE) != 0;
      j["clamped"] = (s.flags & lcmt_feedback::FLAG_CLAMPED) != 0;
      j["watchdog_events"] = s.watchdog_events;
      j["clamp_events"] = s.clamp_events;
      j["max_force_n"] = s.max_force_n;
      j["f"] = {s.force_n.x(), s.force_n.y(), s.force_n.z()};
      j["fn"] = s.force_n.norm();
      j["buttons"] = s.buttons;
      j["device_body"] = s.device_grab_body;   // > 0: the page drives this user's device
      j["device_grab_seq"] = s.device_grab_seq;
      if (s.have_device && s.have_mapping) {
        // The device cursor (any device kind: its DEVICE_STATE through the coupler's mapping) and its
        // reach: the distance to the body origin a press grabs when nothing names the body (the coupler's
        // nearest-body rule).
        const Vec3 x = s.position_scale * s.device_m + s.offset;
        const Vec3 p = to_disp(x);
        j["proxy"] = {p.x(), p.y(), p.z()};
        double best = std::numeric_limits<double>::infinity();
        int nearest = 0;
        for (int k = 1; k < model->nbodies; ++k) {
          const double d2 = (r[k] - x).squaredNorm();
          if (d2 < best) best = d2, nearest = k;
        }
        if (nearest > 0) {
          j["reach"] = std::sqrt(best) * disp_scale;
          j["reach_body"] = nearest;
        }
      }
      if (s.uf_active) {
        // The grab point is a material point of the body: fixed in its frame from the grab on.
        if (s.uf_body != s.track_body || s.uf_point != s.track_key) {
          s.track_body = s.uf_body;
          s.track_key = s.uf_point;
          s.track_local = q[s.uf_body].conjugate() * (s.uf_point - r[s.uf_body]);
        }
        const Vec3 g = to_disp(r[s.uf_body] + q[s.uf_body] * s.track_local);
        j["body"] = s.uf_body;
        j["grab"] = {g.x(), g.y(), g.z()};
      } else {
        s.track_body = 0;
      }
      us.push_back(j);
    }
    f["users"] = us;
  }
  if (any_positions)
    for (size_t i = 0; i < x_scene.size(); ++i) {
      const Vec3 p = to_disp(x_scene[i]);
      for (int a = 0; a < 3; ++a) frame_pos[3 * i + static_cast<size_t>(a)] = static_cast<float>(p[a]);
    }
  if (any_positions && with_quats) {   // x y z w per body, after the points
    std::lock_guard<std::mutex> lock(mutex);
    float* o = frame_pos.data() + 3 * x_scene.size();
    for (int k = 0; k < model->nbodies; ++k, o += 4) {
      const Quat& qk = q[static_cast<size_t>(k)];
      o[0] = static_cast<float>(qk.x()), o[1] = static_cast<float>(qk.y()), o[2] = static_cast<float>(qk.z()),
      o[3] = static_cast<float>(qk.w());
    }
  }
  net([&](auto& srv) {
    for (auto& kv : clients) {
      Client& c = kv.second;
      if (!c.due) continue;
      auto con = srv.get_con_from_hdl(kv.first);
      if (!con || con->get_state() != websocketpp::session::state::open) continue;
      // slow tab: skip, do not queue
      if ((c.frames_acked >= 0 && c.frames_sent - c.frames_acked >= opt.max_frames_in_flight) ||
          con->get_buffered_amount() > opt.max_buffered_bytes) {
        frames_dropped.fetch_add(1, std::memory_order_relaxed);
        continue;
      }
      json fj = f;
      fj["you"] = c.user;
      if (c.mask_sent != mv) fj["active"] = mask;   // the active region, when it changed (each reselection)
      const bool with_positions = c.scene_sent != sm;
      encode_frame(fj.dump(), with_positions ? frame_pos.data() : nullptr, with_positions ? frame_pos.size() : 0, msg_buf);
      websocketpp::lib::error_code ec;
      srv.send(kv.first, msg_buf.data(), msg_buf.size(), websocketpp::frame::opcode::binary, ec);
      if (ec) continue;
      c.mask_sent = mv;
      c.updates_sent = upd;
      if (with_positions) c.scene_sent = sm;
      c.last_frame = now;
      ++c.frames_sent;
      frames_sent.fetch_add(1, std::memory_order_relaxed);
      frame_bytes.fetch_add(static_cast<int64_t>(msg_buf.size()), std::memory_order_relaxed);
    }
  });
}

void Viewer::Impl::schedule() {
  timer->expires_after(std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(1.0 / opt.max_fps)));
  timer->async_wait([this](const asio::error_code& ec) {
    if (ec) return;
    tick();
    schedule();
  });
}

Viewer::Viewer(bus::Bus& bus, const ViewerOptions& options) : impl_(std::make_unique<Impl>(bus, options)) {
  if (!(options.max_fps > 0 && options.max_fps <= 240)) throw std::runtime_error("viewer: --max-fps must be in (0, 240]");
  if (options.users < 1 || options.users > 8) throw std::runtime_error("viewer: --users must be in [1, 8]");
  if (options.max_frames_in_flight < 1) throw std::runtime_error("viewer: max_frames_in_flight must be >= 1");
  if (options.port < 0 || options.port > 65535) throw std::runtime_error("viewer: --port must be in [0, 65535]");
  impl_->setup_access();
  impl_->load_scene();
  impl_->start_server();
  impl_->subscribe();
}

Viewer::~Viewer() = default;

int Viewer::run(const std::atomic<bool>& stop) {
  Impl& m = *impl_;
  m.schedule();
  m.net([&](auto& srv) {
    auto& io = srv.get_io_service();
    while (!stop.load(std::memory_order_relaxed)) io.run_for(std::chrono::milliseconds(100));
    // Release every tab's grab, close the sockets, let the closes go out.
    for (auto& kv : m.clients) m.publish_pointer(kv.second, false);
    websocketpp::lib::error_code ec;
    srv.stop_listening(ec);
    for (auto& kv : m.clients) srv.close(kv.first, websocketpp::close::status::going_away, "session over", ec);
    m.timer->cancel();
    io.run_for(std::chrono::milliseconds(300));
    srv.stop();
  });
  return 0;
}

int Viewer::port() const { return impl_->bound_port; }
std::string Viewer::url() const {
  const Impl& m = *impl_;
  return std::string(m.tls ? "https://" : "http://") + m.opt.bind + ":" + std::to_string(m.bound_port) + "/" +
         (m.open_access ? "" : "?token=" + m.pull_token);
}
std::string Viewer::watch_url() const {
  const Impl& m = *impl_;
  if (m.watch_token.empty()) return "";
  return std::string(m.tls ? "https://" : "http://") + m.opt.bind + ":" + std::to_string(m.bound_port) + "/?token=" +
         m.watch_token;
}
ViewerRefusals Viewer::refusals() const {
  ViewerRefusals r;
  r.no_token = impl_->refused[0].load();
  r.wrong_token = impl_->refused[1].load();
  r.foreign_origin = impl_->refused[2].load();
  r.watch_pull = impl_->refused[3].load();
  return r;
}
int64_t Viewer::frames_sent() const { return impl_->frames_sent.load(); }
int64_t Viewer::frame_bytes() const { return impl_->frame_bytes.load(); }
int64_t Viewer::frames_dropped() const { return impl_->frames_dropped.load(); }
int Viewer::clients() const { return impl_->nclients.load(); }
int64_t Viewer::pointer_messages() const { return impl_->pointer_msgs.load(); }

}  // namespace haptree
