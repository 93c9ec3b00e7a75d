// Viewer: the page's messages parsed without trusting them, and the HTTP side (page, scene, 404s).
#include <gtest/gtest.h>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <fstream>
#include <cmath>
#include <cstring>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/lcmt_scene_state.hpp"
#include "sim_server/sim_server.hpp"
#include "haptree/io/urdf.hpp"
#include "viewer/robot_visuals.hpp"
#include "viewer/viewer.hpp"

namespace haptree {
namespace {

ClientCommand parse(const std::string& s) { return parse_client_message(s.data(), s.size()); }

TEST(ViewerParse, AcceptsThePointerCommandsAndTheAcknowledgement) {
  ClientCommand c = parse(R"({"t":"down","i":12,"p":[1.5,-2,3e1]})");
  EXPECT_EQ(c.kind, ClientCommand::Kind::kDown);
  EXPECT_EQ(c.atom, 12);
  EXPECT_EQ(c.p, Vec3(1.5, -2, 30));
  c = parse(R"({"t":"move","p":[0,0,1]})");
  EXPECT_EQ(c.kind, ClientCommand::Kind::kMove);
  EXPECT_EQ(c.p, Vec3(0, 0, 1));
  EXPECT_EQ(parse(R"({"t":"up"})").kind, ClientCommand::Kind::kUp);
  c = parse(R"({"t":"ack","n":1234567890123})");
  EXPECT_EQ(c.kind, ClientCommand::Kind::kAck);
  EXPECT_EQ(c.frames, 1234567890123);
  EXPECT_EQ(parse(R"({"t":"ack","n":0})").frames, 0);
}

TEST(ViewerParse, RefusesNonFiniteMalformedAndAbsurdInput) {
  for (const char* s : {R"({"t":"move","p":[NaN,0,0]})", R"({"t":"move","p":[1e400,0,0]})",
                        R"({"t":"move","p":[1e7,0,0]})", R"({"t":"move","p":[0,0]})", R"({"t":"move","p":["0",0,0]})",
                        R"({"t":"move"})", R"({"t":"down","p":[0,0,0]})", R"({"t":"down","i":-1,"p":[0,0,0]})",
                        R"({"t":"down","i":1.5,"p":[0,0,0]})", R"({"t":"down","i":4294967296,"p":[0,0,0]})",
                        R"({"t":"jump"})", R"({"t":3})",
                        R"({"t":"ack"})", R"({"t":"ack","n":-1})", R"({"t":"ack","n":1.5})", R"({"t":"ack","n":"7"})",
                        R"({"t":"ack","n":18446744073709551615})", R"([1,2,3])", "", "{", "\xff\xfe", "null"})
    EXPECT_EQ(parse(s).kind, ClientCommand::Kind::kInvalid) << s;
  EXPECT_EQ(parse_client_message(nullptr, 10).kind, ClientCommand::Kind::kInvalid);
  const std::string big = R"({"t":"up","pad":")" + std::string(5000, 'x') + "\"}";
  EXPECT_EQ(parse(big).kind, ClientCommand::Kind::kInvalid);   // > 4 KB: refused unread
  std::mt19937 rng(12);
  for (int k = 0; k < 2000; ++k) {   // random bytes: never a command with a non-finite point, never a throw
    std::string s(static_cast<size_t>(rng() % 64), '\0');
    for (auto& ch : s) ch = static_cast<char>(rng());
    const ClientCommand c = parse(s);
    EXPECT_TRUE(c.p.allFinite());
  }
}

TEST(ViewerParse, TokenCookieAndOrigin) {
  EXPECT_EQ(query_param("/ws?token=abc", "token"), "abc");
  EXPECT_EQ(query_param("/?x=1&token=a%2Db+c&y=2", "token"), "a-b c");
  EXPECT_EQ(query_param("/?tokens=1&xtoken=2", "token"), "");
  EXPECT_EQ(query_param("/?token=%zz", "token"), "");
  EXPECT_EQ(query_param("/?token=%2", "token"), "");
  EXPECT_EQ(query_param("/token=abc", "token"), "");
  EXPECT_EQ(cookie_value("a=1; haptree_viewer_80=tok; b=2", "haptree_viewer_80"), "tok");
  EXPECT_EQ(cookie_value("haptree_viewer_8=x; haptree_viewer_80=y", "haptree_viewer_80"), "y");
  EXPECT_EQ(cookie_value("xhaptree_viewer_80=y", "haptree_viewer_80"), "");
  EXPECT_EQ(cookie_value("", "a"), "");
  EXPECT_TRUE(same_origin("", "127.0.0.1:80", false));   // not a browser
  EXPECT_TRUE(same_origin("http://127.0.0.1:8080", "127.0.0.1:8080", false));
  EXPECT_TRUE(same_origin("http://LabHost:8080", "labhost:8080", false));
  EXPECT_TRUE(same_origin("https://h:1", "h:1", true));
  EXPECT_FALSE(same_origin("http://h:1", "h:1", true));
  EXPECT_FALSE(same_origin("https://h:1", "h:1", false));
  EXPECT_FALSE(same_origin("http://127.0.0.1:8081", "127.0.0.1:8080", false));
  EXPECT_FALSE(same_origin("http://evil.example", "127.0.0.1:8080", false));
  EXPECT_FALSE(same_origin("null", "127.0.0.1:8080", false));
  EXPECT_FALSE(same_origin("http://127.0.0.1:8080", "", false));
}

std::string http_get(int port, const std::string& path) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(static_cast<uint16_t>(port));
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) {
    ::close(fd);
    return "";
  }
  const std::string req = "GET " + path + " HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n";
  (void)!::write(fd, req.data(), req.size());
  std::string out;
  char buf[65536];
  for (ssize_t n; (n = ::read(fd, buf, sizeof buf)) > 0;) out.append(buf, static_cast<size_t>(n));
  ::close(fd);
  return out;
}

