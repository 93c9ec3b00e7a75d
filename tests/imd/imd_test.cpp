// IMD server tests. The receiver here is written from the IMD specification (IMDv3 document of
// Becksteinlab/imdclient, and the v2 layout it inherits), with its own byte handling: it does not use
// haptree/imd's encoder or parser, so it checks them rather than mirroring them.
#include <gtest/gtest.h>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <mutex>
#include <random>
#include <thread>
#include <vector>

#include "haptree/bus/channels.hpp"
#include "haptree/data.hpp"
#include "haptree/dca.hpp"
#include "haptree/imd/protocol.hpp"
#include "haptree/molecule/body_poses.hpp"
#include "haptree/molecule/scene.hpp"
#include "imd_bridge/imd_server.hpp"
#include "tests/imd/imd_receiver.hpp"
#include "sim_server/sim_server.hpp"

namespace haptree {
namespace {

using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;

// ---------------------------------------------------------------- protocol unit tests

TEST(ImdProtocol, ParsesEveryControlPacketAndWaitsForCompleteOnes) {
  const int32_t types[] = {0, 3, 5, 7, 8, 9, 11, 16};
  for (int32_t t : types) {
    std::vector<uint8_t> b;
    put_be32(b, static_cast<uint32_t>(t));
    put_be32(b, 17);
    imd::ClientMessage m;
    for (size_t k = 0; k < 8; ++k)
      EXPECT_EQ(imd::parse_client_message(b.data(), k, 10, m).status, imd::ParseStatus::kNeedMore) << t << " " << k;
    const auto r = imd::parse_client_message(b.data(), b.size(), 10, m);
    ASSERT_EQ(r.status, imd::ParseStatus::kMessage) << t;
    EXPECT_EQ(r.consumed, 8u);
    EXPECT_EQ(static_cast<int32_t>(m.type), t);
    EXPECT_EQ(m.value, 17);
  }
}

TEST(ImdProtocol, MdcommRoundTripAndEveryPrefixNeedsMore) {
  const std::vector<int32_t> idx = {7, 2, 9};
  const std::vector<float> f = {1.5f, -2.f, 3.f, 0.f, 0.25f, -1e3f, 4.f, 5.f, 6.f};
  std::vector<uint8_t> b;
  imd::append_mdcomm(b, idx.data(), f.data(), 3);
  ASSERT_EQ(b.size(), 8u + 16u * 3u);
  EXPECT_EQ(be32(b.data()), 6u);
  EXPECT_EQ(be32(b.data() + 4), 3u);
  imd::ClientMessage m;
  for (size_t k = 0; k < b.size(); ++k)
    ASSERT_EQ(imd::parse_client_message(b.data(), k, 10, m).status, imd::ParseStatus::kNeedMore) << k;
  b.push_back(0xAB);   // the start of the next packet is not consumed
  const auto r = imd::parse_client_message(b.data(), b.size(), 10, m);
  ASSERT_EQ(r.status, imd::ParseStatus::kMessage);
  EXPECT_EQ(r.consumed, b.size() - 1);
  EXPECT_EQ(m.indices, idx);
  EXPECT_EQ(m.forces, f);
}

TEST(ImdProtocol, RejectsGarbageWithoutWaitingForIt) {
  imd::ClientMessage m;
  auto status = [&](int32_t type, int32_t length, std::vector<uint8_t> body = {}) {
    std::vector<uint8_t> b;
    put_be32(b, static_cast<uint32_t>(type));
    put_be32(b, static_cast<uint32_t>(length));
    b.insert(b.end(), body.begin(), body.end());
    return imd::parse_client_message(b.data(), b.size(), 10, m);
  };
  EXPECT_EQ(status(999, 0).status, imd::ParseStatus::kError);
  EXPECT_EQ(status(-1, 0).status, imd::ParseStatus::kError);
  EXPECT_EQ(status(2, 10).status, imd::ParseStatus::kError);          // FCOORDS: engine-only
  EXPECT_EQ(status(4, 2).status, imd::ParseStatus::kError);           // HANDSHAKE: engine-only
  EXPECT_EQ(status(6, -5).status, imd::ParseStatus::kError);          // negative count
  const auto huge = status(6, 1 << 30);                               // would be 16 GiB: refused at once
  EXPECT_EQ(huge.status, imd::ParseStatus::kError);
  EXPECT_NE(huge.error.find("more than the 10"), std::string::npos) << huge.error;
  std::vector<uint8_t> body(16);
  const int32_t bad_index = 10;
  std::memcpy(body.data(), &bad_index, 4);
  EXPECT_EQ(status(6, 1, body).status, imd::ParseStatus::kError);     // index outside [0, 10)
  const int32_t ok_index = 3;
  const float nan = std::nanf("");
  std::memcpy(body.data(), &ok_index, 4);
  std::memcpy(body.data() + 8, &nan, 4);
  EXPECT_EQ(status(6, 1, body).status, imd::ParseStatus::kError);     // non-finite force
  EXPECT_EQ(imd::max_client_message_bytes(10), 8u + 160u);
  // One atom twice (fuzz/imd_client found it accepted): its pull would be applied twice.
  std::vector<uint8_t> twice(32, 0);
  const int32_t idx[2] = {3, 3};
  std::memcpy(twice.data(), idx, 8);
  const auto dup = status(6, 2, twice);
  EXPECT_EQ(dup.status, imd::ParseStatus::kError);
  EXPECT_NE(dup.error.find("atom index 3 given twice"), std::string::npos) << dup.error;
  const int32_t distinct[2] = {3, 4};
  std::memcpy(twice.data(), distinct, 8);
  EXPECT_EQ(status(6, 2, twice).status, imd::ParseStatus::kMessage);
}

// Random streams (a seeded smoke test; T's fuzz target runs the same pure function longer): the
// parser never reads past the buffer (ASan would see it), never consumes more than it was given, and
// every message it accepts is in range.
TEST(ImdProtocol, RandomBytesAreParsedOrRefusedWithinBounds) {
  std::mt19937 g(7);
  imd::ClientMessage m;
  int messages = 0, errors = 0;
  for (int it = 0; it < 20000; ++it) {
    std::vector<uint8_t> b(g() % 64);
    for (auto& c : b) c = static_cast<uint8_t>(g());
    if (b.size() >= 8 && it % 2 == 0) {   // half of them with a valid type, to reach the bodies
      const int32_t t = static_cast<int32_t>(g() % 17), n = static_cast<int32_t>(g() % 5);
      imd::write_be32(b.data(), t);
      imd::write_be32(b.data() + 4, n);
    }
    const auto r = imd::parse_client_message(b.data(), b.size(), 4, m);
    if (r.status == imd::ParseStatus::kMessage) {
      ++messages;
      ASSERT_LE(r.consumed, b.size());
      if (m.type == imd::Type::kMdcomm) {
        ASSERT_EQ(m.forces.size(), 3 * m.indices.size());
        for (int32_t i : m.indices) ASSERT_TRUE(i >= 0 && i < 4);
        for (float f : m.forces) ASSERT_TRUE(std::isfinite(f));
      }
    } else if (r.status == imd::ParseStatus::kError) {
      ++errors;
      ASSERT_FALSE(r.error.empty());
    }
  }
  EXPECT_GT(messages, 1000);
  EXPECT_GT(errors, 1000);
}

TEST(ImdProtocol, EngineHeadersAreBigEndianAndHandshakeIsNative) {
  std::vector<uint8_t> b;
  imd::append_handshake(b, 3);
  imd::SessionInfo si;
  si.velocities = true;
  imd::append_session_info(b, si);
  const float xyz[6] = {1, 2, 3, 4, 5, 6};
  imd::append_vectors(b, imd::Type::kFcoords, xyz, 2);
  ASSERT_EQ(b.size(), 8u + 8u + 7u + 8u + 24u);
  EXPECT_EQ(be32(b.data()), 4u);
  int32_t v;
  std::memcpy(&v, b.data() + 4, 4);
  EXPECT_EQ(v, 3);
  EXPECT_EQ(be32(b.data() + 8), 10u);
  EXPECT_EQ(be32(b.data() + 12), 7u);
  const uint8_t flags[7] = {1, 0, 0, 1, 0, 1, 0};   // time, energies, box, coords, wrapped, vel, forces
  EXPECT_EQ(std::memcmp(b.data() + 16, flags, 7), 0);
  EXPECT_EQ(be32(b.data() + 23), 2u);
  EXPECT_EQ(be32(b.data() + 27), 2u);
  float back[6];
  std::memcpy(back, b.data() + 31, 24);
  for (int i = 0; i < 6; ++i) EXPECT_EQ(back[i], xyz[i]);
}

// ---------------------------------------------------------------- server against published states

// A bus with an ImdServer on it and scene states the test publishes itself from forward kinematics.
struct Fixture {
  bus::Bus bus{"memq://"};
  std::unique_ptr<ImdServer> server;
  std::unique_ptr<bus::HandlerThread> handler;
  std::atomic<bool> stop{false};
  std::thread thread;
  mol::MolecularScene scene = mol::load_molecular_scene("ala20");
  explicit Fixture(ImdServerOptions o) {
    o.port = 0;
    o.scene = "ala20";
    server = std::make_unique<ImdServer>(bus, o);
    handler = std::make_unique<bus::HandlerThread>(bus, 2);
    thread = std::thread([this] { server->run(stop); });
  }
  ~Fixture() {
    stop = true;
    thread.join();
    handler->stop();
  }
  // Publishes the scene state of configuration q at (version, t); returns the atom positions in Å
  // from the scene's own kinematics (Data::R, Data::r), the oracle for what the server sends.
  std::vector<Vec3> publish(const Eigen::VectorXd& q, int64_t version, double t) {
    const Model& m = *scene.model;
    Data d(m);
    forward_kinematics(m, d, q);
    lcmt_scene_state s{};
    bus::stamp(s, 1);
    s.version = version;
    s.sim_time = t;
    s.nbodies = m.nbodies;
    s.body_active.assign(s.nbodies, 0);
    s.first_body = 0;
    s.total_bodies = s.nbodies;
    for (int k = 0; k < m.nbodies; ++k) {
      s.body_position.push_back({d.r[k].x(), d.r[k].y(), d.r[k].z()});
      const Quat qk(d.R[k]);
      s.body_orientation.push_back({qk.w(), qk.x(), qk.y(), qk.z()});
    }
    bus.publish(bus::channel::scene_state(), s);
    std::vector<Vec3> x;
    scene.atom_positions(d, x);
    for (auto& p : x) p *= 10.0;
    return x;
  }
  Eigen::VectorXd random_q(unsigned seed) const {
    std::mt19937 g(seed);
    std::uniform_real_distribution<double> u(-0.3, 0.3);
    Eigen::VectorXd q = neutral_configuration(*scene.model);
    for (int i = 0; i < q.size(); ++i) q[i] += u(g);
    return q;
  }
};

// Waits until the server sees a receiver (the handshake was sent).
void wait_connected(const ImdServer& s, bool want = true) {
  for (int i = 0; i < 500 && s.client_connected() != want; ++i) std::this_thread::sleep_for(2ms);
}

TEST(ImdServer, HandshakeV2ThenCoordinatesOnlyAfterGo) {
  ImdServerOptions o;
  o.version = 2;
  Fixture fx(o);
  Receiver r(fx.server->port());
  ASSERT_GE(r.fd, 0);
  EXPECT_EQ(r.handshake(), 2);
  wait_connected(*fx.server);
  const auto q = fx.random_q(1);
  fx.publish(q, 1, 0.0005);
  int32_t type, n;
  EXPECT_FALSE(r.header(type, n, 0.3)) << "no frame before IMD_GO";
  ASSERT_TRUE(r.send_simple(3));   // GO
  std::vector<Vec3> want;
  for (int i = 0; i < 200 && !r.header(type, n, 0.01); ++i) want = fx.publish(q, 2 + i, 0.001 * (i + 2));
  EXPECT_EQ(type, 2) << "v2 sends coordinates, no time packet";
  ASSERT_EQ(n, fx.scene.natoms());
  std::vector<float> x(3 * static_cast<size_t>(n));
  ASSERT_TRUE(r.read_exact(x.data(), x.size() * 4));
  EXPECT_NEAR(x[0], want[0].x(), 1e-4 * std::max(1.0, std::abs(want[0].x())));
}

TEST(ImdServer, HandshakeV3SessionInfoAndCoordinatesMatchTheSessionsAtoms) {
  ImdServerOptions o;
  o.version = 3;
  Fixture fx(o);
  Receiver r(fx.server->port());
  ASSERT_GE(r.fd, 0);
  ASSERT_EQ(r.handshake(), 3);
  int32_t type, n;
  ASSERT_TRUE(r.header(type, n));
  ASSERT_EQ(type, 10);   // session info
  ASSERT_EQ(n, 7);
  uint8_t flags[7];
  ASSERT_TRUE(r.read_exact(flags, 7));
  const uint8_t want_flags[7] = {1, 0, 0, 1, 0, 1, 1};   // time, coordinates, velocities, forces
  EXPECT_EQ(std::memcmp(flags, want_flags, 7), 0);
  ASSERT_TRUE(r.send_simple(3));
  wait_connected(*fx.server);
  std::this_thread::sleep_for(50ms);   // GO handled before the states below
  // Two configurations 0.01 ps apart (20 steps of 0.0005): coordinates and finite-difference velocities.
  const auto qa = fx.random_q(2), qb = fx.random_q(3);
  const auto xa = fx.publish(qa, 100, 0.05);
  Frame fa, fb;
  ASSERT_TRUE(read_frame(r, fa, true));
  const auto xb = fx.publish(qb, 120, 0.06);
  ASSERT_TRUE(read_frame(r, fb, true));
  ASSERT_TRUE(fa.has_time && fb.has_time);
  EXPECT_EQ(fa.step, 100);
  EXPECT_EQ(fb.step, 120);
  EXPECT_DOUBLE_EQ(fb.time, 0.06);
  EXPECT_NEAR(fb.dt, 0.0005, 1e-12);   // (0.06 - 0.05) / 20 steps
  ASSERT_EQ(fb.x.size(), 3u * fx.scene.natoms());
  // float32 carries 24 bits: |x| ≤ ~50 Å rounds to ≤ 50 · 2^-24 ≈ 3e-6 Å; the quaternion round trip
  // adds ~1e-14. 1e-5 Å is a bound on both with margin, and far below any misplaced atom (≥ 0.1 Å).
  double worst = 0;
  for (int a = 0; a < fx.scene.natoms(); ++a)
    for (int i = 0; i < 3; ++i) {
      worst = std::max(worst, std::abs(fa.x[3 * a + i] - xa[a][i]));
      worst = std::max(worst, std::abs(fb.x[3 * a + i] - xb[a][i]));
    }
  EXPECT_LT(worst, 1e-5);
  // Velocities, Å/ps: (xb − xa) / 0.01 ps. Float32 of values up to ~1e3 Å/ps: ~1e-4 relative to
  // 0.01 of the 1e-5 above, i.e. a bound of 1e-5 Å / 0.01 ps = 1e-3 Å/ps plus float32 rounding.
  double worst_v = 0;
  for (int a = 0; a < fx.scene.natoms(); ++a)
    for (int i = 0; i < 3; ++i)
      worst_v = std::max(worst_v, std::abs(fb.v[3 * a + i] - (xb[a][i] - xa[a][i]) / 0.01));
  EXPECT_LT(worst_v, 2e-3);
  // Forces: the scene's force field at configuration b, kJ/(mol nm) / 10 = kJ/(mol Å), float32.
  std::vector<Vec3> xb_nm(xb.size()), F;
  for (size_t a = 0; a < xb.size(); ++a) xb_nm[a] = xb[a] / 10.0;
  fx.scene.force_field->compute_atoms(xb_nm, F);
  ASSERT_EQ(fb.f.size(), 3u * F.size());
  double fmax = 0, worst_f = 0;
  for (size_t a = 0; a < F.size(); ++a)
    for (int i = 0; i < 3; ++i) {
      fmax = std::max(fmax, std::abs(F[a][i]) / 10.0);
      worst_f = std::max(worst_f, std::abs(fb.f[3 * a + i] - F[a][i] / 10.0));
    }
  EXPECT_GT(fmax, 1.0) << "a random conformation has nonzero forces";
  // The server evaluates at its own positions (from the quaternions, ~1e-15 nm apart) and rounds to
  // float32: relative 1e-6 of the largest force covers both.
  EXPECT_LT(worst_f, 1e-6 * fmax + 1e-6) << "max |F| " << fmax;
}

TEST(ImdServer, RateChangePauseResumeAndDisconnect) {
  ImdServerOptions o;
  o.version = 3;
  Fixture fx(o);
  Receiver r(fx.server->port());
  ASSERT_EQ(r.handshake(), 3);
  int32_t type, n;
  uint8_t flags[7];
  ASSERT_TRUE(r.header(type, n) && r.read_exact(flags, 7));
  ASSERT_TRUE(r.send_simple(3));
  ASSERT_TRUE(r.send_simple(8, 5));   // TRATE: a frame every 5 steps
  std::this_thread::sleep_for(50ms);
  const auto q = fx.random_q(4);
  std::atomic<bool> done{false};
  std::atomic<int64_t> published{0};
  // One state every 10 ms: slower than the server's 5 ms poll, so it sees (nearly) every version and a
  // step difference of exactly 5 can show. At 1 ms the server coalesced ~5 states per poll, and under
  // load (stress-ng --cpu 2) no difference was exactly 5 in 2 of 40 runs.
  std::thread pub([&] {
    for (int64_t v = 1; !done; ++v) {
      fx.publish(q, v, 0.0005 * v);
      published = v;
      std::this_thread::sleep_for(10ms);
    }
  });
  Frame f;
  std::vector<int64_t> steps;
  for (int i = 0; i < 10; ++i) {
    ASSERT_TRUE(read_frame(r, f, true));
    steps.push_back(f.step);
  }
  for (size_t i = 1; i < steps.size(); ++i) EXPECT_GE(steps[i] - steps[i - 1], 5) << i;
  int exact = 0;
  for (size_t i = 1; i < steps.size(); ++i) exact += steps[i] - steps[i - 1] == 5;
  EXPECT_GT(exact, 0) << "every 5th step is served when the receiver keeps up";
  // Pause: drain what was in flight until 100 ms pass without a byte (unpaused, a frame comes every
  // ~50 ms), then no frame while at least 2 frames' worth of states (10) are published — counted, not
  // timed: a fixed 0.4 s saw only 13-46 of the 50 states it expected under load.
  ASSERT_TRUE(r.send_simple(7));
  uint8_t junk[65536];
  for (const auto until = Clock::now() + 3s; Clock::now() < until;) {
    pollfd p{r.fd, POLLIN, 0};
    if (::poll(&p, 1, 100) <= 0) break;
    if (::recv(r.fd, junk, sizeof junk, MSG_DONTWAIT) <= 0) break;
  }
  const int64_t before = published;
  EXPECT_FALSE(r.header(type, n, 0.4)) << "a frame arrived while paused";
  for (const auto until = Clock::now() + 5s; published - before < 10 && Clock::now() < until;)
    EXPECT_FALSE(r.header(type, n, 0.05)) << "a frame arrived while paused";
  EXPECT_GE(published - before, 10) << "the session keeps publishing while the receiver is paused";
  ASSERT_TRUE(r.send_simple(7));   // v3: pause is idempotent, still paused
  EXPECT_FALSE(r.header(type, n, 0.3));
  ASSERT_TRUE(r.send_simple(11));  // RESUME
  ASSERT_TRUE(read_frame(r, f, true, 2));
  ASSERT_TRUE(r.send_simple(8, 0));   // TRATE < 1: back to the default (every step)
  // Disconnect: the engine closes, and takes the next receiver.
  ASSERT_TRUE(r.send_simple(0));
  EXPECT_TRUE(r.closed_by_peer());
  wait_connected(*fx.server, false);
  EXPECT_FALSE(fx.server->client_connected());
  Receiver r2(fx.server->port());
  EXPECT_EQ(r2.handshake(), 3);
  done = true;
  pub.join();
  EXPECT_EQ(fx.server->counters().dropped.load(), 0);
}

TEST(ImdServer, V2PauseToggles) {
  ImdServerOptions o;
  o.version = 2;
  Fixture fx(o);
  Receiver r(fx.server->port());
  ASSERT_EQ(r.handshake(), 2);
  ASSERT_TRUE(r.send_simple(3));
  ASSERT_TRUE(r.send_simple(7));   // pause
  std::this_thread::sleep_for(50ms);
  const auto q = fx.random_q(5);
  int32_t type, n;
  for (int i = 0; i < 20; ++i) fx.publish(q, i + 1, 0.001 * i);
  EXPECT_FALSE(r.header(type, n, 0.3));
  ASSERT_TRUE(r.send_simple(7));   // v2: the second pause resumes
  std::this_thread::sleep_for(50ms);
  bool got = false;
  for (int i = 0; i < 200 && !got; ++i) {
    fx.publish(q, 100 + i, 0.1 + 0.001 * i);
    got = r.header(type, n, 0.01);
  }
  EXPECT_TRUE(got);
  EXPECT_EQ(type, 2);
}

// The IMD pull as a user force: converted units, the atom's body, the atom as grab point, and the
// wrench of several atoms about it.
TEST(ImdServer, MdcommBecomesTheUserForceInSceneUnits) {
  for (int version : {2, 3}) {
    ImdServerOptions o;
    o.version = version;
    o.user_id = 3;
    Fixture fx(o);
    std::mutex mu;
    lcmt_user_force last{};
    int64_t got = 0;
    fx.bus.subscribe<lcmt_user_force>(bus::channel::user_force(3), [&](const lcmt_user_force& m, const std::string&) {
      std::lock_guard<std::mutex> l(mu);
      last = m;
      ++got;
    });
    Receiver r(fx.server->port());
    ASSERT_EQ(r.handshake(), version);
    ASSERT_TRUE(r.send_simple(3));
    const auto q = fx.random_q(6);
    const auto x = fx.publish(q, 1, 0.0005);   // Å
    std::this_thread::sleep_for(50ms);
    const int a = fx.scene.natoms() - 3, b = 0;
    ASSERT_TRUE(r.send_forces({a, b}, {1.f, -2.f, 0.5f, 0.f, 0.f, 0.25f}));
    const double unit = version == 2 ? 41.84 : 10.0;   // kcal/(mol Å) or kJ/(mol Å) -> kJ/(mol nm)
    const Vec3 fa = unit * Vec3(1, -2, 0.5), fb = unit * Vec3(0, 0, 0.25);
    // The strongest pulled atom anchors the grab; the other's force acts about it.
    const Vec3 p = x[a] / 10.0;
    const Vec3 M = (x[b] / 10.0 - p).cross(fb);
    lcmt_user_force m{};
    for (int i = 0; i < 200; ++i) {
      std::this_thread::sleep_for(5ms);
      std::lock_guard<std::mutex> l(mu);
      if (got > 0 && last.active) { m = last; break; }
    }
    ASSERT_TRUE(m.active) << "v" << version;
    EXPECT_EQ(m.user_id, 3);
    EXPECT_EQ(m.grab_body, fx.scene.torsion.atom_model_body[a]);
    for (int i = 0; i < 3; ++i) {
      EXPECT_NEAR(m.grab_point[i], p[i], 1e-6);   // Å float32 round trip of the oracle: ~1e-7 nm
      EXPECT_NEAR(m.force[3 + i], fa[i] + fb[i], 1e-4) << "v" << version;
      EXPECT_NEAR(m.force[i], M[i], 1e-4) << "v" << version;
    }
    // An empty MDCOMM releases the pull.
    ASSERT_TRUE(r.send_forces({}, {}));
    bool released = false;
    for (int i = 0; i < 200 && !released; ++i) {
      std::this_thread::sleep_for(5ms);
      std::lock_guard<std::mutex> l(mu);
      released = !last.active;
    }
    EXPECT_TRUE(released);
  }
}

// ---------------------------------------------------------------- against a running session

struct Session {
  bus::Bus bus{"memq://"};
  SimServerOptions so;
  std::unique_ptr<SimServer> sim;
  std::unique_ptr<ImdServer> imd;
  std::unique_ptr<bus::HandlerThread> handler;
  std::atomic<bool> stop{false};
  std::thread sim_thread, imd_thread;
  explicit Session(ImdServerOptions o) {
    so.scene = "ala20";
    so.dt = 0.0005;
    so.rate_hz = 4000;
    so.display_rate_hz = 100;
    so.users = 1;
    so.max_user_force = 5000;   // the IMD pull's own clamp (ImdServerOptions::max_force): the server must not cut it
    sim = std::make_unique<SimServer>(bus, so);
    o.port = 0;
    o.scene = "ala20";
    o.user_id = 0;
    imd = std::make_unique<ImdServer>(bus, o);
    handler = std::make_unique<bus::HandlerThread>(bus, 2);
    sim_thread = std::thread([this] { sim->run(stop); });
    imd_thread = std::thread([this] { imd->run(stop); });
  }
  ~Session() {
    stop = true;
    imd_thread.join();
    sim_thread.join();
    handler->stop();
  }
};

// Pulls atom `a` with `force` (kJ/(mol Å), IMD v3) for 1 ps of session time; returns its displacement (Å).
Vec3 pull_atom(const Vec3& force, int64_t* published = nullptr) {
  ImdServerOptions o;
  o.version = 3;
  Session s(o);
  Receiver r(s.imd->port());
  EXPECT_EQ(r.handshake(), 3);
  int32_t type, n;
  uint8_t flags[7];
  EXPECT_TRUE(r.header(type, n) && r.read_exact(flags, 7));
  EXPECT_TRUE(r.send_simple(3));
  Frame f0, f;
  if (!read_frame(r, f0, true)) return Vec3::Constant(NAN);
  const int natoms = static_cast<int>(f0.x.size() / 3);
  const int a = natoms - 3;   // near the free C-terminal end (the first segment root is welded)
  EXPECT_TRUE(r.send_forces({a}, {float(force.x()), float(force.y()), float(force.z())}));
  do {
    if (!read_frame(r, f, true)) return Vec3::Constant(NAN);
  } while (f.time < f0.time + 1.0);
  if (published) *published = s.imd->counters().forces_published.load();
  return Vec3(f.x[3 * a] - f0.x[3 * a], f.x[3 * a + 1] - f0.x[3 * a + 1], f.x[3 * a + 2] - f0.x[3 * a + 2]);
}

TEST(ImdSession, ForceOnAnAtomMovesItAlongTheForce) {
  // 25 kJ/(mol Å) = 250 kJ/(mol nm), under the default clamp. The unpulled atom drifts by itself
  // (the force field relaxes the ideal helix: ~1.2 Å along this direction in 1 ps), so the test pulls
  // both ways from the same start: the drift is common, the pull is not.
  const Vec3 dir = Vec3(1, 1, 0).normalized();
  int64_t published = 0;
  const Vec3 plus = pull_atom(25.0 * dir, &published), minus = pull_atom(-25.0 * dir);
  const double along_plus = plus.dot(dir), along_minus = minus.dot(dir);
  std::printf("pulled atom: %+.3f A along +f, %+.3f A along -f (component on +f), in 1 ps\n", along_plus,
              along_minus);
  EXPECT_GT(along_plus, 3.0) << "moves along +f";
  EXPECT_LT(along_minus, -3.0) << "moves along -f";
  EXPECT_GT(along_plus - along_minus, 8.0);
  EXPECT_GT(published, 0);
}

TEST(ImdSession, GarbageHugeTruncatedSilentAndStalledReceiversNeverStopTheSession) {
  ImdServerOptions o;
  o.version = 2;
  o.go_timeout_s = 0.3;
  o.send_timeout_s = 0.5;
  Session s(o);
  const int port = s.imd->port();
  auto steps_advance = [&] {
    const int64_t a = s.sim->steps_done();
    std::this_thread::sleep_for(100ms);
    return s.sim->steps_done() > a;
  };
  int64_t dropped = 0;
  auto expect_dropped = [&](Receiver& r, const char* what) {
    EXPECT_TRUE(r.closed_by_peer()) << what;
    wait_connected(*s.imd, false);
    EXPECT_EQ(s.imd->counters().dropped.load(), ++dropped) << what;
    EXPECT_TRUE(steps_advance()) << what;
  };
  {  // garbage header
    Receiver r(port);
    ASSERT_EQ(r.handshake(), 2);
    ASSERT_TRUE(r.send_bytes({0xde, 0xad, 0xbe, 0xef, 0x01, 0x02, 0x03, 0x04}));
    expect_dropped(r, "garbage header");
  }
  {  // huge length: 2^30 atoms (16 GiB) must be refused at the header
    Receiver r(port);
    ASSERT_EQ(r.handshake(), 2);
    ASSERT_TRUE(r.send_simple(3));
    ASSERT_TRUE(r.send_simple(6, 1 << 30));
    expect_dropped(r, "huge length");
  }
  {  // truncated MDCOMM, then the receiver goes away
    Receiver r(port);
    ASSERT_EQ(r.handshake(), 2);
    ASSERT_TRUE(r.send_simple(3));
    std::vector<uint8_t> b;
    put_be32(b, 6);
    put_be32(b, 2);
    b.resize(b.size() + 12);   // 12 of 32 body bytes
    ASSERT_TRUE(r.send_bytes(b));
    std::this_thread::sleep_for(50ms);
    ::shutdown(r.fd, SHUT_WR);
    expect_dropped(r, "truncated packet");
  }
  {  // silent: never sends IMD_GO
    Receiver r(port);
    ASSERT_EQ(r.handshake(), 2);
    expect_dropped(r, "no IMD_GO");
  }
  {  // stalled: GO, then never reads (small receive buffer fills up)
    Receiver r(port, 4096);
    ASSERT_EQ(r.handshake(), 2);
    ASSERT_TRUE(r.send_simple(3));
    EXPECT_TRUE(r.closed_by_peer(0.1) == false);
    std::this_thread::sleep_for(100ms);
    // Not reading: wait for the engine to give up (the test only looks for EOF afterwards).
    bool gone = false;
    for (int i = 0; i < 300 && !gone; ++i) {
      std::this_thread::sleep_for(10ms);
      gone = !s.imd->client_connected();
    }
    EXPECT_TRUE(gone) << "stalled receiver";
    EXPECT_EQ(s.imd->counters().dropped.load(), ++dropped);
    EXPECT_GT(s.imd->counters().frames_skipped.load(), 0) << "frames were skipped, not queued";
    EXPECT_TRUE(steps_advance());
  }
  {  // a client that vanishes without a word while streaming
    auto r = std::make_unique<Receiver>(port);
    ASSERT_EQ(r->handshake(), 2);
    ASSERT_TRUE(r->send_simple(3));
    Frame f;
    ASSERT_TRUE(read_frame(*r, f, false));
    r.reset();
    wait_connected(*s.imd, false);
    EXPECT_FALSE(s.imd->client_connected());
  }
  // After all that, a well-behaved receiver is served.
  Receiver r(port);
  ASSERT_EQ(r.handshake(), 2);
  ASSERT_TRUE(r.send_simple(3));
  Frame f;
  ASSERT_TRUE(read_frame(r, f, false));
  EXPECT_EQ(f.x.size(), 3u * s.imd->natoms());
  EXPECT_TRUE(steps_advance());
}

TEST(ImdServer, RefusesBadOptionsInWords) {
  bus::Bus bus("memq://");
  ImdServerOptions o;
  o.port = 0;
  o.scene = "protein_like";
  try {
    ImdServer s(bus, o);
    FAIL() << "procedural scene accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("molecular"), std::string::npos) << e.what();
  }
  o.scene = "ala20";
  o.bind = "localhost:1";
  EXPECT_THROW(ImdServer(bus, o), std::runtime_error);
  o.bind = "127.0.0.1";
  o.version = 4;
  EXPECT_THROW(ImdServer(bus, o), std::invalid_argument);
}

}  // namespace
}  // namespace haptree
