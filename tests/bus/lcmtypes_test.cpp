// Tests for lcmtypes/*.lcm (schema_version first, fixed-size fields where possible) and haptree/bus/wire.hpp, snapshot.hpp.
#include <gtest/gtest.h>

#include <random>
#include <set>
#include <type_traits>

#include "haptree/bus/snapshot.hpp"
#include "haptree/coupling.hpp"
#include "haptree/bus/wire.hpp"

namespace haptree::bus {
namespace {

std::mt19937_64 rng(42);
double rd() { return std::uniform_real_distribution<double>(-1e3, 1e3)(rng); }
int32_t ri() { return std::uniform_int_distribution<int32_t>(-100000, 100000)(rng); }
int64_t rl() { return std::uniform_int_distribution<int64_t>()(rng); }

lcmt_device_state make(lcmt_device_state* m) {
  stamp(*m, rl(), rl());
  m->seq = rl();
  m->device_id = ri();
  for (auto& x : m->position_m) x = rd();
  for (auto& x : m->orientation) x = rd();
  for (auto& x : m->linear_velocity_mps) x = rd();
  m->buttons = ri();
  return *m;
}
lcmt_feedback make(lcmt_feedback* m) {
  stamp(*m, rl(), rl());
  m->seq = rl();
  m->device_id = ri();
  m->echo_device_seq = rl();
  m->snapshot_version = rl();
  for (auto& x : m->force_n) x = rd();
  for (auto& x : m->torque_nm) x = rd();
  m->flags = lcmt_feedback::FLAG_CLAMPED | lcmt_feedback::FLAG_STALE;
  return *m;
}
lcmt_user_force make(lcmt_user_force* m) {
  stamp(*m, rl(), rl());
  m->seq = rl();
  m->user_id = ri();
  m->grab_body = ri();
  for (auto& x : m->grab_point) x = rd();
  for (auto& x : m->force) x = rd();
  m->snapshot_version = rl();
  m->active = true;
  return *m;
}
lcmt_coupling_snapshot make(lcmt_coupling_snapshot* m) {
  SnapshotView s;
  s.model_fingerprint = 0xF00DFACECAFEBEEFull;  // top bit set: exercises the int64 bit-cast
  s.version = rl();
  s.sim_time = rd();
  for (int g = 0; g < 3; ++g) s.grabs.push_back({ri(), {rd(), rd(), rd()}, {rd(), rd(), rd()}});
  for (int i = 0; i < 40; ++i) s.ints.push_back(ri());
  for (int i = 0; i < 500; ++i) s.values.push_back(rd());
  to_lcmt(s, *m);
  m->utime = rl();
  m->instance_id = rl();
  m->user_id = ri();
  return *m;
}
lcmt_scene_state make(lcmt_scene_state* m) {
  stamp(*m, rl(), rl());
  m->version = rl();
  m->sim_time = rd();
  m->nbodies = 17;
  m->body_position.assign(17, std::vector<double>(3));
  m->body_orientation.assign(17, std::vector<double>(4));
  for (auto& p : m->body_position) for (auto& x : p) x = rd();
  for (auto& p : m->body_orientation) for (auto& x : p) x = rd();
  m->active_dofs = ri();
  m->neglected_metric = rd();
  m->step_ms = rd();
  m->body_active.assign(17, 1);
  m->first_body = 0;
  m->total_bodies = 17;
  return *m;
}
lcmt_process_stats make(lcmt_process_stats* m) {
  stamp(*m, rl(), rl());
  m->seq = rl();
  m->process_name = "coupler";
  m->process_id = 3;
  m->loop_rate_hz = rd();
  m->latency_p50_us = rd();
  m->latency_p99_us = rd();
  m->snapshot_age_ms = rd();
  m->messages_in = rl();
  m->messages_out = rl();
  m->rejected_messages = rl();
  m->stale_events = rl();
  m->watchdog_events = rl();
  m->clamp_events = rl();
  m->nonfinite_events = rl();
  m->n_extra = 2;
  m->extra_names = {"force_n", "snapshot_version"};
  m->extra_values = {rd(), rd()};
  return *m;
}

template <class T>
std::vector<uint8_t> encode(const T& m) {
  std::vector<uint8_t> b(static_cast<size_t>(m.getEncodedSize()));
  EXPECT_EQ(m.encode(b.data(), 0, static_cast<int>(b.size())), static_cast<int>(b.size()));
  return b;
}

template <class T>
class LcmTypes : public ::testing::Test {};
using AllTypes = ::testing::Types<lcmt_device_state, lcmt_feedback, lcmt_user_force, lcmt_coupling_snapshot,
                                  lcmt_scene_state, lcmt_process_stats>;
TYPED_TEST_SUITE(LcmTypes, AllTypes);

TYPED_TEST(LcmTypes, RoundTripIsByteExactAndSchemaAtByte8) {
  TypeParam m{};
  make(&m);
  const auto bytes = encode(m);
  int32_t schema = -1;
  ASSERT_TRUE(peek_schema_version(bytes.data(), bytes.size(), &schema));
  EXPECT_EQ(schema, TypeParam::SCHEMA_VERSION);
  // Schema 2 added instance_id; FEEDBACK's schema 3 added the instance ids of the snapshot and device state
  // it answers (replay across restarts).
  EXPECT_EQ(schema, (std::is_same_v<TypeParam, lcmt_feedback> ? 3 : 2));
  // instance_id right after utime: readable at byte 20 without decoding (origin checks, duplicate writers).
  int64_t inst = 0;
  ASSERT_TRUE(peek_instance_id(bytes.data(), bytes.size(), &inst));
  EXPECT_EQ(inst, m.instance_id);
  EXPECT_NE(m.instance_id, 0);
  int64_t fp = 0;
  ASSERT_TRUE(peek_fingerprint(bytes.data(), bytes.size(), &fp));
  EXPECT_EQ(fp, TypeParam::getHash());

  TypeParam back{};
  ASSERT_EQ(decode_checked(bytes.data(), bytes.size(), back), DecodeResult::kOk);
  EXPECT_EQ(back.utime, m.utime);
  EXPECT_EQ(back.instance_id, m.instance_id);
  EXPECT_EQ(encode(back), bytes);  // every field survived (doubles bit-exact)

  // A schema_version other than this build's decodes but is refused, and is readable at byte 8.
  TypeParam other = m;
  other.schema_version = 99;
  const auto ob = encode(other);
  ASSERT_TRUE(peek_schema_version(ob.data(), ob.size(), &schema));
  EXPECT_EQ(schema, 99);
  EXPECT_EQ(decode_checked(ob.data(), ob.size(), back), DecodeResult::kSchemaMismatch);

  // Truncations and a trailing byte are refused, never thrown.
  for (size_t n : {size_t(0), size_t(7), size_t(11), bytes.size() / 2, bytes.size() - 1})
    EXPECT_NE(decode_checked(bytes.data(), n, back), DecodeResult::kOk) << n;
  auto longer = bytes;
  longer.push_back(0);
  EXPECT_EQ(decode_checked(longer.data(), longer.size(), back), DecodeResult::kMalformed);
}

TYPED_TEST(LcmTypes, CorruptedBodyAfterRightFingerprintNeverThrowsOrBalloons) {
  TypeParam m{};
  make(&m);
  auto bytes = encode(m);
  std::mt19937 g(7);
  TypeParam back{};
  int ok = 0;
  for (int trial = 0; trial < 2000; ++trial) {
    auto b = bytes;
    const int flips = 1 + trial % 8;
    for (int k = 0; k < flips; ++k) b[8 + g() % (b.size() - 8)] = static_cast<uint8_t>(g());
    if (trial % 3 == 0) b.resize(8 + g() % (b.size() - 8));
    if (decode_checked(b.data(), b.size(), back) != DecodeResult::kOk) continue;
    ++ok;
    // Whatever is accepted is a consistent message: it encodes back to exactly the accepted bytes
    // (strings excepted: a flipped byte can put a NUL inside one, which encode() stops at).
    if constexpr (!std::is_same_v<TypeParam, lcmt_process_stats>) {
      EXPECT_EQ(encode(back), b);
    }
  }
  ::testing::Test::RecordProperty("accepted_after_corruption", ok);
  EXPECT_LT(back.getEncodedSize(), 4 * static_cast<int>(bytes.size()) + 1024);
}

// counts_plausible reads the variable-length counts at fixed offsets that follow the field order of the
// .lcm files: check each offset against an encoded message whose counts are known.
int32_t be32_at(const std::vector<uint8_t>& b, size_t off) {
  return static_cast<int32_t>((uint32_t(b[off]) << 24) | (uint32_t(b[off + 1]) << 16) | (uint32_t(b[off + 2]) << 8) |
                              uint32_t(b[off + 3]));
}
TEST(LcmTypes, CountOffsetsOfThePlausibilityGuardFollowTheFieldOrder) {
  lcmt_coupling_snapshot snap{};
  make(&snap);
  EXPECT_EQ(be32_at(encode(snap), 56), 3);    // n_grabs
  lcmt_scene_state scene{};
  make(&scene);
  EXPECT_EQ(be32_at(encode(scene), 44), 17);  // nbodies
  lcmt_process_stats stats{};
  make(&stats);
  EXPECT_EQ(be32_at(encode(stats), 36), 8);   // strlen("coupler") + NUL
  // A count far beyond the message is refused before decode() would resize() for it.
  for (auto [bytes, off] : {std::pair{encode(snap), size_t(56)}, std::pair{encode(scene), size_t(44)},
                            std::pair{encode(stats), size_t(36)}}) {
    bytes[off] = 0x7f;
    lcmt_coupling_snapshot a;
    lcmt_scene_state b;
    lcmt_process_stats c;
    const DecodeResult r = off == 56 ? decode_checked(bytes.data(), bytes.size(), a)
                           : off == 44 ? decode_checked(bytes.data(), bytes.size(), b)
                                       : decode_checked(bytes.data(), bytes.size(), c);
    EXPECT_EQ(r, DecodeResult::kMalformed) << off;
  }
}

TEST(LcmTypes, InstanceIdsAreNonzeroAndDistinct) {
  std::set<int64_t> ids;
  for (int i = 0; i < 1000; ++i) ids.insert(new_instance_id());
  EXPECT_EQ(ids.size(), 1000u);
  EXPECT_EQ(ids.count(0), 0u);
}

TEST(LcmTypes, FingerprintsAreDistinct) {
  const std::set<int64_t> fps = {lcmt_device_state::getHash(), lcmt_feedback::getHash(),
                                 lcmt_user_force::getHash(),   lcmt_coupling_snapshot::getHash(),
                                 lcmt_scene_state::getHash(),  lcmt_process_stats::getHash()};
  EXPECT_EQ(fps.size(), 6u);
}

TEST(Snapshot, ViewToLcmtToViewIsACopy) {
  SnapshotView s;
  s.model_fingerprint = 0x8000000000000001ull;
  s.version = 12345;
  s.sim_time = 0.25;
  s.grabs.push_back({4, {1, 2, 3}, {-1, -2, -3}});
  s.grabs.push_back({9, {4, 5, 6}, {0.5, 0.25, 0.125}});
  s.ints = {1, -2, 3};
  s.values = {0.1, 0.2, 0.3, 0.4};
  lcmt_coupling_snapshot m;
  to_lcmt(s, m);
  m.utime = 1;
  m.user_id = 2;
  const auto bytes = encode(m);
  lcmt_coupling_snapshot m2;
  ASSERT_EQ(decode_checked(bytes.data(), bytes.size(), m2), DecodeResult::kOk);
  SnapshotView r;
  from_lcmt(m2, r);
  EXPECT_EQ(r.model_fingerprint, s.model_fingerprint);
  EXPECT_EQ(r.version, s.version);
  EXPECT_EQ(r.sim_time, s.sim_time);
  ASSERT_EQ(r.grabs.size(), 2u);
  for (size_t g = 0; g < 2; ++g) {
    EXPECT_EQ(r.grabs[g].body, s.grabs[g].body);
    EXPECT_EQ(r.grabs[g].point, s.grabs[g].point);
    EXPECT_EQ(r.grabs[g].velocity, s.grabs[g].velocity);
  }
  EXPECT_EQ(r.ints, s.ints);
  EXPECT_EQ(r.values, s.values);
}

// The coupling's own snapshot type converts with the same templates (no dependency of the bus on it).
TEST(Snapshot, CouplingSnapshotToLcmtAndBack) {
  CouplingSnapshot s;
  s.model_fingerprint = 0xFEDCBA9876543210ull;
  s.version = 77;
  s.sim_time = 1.5;
  Grab g;
  g.body = 3;
  g.point = Vec3(1, 2, 3);
  g.velocity = Vec3(4, 5, 6);
  s.grabs = {g};
  s.ints = {kSnapshotLayout, 1, 2};
  s.values = {1.0, -2.0};
  lcmt_coupling_snapshot m;
  to_lcmt(s, m);
  const auto bytes = encode(m);
  lcmt_coupling_snapshot m2;
  ASSERT_EQ(decode_checked(bytes.data(), bytes.size(), m2), DecodeResult::kOk);
  CouplingSnapshot r;
  from_lcmt(m2, r);
  EXPECT_EQ(r.model_fingerprint, s.model_fingerprint);
  EXPECT_EQ(r.version, 77);
  EXPECT_EQ(r.sim_time, 1.5);
  ASSERT_EQ(r.grabs.size(), 1u);
  EXPECT_EQ(r.grabs[0].body, 3);
  EXPECT_EQ(r.grabs[0].point, g.point);
  EXPECT_EQ(r.grabs[0].velocity, g.velocity);
  EXPECT_EQ(r.ints, s.ints);
  EXPECT_EQ(r.values, s.values);
}

}  // namespace
}  // namespace haptree::bus