TEST(Viewer, ServesThePageTheSceneAndNothingElse) {
  bus::Bus bus("memq://");
  ViewerOptions o;
  o.port = 0;   // any free port
  o.scene = "chain";
  o.n = 5;
  o.token = "unit-test-token-0123456789";
  Viewer v(bus, o);
  ASSERT_GT(v.port(), 0);
  EXPECT_EQ(v.url(), "http://127.0.0.1:" + std::to_string(v.port()) + "/?token=" + o.token);
  std::atomic<bool> stop{false};
  std::thread t([&] { v.run(stop); });
  const std::string tq = "?token=" + o.token;
  const std::string page = http_get(v.port(), "/" + tq);
  EXPECT_NE(page.find("200 OK"), std::string::npos);
  EXPECT_NE(page.find("vendor/ngl.js"), std::string::npos);
  EXPECT_NE(page.find("Set-Cookie: haptree_viewer_" + std::to_string(v.port()) + "=" + o.token + ";"), std::string::npos);
  // without the token, or with another one (also one that only differs in its last character): 403
  for (const std::string& bad : std::vector<std::string>{"/", "/scene.pdb", "/?token=" + o.token.substr(0, o.token.size() - 1) + "X",
                                 "/?token=" + o.token + "0", "/?token="})
    EXPECT_NE(http_get(v.port(), bad).find("403"), std::string::npos) << bad;
  EXPECT_EQ(v.refusals().no_token, 3);
  EXPECT_EQ(v.refusals().wrong_token, 2);
  const std::string pdb = http_get(v.port(), "/scene.pdb" + tq);
  // chain(5): the ground + 5 bodies as points, 5 joints as CONECT records
  size_t atoms = 0, conect = 0;
  for (size_t p = 0; (p = pdb.find("\nHETATM", p)) != std::string::npos; ++p) ++atoms;
  for (size_t p = 0; (p = pdb.find("\nCONECT", p)) != std::string::npos; ++p) ++conect;
  EXPECT_EQ(atoms, 6u);
  EXPECT_EQ(conect, 5u);
  for (const char* bad : {"/../../etc/passwd", "/vendor/../viewer.cpp", "/nothing", "/index.html/.."})
    EXPECT_NE(http_get(v.port(), bad + tq).find("404"), std::string::npos) << bad;
  stop = true;
  t.join();
}

TEST(Viewer, BusyPortIsAClearError) {
  bus::Bus bus("memq://");
  ViewerOptions o;
  o.port = 0;
  o.scene = "chain";
  o.n = 3;
  Viewer a(bus, o);
  o.port = a.port();
  try {
    Viewer b(bus, o);
    FAIL() << "a second viewer on port " << o.port << " must not start";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(std::to_string(o.port)), std::string::npos) << e.what();
  }
}

