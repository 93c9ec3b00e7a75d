// replay_coupling on hand-made logs with what the chaos soak puts into a session's log.
//  * an undecodable message on the COUPLER_SETTINGS channel (garbage, a cut message) must not shift which
//    settings message a FEEDBACK is replayed with (it did: pass 2 counted every event on the channel, pass 1
//    only the decodable ones, so the replay took a later settings message, or read past the end);
//  * a FEEDBACK is replayed with the settings of the coupler instance that sent it (the coupler stamps its
//    settings with its FEEDBACK's instance id), not with a later settings message of another coupler;
//  * a copy of an old FEEDBACK (replayed exact bytes, or a stale one: utime an hour back, another instance
//    id) whose inputs are no longer kept is a copy, not a missing snapshot/pose.
// Each FEEDBACK force is computed here with coupler_feedback, as the coupler does: the replay must find
// deviation 0 (same computation on the same bits).
#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <sys/wait.h>

#include <cstdio>
#include <string>

#include "coupler/coupler.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/dca.hpp"
#include "haptree/lcmt_device_state.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "haptree/safety.hpp"
#include "haptree/scenes.hpp"

namespace haptree {
namespace {

std::string run(const std::string& cmd, int* code) {
  FILE* p = ::popen((cmd + " 2>&1").c_str(), "r");
  std::string out;
  char buf[4096];
  for (size_t n; p && (n = std::fread(buf, 1, sizeof buf, p)) > 0;) out.append(buf, n);
  const int st = p ? ::pclose(p) : -1;
  *code = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
  return out;
}

long long number_before(const std::string& out, const std::string& word) {
  const auto k = out.find(word);
  if (k == std::string::npos) return -1;
  const auto b = out.rfind(' ', k - 2);
  return std::atoll(out.c_str() + (b == std::string::npos ? 0 : b + 1));
}

// A log writer with the session's messages: snapshots of protein_like(8), device states, FEEDBACK computed
// as the coupler computes it.
struct LogMaker {
  explicit LogMaker(const std::string& path) : file(path, "w") {
    SceneOptions so;
    so.n = 8;
    model = make_scene("protein_like", so);
    State st(*model);
    Data d(*model);
    forward_dynamics(*model, d, st);
    body = model->nbodies - 1;
    make_coupling_snapshot(*model, d, {make_grab(d, body, Vec3(0.01, 0, 0))}, {}, 1, st.t, snap);
    ws.reserve_for(snap);
  }
  void write(const std::string& channel, const std::string& bytes) {
    lcm::LogEvent ev{};
    ev.timestamp = (t_us += 1000);
    ev.channel = channel;
    ev.datalen = static_cast<int32_t>(bytes.size());
    ev.data = const_cast<char*>(bytes.data());
    ASSERT_EQ(file.writeEvent(&ev), 0);
  }
  template <class M>
  static std::string encode(const M& m) {
    std::string b(static_cast<size_t>(m.getEncodedSize()), '\0');
    m.encode(b.data(), 0, static_cast<int>(b.size()));
    return b;
  }
  void settings(const CouplerOptions& o, int64_t coupler_instance = 77) {
    lcmt_coupler_settings m{};
    to_settings(o, coupler_instance, m);
    write(bus::channel::coupler_settings(o.user), encode(m));
  }
  void snapshot(int64_t version) {
    snap.version = version;
    lcmt_coupling_snapshot m{};
    bus::to_lcmt(snap, m);
    bus::stamp(m, kServer);
    write(bus::channel::coeffs(0), encode(m));
  }
  // A device state and the FEEDBACK the coupler with options `o` computes from it and snapshot `version`
  // (the last one written); returns the FEEDBACK's bytes.
  std::string state_and_feedback(const CouplerOptions& o, int64_t seq) {
    lcmt_device_state p{};
    bus::stamp(p, kDevice);
    p.seq = seq;
    p.device_id = o.device;
    p.orientation[0] = 1;
    p.position_m[0] = 0.0002 * static_cast<double>(seq % 7);
    p.linear_velocity_mps[1] = 0.01;
    p.buttons = 1;
    write(bus::channel::device_state(o.device), encode(p));
    CouplingInputs in{Vec3(p.position_m[0], p.position_m[1], p.position_m[2]),
                      Vec3(p.linear_velocity_mps[0], p.linear_velocity_mps[1], p.linear_velocity_mps[2])};
    Vec6 f_u, f_feed;
    Vec3 force;
    EXPECT_EQ(coupler_feedback(o, snap, in, ws, f_u, f_feed, force), CouplingStatus::kOk);
    force = clamp_norm(finite_or_zero(force), o.max_force_n);
    EXPECT_LT(force.norm(), 0.99 * o.max_force_n);   // not clamped, so it depends on the gains:
    CouplerOptions stiffer = o;
    stiffer.stiffness *= 1.75;
    Vec3 force_stiffer;
    coupler_feedback(stiffer, snap, in, ws, f_u, f_feed, force_stiffer);
    EXPECT_GT((force_stiffer - force).norm(), 1e-3);   // far above the replay's 1e-12 N tolerance
    lcmt_feedback f{};
    bus::stamp(f, kCoupler);
    f.seq = ++feedback_seq;
    f.device_id = o.device;
    f.echo_device_seq = seq;
    f.snapshot_version = snap.version;
    f.snapshot_instance_id = kServer;
    f.echo_device_instance_id = kDevice;
    for (int i = 0; i < 3; ++i) f.force_n[i] = force[i];
    const std::string b = encode(f);
    write(bus::channel::feedback(o.device), b);
    return b;
  }
  // Options whose device origin maps near the grab point (position scale 10).
  CouplerOptions options(double stiffness) const {
    CouplerOptions o;
    o.stiffness = stiffness;
    o.offset = snap.grabs[0].point - Vec3(0.001, 0.0005, 0);
    return o;
  }
  static constexpr int64_t kServer = 0x1111, kDevice = 0x2222, kCoupler = 0x3333;
  lcm::LogFile file;
  std::shared_ptr<const Model> model;
  int body = 0;
  CouplingSnapshot snap;
  CouplingWorkspace ws;
  int64_t t_us = 1700000000000000LL, feedback_seq = 0;
};

TEST(ReplayLog, UndecodableSettingsMessageDoesNotShiftTheSettings) {
  const std::string path = ::testing::TempDir() + "replay_settings.lcmlog";
  {
    LogMaker log(path);
    const CouplerOptions a = log.options(20), b = log.options(35);
    lcmt_coupler_settings s{};
    to_settings(a, 77, s);
    const std::string ch = bus::channel::coupler_settings(0);
    log.write(ch, LogMaker::encode(s).substr(0, 40));                 // cut short: undecodable
    log.write(ch, std::string(LogMaker::encode(s)).append(3, 'x'));   // extended: undecodable
    log.settings(a);
    log.snapshot(1);
    for (int64_t seq = 1; seq <= 3; ++seq) log.state_and_feedback(a, seq);
    log.settings(b);   // a later session setting: must not be used for the FEEDBACK above
    log.snapshot(2);
    for (int64_t seq = 4; seq <= 6; ++seq) log.state_and_feedback(b, seq);
  }
  int code = 0;
  const std::string out = run(std::string(HAPTREE_REPLAY_COUPLING) + " " + path, &code);
  EXPECT_EQ(code, 0) << out;
  EXPECT_EQ(number_before(out, "compared"), 6) << out;
  EXPECT_NE(out.find("max deviation 0.000e+00 N"), std::string::npos) << out;
}

TEST(ReplayLog, FeedbackIsReplayedWithItsOwnCouplersSettings) {
  const std::string path = ::testing::TempDir() + "replay_own_settings.lcmlog";
  {
    LogMaker log(path);
    const CouplerOptions a = log.options(20), other = log.options(35);
    log.settings(a, LogMaker::kCoupler);
    log.snapshot(1);
    log.state_and_feedback(a, 1);
    log.settings(other, 0x4444);   // another coupler's (a replayed message of an earlier session)
    for (int64_t seq = 2; seq <= 4; ++seq) log.state_and_feedback(a, seq);
  }
  int code = 0;
  const std::string out = run(std::string(HAPTREE_REPLAY_COUPLING) + " " + path, &code);
  EXPECT_EQ(code, 0) << out;
  EXPECT_EQ(number_before(out, "compared"), 4) << out;
  EXPECT_NE(out.find("max deviation 0.000e+00 N"), std::string::npos) << out;
}

TEST(ReplayLog, CopyOfAnOldFeedbackIsACopyNotAMissingInput) {
  const std::string path = ::testing::TempDir() + "replay_copies.lcmlog";
  {
    LogMaker log(path);
    const CouplerOptions a = log.options(20);
    log.settings(a);
    log.snapshot(1);
    std::string old = log.state_and_feedback(a, 1);
    // More snapshots than the replay keeps (4096): snapshot 1 is gone when the copies come.
    for (int64_t v = 2; v <= 5000; ++v) log.snapshot(v);
    log.state_and_feedback(a, 2);
    const std::string ch = bus::channel::feedback(0);
    log.write(ch, old);   // replayed: the exact bytes
    // Stale: utime an hour back and another instance id (chaos_soak's header offsets: utime at 12, id at 20).
    for (int i = 0; i < 8; ++i) {
      old[12 + static_cast<size_t>(i)] = static_cast<char>(old[12 + static_cast<size_t>(i)] ^ (i == 5 ? 0x40 : 0));
      old[20 + static_cast<size_t>(i)] = static_cast<char>(0x5a + i);
    }
    log.write(ch, old);
  }
  int code = 0;
  const std::string out = run(std::string(HAPTREE_REPLAY_COUPLING) + " " + path, &code);
  EXPECT_EQ(code, 0) << out;
  EXPECT_EQ(number_before(out, "compared"), 2) << out;
  EXPECT_EQ(number_before(out, "missing snapshot/pose"), 0) << out;
  EXPECT_EQ(number_before(out, "copies of an"), 2) << out;
}

}  // namespace
}  // namespace haptree