// A scene too large for one datagram comes as chunks of <= 1000 bodies, each < 60 KB, that cover every
// body once; the active flags agree with the step's active DOF count (chain: one DOF per joint).
TEST(SceneState, LargeSceneIsSplitIntoDatagramSizedChunksWithActiveFlags) {
  bus::Bus bus("memq://");
  SimServerOptions o;
  o.scene = "chain";
  o.n = 2500;
  o.steps = 8;   // the chunks of one state go out one per step after it is started: 3 chunks, then spare steps
  o.budget_dofs = 48;
  SimServer server(bus, o);
  std::vector<lcmt_scene_state> got;
  bus.subscribe<lcmt_scene_state>(bus::channel::scene_state(), [&](const lcmt_scene_state& m, const std::string&) {
    got.push_back(m);
  });
  std::atomic<bool> stop{false};
  server.run(stop);
  while (bus.handle_timeout(0) > 0) {
  }
  ASSERT_GE(got.size(), 3u);   // the first display period: one state in 3 chunks
  const int64_t v = got[0].version;
  std::vector<int> seen(2501, 0);
  int active = 0;
  for (const auto& m : got) {
    if (m.version != v) continue;
    EXPECT_EQ(m.total_bodies, 2501);
    EXPECT_LE(m.nbodies, 1000);
    EXPECT_LT(m.getEncodedSize(), 60000);
    ASSERT_EQ(static_cast<int>(m.body_active.size()), m.nbodies);
    for (int i = 0; i < m.nbodies; ++i) {
      ++seen[static_cast<size_t>(m.first_body + i)];
      active += m.body_active[static_cast<size_t>(i)];
    }
    EXPECT_EQ(m.active_dofs, got[0].active_dofs);
  }
  for (int k = 0; k < 2501; ++k) EXPECT_EQ(seen[static_cast<size_t>(k)], 1) << "body " << k;
  EXPECT_EQ(active, got[0].active_dofs);
  EXPECT_GT(active, 0);
  EXPECT_EQ(seen.size(), 2501u);
}

// The sample robots' mesh files (data/robots/make_robots.py writes them from known solids): each format
// gives the solid's triangles and extent, in metres.
void extent(const TriMesh& m, Vec3& lo, Vec3& hi) {
  lo = Vec3::Constant(1e9), hi = Vec3::Constant(-1e9);
  for (const Vec3& v : m.v) lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
}

TEST(RobotVisuals, MeshFilesOfEveryFormat) {
  const std::string d = std::string(HAPTREE_ROBOTS_DIR) + "/meshes/arm/";
  Vec3 lo, hi;
  const TriMesh wrist = load_mesh_file(d + "wrist.stl");   // ASCII STL: a 0.06 x 0.05 x 0.05 box at x = 0.03
  EXPECT_EQ(wrist.f.size(), 12u);
  extent(wrist, lo, hi);
  EXPECT_NEAR((lo - Vec3(0, -0.025, -0.025)).norm(), 0, 1e-6);
  EXPECT_NEAR((hi - Vec3(0.06, 0.025, 0.025)).norm(), 0, 1e-6);
  const TriMesh upper = load_mesh_file(d + "upper.stl");   // binary STL: a 24-segment cylinder + a box
  EXPECT_EQ(upper.f.size(), 4u * 24u + 12u);
  extent(upper, lo, hi);
  EXPECT_NEAR(hi.z(), 0.3, 1e-6);
  EXPECT_NEAR(lo.z(), -0.03, 1e-6);
  const TriMesh grip = load_mesh_file(d + "gripper.obj");   // OBJ: three boxes
  EXPECT_EQ(grip.f.size(), 36u);
  extent(grip, lo, hi);
  EXPECT_NEAR(hi.x(), 0.07, 1e-6);
  EXPECT_NEAR(hi.y(), 0.04, 1e-6);
  // DAE in millimetres under a node translated by 10 mm: a puck of radius 0.08 m from z = 0 to 0.05 m
  const TriMesh base = load_mesh_file(d + "base.dae");
  EXPECT_EQ(base.f.size(), 4u * 24u);
  extent(base, lo, hi);
  EXPECT_NEAR(lo.z(), 0.0, 1e-9);
  EXPECT_NEAR(hi.z(), 0.05, 1e-9);
  EXPECT_NEAR(hi.x(), 0.08, 1e-9);
}

TEST(RobotVisuals, MalformedMeshFilesAreOneLineErrors) {
  const std::string dir = ::testing::TempDir();
  const std::pair<const char*, const char*> bad[] = {
      {"trunc.stl", "not solid at all, too short"}, {"bad.obj", "v 0 0 0\nv 1 0 0\nf 1 2 7\n"},
      {"nan.obj", "v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"}, {"notcollada.dae", "<x/>"},
      {"range.dae", "<COLLADA><library_geometries><geometry id='g'><mesh><source id='s'><float_array>0 0 0 1 0 0 0 1 0"
                    "</float_array></source><vertices id='v'><input semantic='POSITION' source='#s'/></vertices>"
                    "<triangles><input semantic='VERTEX' source='#v' offset='0'/><p>0 1 9</p></triangles></mesh>"
                    "</geometry></library_geometries></COLLADA>"},
      {"mesh.ply", "ply"}};
  for (const auto& [name, text] : bad) {
    const std::string p = dir + "/" + name;
    std::ofstream(p) << text;
    EXPECT_THROW(load_mesh_file(p), std::runtime_error) << name;
  }
  EXPECT_THROW(load_mesh_file(dir + "/missing.stl"), std::runtime_error);
}

TEST(RobotVisuals, SampleRobotsAndAMissingMesh) {
  const std::string d = HAPTREE_ROBOTS_DIR;
  auto arm = io::load_urdf(d + "/arm.urdf", {});
  RobotVisuals v = load_robot_visuals(d + "/arm.urdf", *arm, {});
  EXPECT_EQ(v.meshes, 5);
  EXPECT_EQ(v.missing, 0);
  EXPECT_TRUE(v.warnings.empty());
  size_t tris = 0;
  for (const auto& b : v.bodies) {
    EXPECT_GE(b.body, 1);
    EXPECT_EQ(b.position.size(), b.normal.size());
    EXPECT_EQ(b.position.size(), b.color.size());
    tris += b.position.size() / 9;
  }
  EXPECT_EQ(tris, 4u * 24u + (4u * 24u + 12u) + (4u * 20u + 12u) + 12u + 36u);
  // the upper link's mesh is in its own frame: the cylinder's top at z = 0.3 m above the shoulder
  const int upper = arm->body_index("upper");
  for (const auto& b : v.bodies)
    if (b.body == upper) {
      float top = -1;
      for (size_t i = 2; i < b.position.size(); i += 3) top = std::max(top, b.position[i]);
      EXPECT_NEAR(top, 0.3f, 1e-6f);
      for (size_t i = 0; i < b.color.size(); i += 3) EXPECT_FLOAT_EQ(b.color[i], 0.95f);   // its material
    }
  auto snake = io::load_urdf(d + "/snake.urdf", {});
  v = load_robot_visuals(d + "/snake.urdf", *snake, {});
  EXPECT_EQ(v.primitives, 10 + 10 + 1);   // a box and a joint sphere per module, the head
  EXPECT_EQ(v.bodies.size(), 10u);
  auto cable = io::load_urdf(d + "/cable.urdf", {});
  v = load_robot_visuals(d + "/cable.urdf", *cable, {});
  EXPECT_EQ(v.primitives, 24);
  // a mesh that is not there: its body's sphere and one warning naming the file, also when used twice
  std::string text;
  {
    std::ifstream in(d + "/arm.urdf");
    text.assign(std::istreambuf_iterator<char>(in), {});
  }
  const std::string to = "meshes/arm/nowhere.stl";
  for (const char* from : {"meshes/arm/wrist.stl", "meshes/arm/fore.stl"}) text.replace(text.find(from), std::strlen(from), to);
  const std::string copy = ::testing::TempDir() + "/arm_missing.urdf";
  std::ofstream(copy) << text;
  v = load_robot_visuals(copy, *arm, {d});   // the others through --mesh-path
  EXPECT_EQ(v.meshes, 3);
  EXPECT_EQ(v.missing, 2);
  ASSERT_EQ(v.warnings.size(), 1u);
  EXPECT_NE(v.warnings[0].find("nowhere.stl"), std::string::npos);
}

}  // namespace
}  // namespace haptree
