// Authenticated sessions (haptree/bus/auth.*): keys, seal/open, and a keyed Bus (memq://), shm channel
// and LCM log that reject strangers, other keys, replays and tampered bytes. udpm: auth_netns_test.cpp.
#include <gtest/gtest.h>
#include <sodium.h>
#include <sys/stat.h>

#include <CLI/CLI.hpp>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <lcm/lcm-cpp.hpp>
#include <vector>

#include "haptree/bus/auth.hpp"
#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/cli.hpp"
#include "haptree/bus/shm_channel.hpp"

namespace haptree::bus {
namespace {

namespace fs = std::filesystem;

const std::string kKeyA = "0123456789abcdef0123456789abcdef-session-A";
const std::string kKeyB = "0123456789abcdef0123456789abcdef-session-B";

template <class T>
std::vector<uint8_t> encode(const T& m) {
  std::vector<uint8_t> b(static_cast<size_t>(m.getEncodedSize()));
  m.encode(b.data(), 0, static_cast<int>(b.size()));
  return b;
}
// What a peer with key `a` puts on the wire for m on channel.
template <class T>
std::vector<uint8_t> sealed(Authenticator& a, const std::string& channel, const T& m) {
  std::vector<uint8_t> b = encode(m);
  const size_t n = b.size();
  b.resize(n + kAuthTrailerBytes);
  EXPECT_EQ(a.seal(channel, b.data(), n), b.size());
  return b;
}

lcmt_user_force user_force(int64_t seq, double fz) {
  lcmt_user_force m{};
  stamp(m, 1);
  m.seq = seq;
  m.grab_body = 3;
  m.force[5] = fz;
  m.active = true;
  return m;
}

fs::path write_file(const std::string& name, const std::string& bytes, int mode = 0600) {
  const fs::path p = fs::temp_directory_path() / ("haptree_auth_" + std::to_string(::getpid()) + name);
  std::ofstream(p, std::ios::binary) << bytes;
  ::chmod(p.c_str(), mode);
  return p;
}

TEST(SessionKey, FileGivesAStableFingerprintThatIsNotTheKey) {
  const fs::path p = write_file("a.key", kKeyA + "\n");
  const auto k = load_session_key(p.string());
  EXPECT_EQ(k->fingerprint.size(), 16u);
  EXPECT_EQ(k->fingerprint, session_key_from_bytes(kKeyA)->fingerprint);   // trailing newline ignored
  EXPECT_NE(k->fingerprint, session_key_from_bytes(kKeyB)->fingerprint);
  EXPECT_EQ(kKeyA.find(k->fingerprint), std::string::npos);
  EXPECT_NE(k->key_id, session_key_from_bytes(kKeyB)->key_id);
  fs::remove(p);
  EXPECT_THROW(session_key_from_bytes("too short"), std::runtime_error);
  try {
    load_session_key("/nonexistent/haptree.key");
    FAIL();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("/nonexistent/haptree.key"), std::string::npos) << e.what();
  }
}

TEST(SessionKey, CommandLineOptionAndEnvironmentVariableSetTheProcessKey) {
  const fs::path p = write_file("cli.key", kKeyA);
  {
    CLI::App app;
    BusOptions o;
    add_bus_options(app, o);
    std::vector<std::string> args{"--session-key-file", p.string()};
    std::reverse(args.begin(), args.end());
    app.parse(args);
    EXPECT_EQ(process_session_key_file(), p.string());
    EXPECT_EQ(process_session_key()->fingerprint, session_key_from_bytes(kKeyA)->fingerprint);
  }
  {
    ::setenv("HAPTREE_SESSION_KEY_FILE", "/from/env.key", 1);
    CLI::App app;
    BusOptions o;
    add_bus_options(app, o);
    app.parse(std::vector<std::string>{});
    EXPECT_EQ(o.session_key_file, "/from/env.key");
    EXPECT_EQ(process_session_key_file(), "/from/env.key");
    ::unsetenv("HAPTREE_SESSION_KEY_FILE");
  }
  set_process_session_key_file("");   // later tests: unkeyed by default
  EXPECT_EQ(process_session_key(), nullptr);
  fs::remove(p);
}

TEST(Authenticator, TrailerMacIsLibsodiumCryptoAuthOverChannelNulBytesAndHeader) {
  // Oracle: the one-shot crypto_auth (HMAC-SHA512-256) of the documented byte string, with the key
  // derived as documented (BLAKE2b-256 of the file bytes under "haptree session key v1").
  ASSERT_GE(sodium_init(), 0);
  const auto k = session_key_from_bytes(kKeyA);
  uint8_t key[32];
  static const char ctx[] = "haptree session key v1";
  crypto_generichash(key, 32, reinterpret_cast<const unsigned char*>(kKeyA.data()), kKeyA.size(),
                     reinterpret_cast<const unsigned char*>(ctx), sizeof ctx - 1);
  ASSERT_EQ(std::memcmp(key, k->key.data(), 32), 0);
  Authenticator a(k);
  const std::string ch = channel::coeffs(0);
  for (int round = 0; round < 3; ++round) {   // the copied init state is reused correctly
    const auto b = sealed(a, ch, user_force(round, 0.25));
    std::vector<uint8_t> covered(ch.begin(), ch.end());
    covered.push_back(0);
    covered.insert(covered.end(), b.begin(), b.end() - 32);
    uint8_t expect[32];
    crypto_auth(expect, covered.data(), covered.size(), key);
    EXPECT_EQ(std::memcmp(expect, b.data() + b.size() - 32, 32), 0) << "round " << round;
    EXPECT_EQ(b[b.size() - 52], 'H');
    EXPECT_EQ(b[b.size() - 49], '1');
  }
}

TEST(Authenticator, DropsAndCountsStrangersOtherKeysReplaysTamperingAndChannelMoves) {
  Authenticator rx(session_key_from_bytes(kKeyA)), peer(session_key_from_bytes(kKeyA)),
      stranger(session_key_from_bytes(kKeyB));
  const std::string ch = channel::user_force(0);
  const auto m1 = sealed(peer, ch, user_force(1, 2.0));
  const auto m2 = sealed(peer, ch, user_force(2, 2.0));
  size_t n = 0;
  EXPECT_EQ(rx.open(ch, m1.data(), m1.size(), &n), AuthVerdict::kOk);
  EXPECT_EQ(n, m1.size() - kAuthTrailerBytes);
  EXPECT_EQ(rx.open(ch, m1.data(), m1.size(), &n), AuthVerdict::kReplay);   // the same bytes again
  EXPECT_EQ(rx.open(ch, m2.data(), m2.size(), &n), AuthVerdict::kOk);
  EXPECT_EQ(rx.open(ch, m1.data(), m1.size(), &n), AuthVerdict::kReplay);   // older
  const auto plain = encode(user_force(3, 2.0));
  EXPECT_EQ(rx.open(ch, plain.data(), plain.size(), &n), AuthVerdict::kNoTrailer);
  const auto other = sealed(stranger, ch, user_force(4, 50.0));
  EXPECT_EQ(rx.open(ch, other.data(), other.size(), &n), AuthVerdict::kWrongKey);
  // Every single byte of message and trailer matters (flip one bit in each position in turn).
  const auto m3 = sealed(peer, ch, user_force(5, 2.0));
  int caught = 0;
  for (size_t i = 0; i < m3.size(); ++i) {
    auto t = m3;
    t[i] ^= 0x10;
    const AuthVerdict v = rx.open(ch, t.data(), t.size(), &n);
    caught += v != AuthVerdict::kOk;
  }
  EXPECT_EQ(caught, static_cast<int>(m3.size()));
  EXPECT_EQ(rx.open(channel::user_force(1), m3.data(), m3.size(), &n), AuthVerdict::kBadMac);  // moved
  EXPECT_EQ(rx.open(ch, m3.data(), m3.size(), &n), AuthVerdict::kOk);   // the untouched original
  const AuthStats& s = rx.stats();
  EXPECT_EQ(s.accepted.load(), 3);
  EXPECT_EQ(s.replayed.load(), 2);
  // Flips in the magic read as "no trailer" (4 bytes), in the key id as "another key" (4 bytes); every
  // other flip, and the channel move, fails the MAC.
  EXPECT_EQ(s.no_trailer.load(), 1 + 4);
  EXPECT_EQ(s.wrong_key.load(), 1 + 4);
  EXPECT_EQ(s.bad_mac.load(), static_cast<int64_t>(m3.size()) - 8 + 1);
}

// A keyed Bus on memq:// — the stranger's bytes are published on its LCM directly (no seal).
TEST(KeyedBus, RejectsAStrangersUserForceAndSnapshotAcceptsThePeers) {
  Bus bus("memq://", session_key_from_bytes(kKeyA));
  ASSERT_NE(bus.authenticator(), nullptr);
  Authenticator peer(session_key_from_bytes(kKeyA)), other_key(session_key_from_bytes(kKeyB));
  const std::string ch_uf = channel::user_force(0), ch_snap = channel::coeffs(0);
  std::vector<double> got;
  auto& sub_uf = bus.subscribe<lcmt_user_force>(ch_uf, [&](const lcmt_user_force& m, const std::string&) {
    got.push_back(m.force[5]);
  });
  int snaps = 0;
  auto& sub_snap = bus.subscribe<lcmt_coupling_snapshot>(ch_snap,
                                                         [&](const lcmt_coupling_snapshot&, const std::string&) { ++snaps; });
  auto inject = [&](const std::string& ch, const std::vector<uint8_t>& b) {
    ASSERT_EQ(bus.lcm().publish(ch, b.data(), static_cast<unsigned>(b.size())), 0);
    while (bus.handle_timeout(0) > 0) {
    }
  };
  lcmt_coupling_snapshot snap{};
  stamp(snap, 1);
  snap.version = 9;
  inject(ch_uf, encode(user_force(1, 100.0)));          // unkeyed stranger
  inject(ch_snap, encode(snap));
  inject(ch_uf, sealed(other_key, ch_uf, user_force(2, 100.0)));   // another session's key
  inject(ch_snap, sealed(other_key, ch_snap, snap));
  auto good = sealed(peer, ch_uf, user_force(3, 1.5));
  inject(ch_uf, good);
  inject(ch_uf, good);                                  // replay
  auto bad = sealed(peer, ch_uf, user_force(4, 1.5));
  bad[40] ^= 1;                                         // tampered force bytes
  inject(ch_uf, bad);
  inject(ch_snap, sealed(peer, ch_snap, snap));
  ASSERT_EQ(got, std::vector<double>{1.5});
  EXPECT_EQ(snaps, 1);
  EXPECT_EQ(sub_uf.stats().auth_rejects.load(), 4);
  EXPECT_EQ(sub_snap.stats().auth_rejects.load(), 2);
  EXPECT_EQ(sub_uf.stats().rejected(), 4);
  const AuthStats& s = bus.authenticator()->stats();
  EXPECT_EQ(s.no_trailer.load(), 2);
  EXPECT_EQ(s.wrong_key.load(), 2);
  EXPECT_EQ(s.replayed.load(), 1);
  EXPECT_EQ(s.bad_mac.load(), 1);
  // Its own publications go through (sealed on publish, verified on receipt).
  ASSERT_EQ(bus.publish(ch_uf, user_force(5, 2.5)), 0);
  while (bus.handle_timeout(0) > 0) {
  }
  EXPECT_EQ(got.back(), 2.5);
  EXPECT_EQ(bus.authenticator()->stats().sealed.load(), 1);
}

TEST(KeyedBus, UnkeyedReceiverSeesTheTrailerAsMalformed) {
  // Mixed sessions fail closed both ways: a keyed sender's messages do not decode on an unkeyed bus.
  Bus bus("memq://", nullptr);
  Authenticator peer(session_key_from_bytes(kKeyA));
  int n = 0;
  auto& sub = bus.subscribe<lcmt_user_force>("UF", [&](const lcmt_user_force&, const std::string&) { ++n; });
  const auto b = sealed(peer, "UF", user_force(1, 1.0));
  bus.lcm().publish("UF", b.data(), static_cast<unsigned>(b.size()));
  bus.handle_timeout(0);
  EXPECT_EQ(n, 0);
  EXPECT_EQ(sub.stats().decode_errors.load(), 1);
}

TEST(KeyedShm, ReaderRejectsUnkeyedAndOtherKeyWritersAndReplays) {
  const std::string ch = "HAPTREE_TEST_AUTH_SHM_" + std::to_string(::getpid());
  ShmReader reader(ch);
  reader.set_session_key(session_key_from_bytes(kKeyA));
  ShmWriter writer(ch);
  lcmt_feedback fb{};
  stamp(fb, 1);
  fb.force_n[0] = 1.25;
  lcmt_feedback got{};
  writer.set_session_key(nullptr);   // stranger: unkeyed
  ASSERT_TRUE(writer.write_msg(fb));
  EXPECT_NE(reader.read_msg(got), ShmRead::kNew);
  writer.set_session_key(session_key_from_bytes(kKeyB));   // another key
  ASSERT_TRUE(writer.write_msg(fb));
  EXPECT_NE(reader.read_msg(got), ShmRead::kNew);
  writer.set_session_key(session_key_from_bytes(kKeyA));   // the session's key
  ASSERT_TRUE(writer.write_msg(fb));
  ASSERT_EQ(reader.read_msg(got), ShmRead::kNew);
  EXPECT_EQ(got.force_n[0], 1.25);
  EXPECT_EQ(reader.rejected(), 2);
  // Replay: bytes of an earlier keyed message written again (raw) are refused.
  std::vector<uint8_t> bytes = encode(fb);
  const size_t n = bytes.size();
  Authenticator old_peer(session_key_from_bytes(kKeyA));
  bytes.resize(n + kAuthTrailerBytes);
  old_peer.seal(ch, bytes.data(), n);
  ShmWriter& raw = writer;   // one live writer per channel (shm_channel.hpp): the same writer, unkeyed
  raw.set_session_key(nullptr);
  ASSERT_TRUE(raw.write(bytes.data(), bytes.size()));
  ASSERT_EQ(reader.read_msg(got), ShmRead::kNew);
  ASSERT_TRUE(raw.write(bytes.data(), bytes.size()));
  EXPECT_NE(reader.read_msg(got), ShmRead::kNew);
  EXPECT_EQ(reader.rejected(), 3);
  EXPECT_EQ(reader.authenticator()->stats().replayed.load(), 1);
  ShmChannel::remove(ch);
}

TEST(KeyedLog, RecordedSessionReplaysWithTheKeyAndNotWithout) {
  const fs::path log = fs::temp_directory_path() / ("haptree_auth_" + std::to_string(::getpid()) + ".lcm");
  const auto key = session_key_from_bytes(kKeyA);
  {
    Bus rec("file://" + log.string() + "?mode=w", key);
    for (int i = 1; i <= 5; ++i) ASSERT_EQ(rec.publish(channel::user_force(0), user_force(i, 0.5 * i)), 0);
  }
  auto replay = [&](std::shared_ptr<const SessionKey> k) {
    Bus play("file://" + log.string() + "?mode=r&speed=0", k);
    std::vector<int64_t> seqs;
    play.subscribe<lcmt_user_force>(channel::user_force(0),
                                    [&](const lcmt_user_force& m, const std::string&) { seqs.push_back(m.seq); });
    while (play.handle_timeout(100) > 0) {
    }
    return seqs;
  };
  EXPECT_EQ(replay(key), (std::vector<int64_t>{1, 2, 3, 4, 5}));
  EXPECT_TRUE(replay(session_key_from_bytes(kKeyB)).empty());
  // A reader of the log file itself (replay_coupling style) verifies each event with verify().
  lcm::LogFile f(log.string(), "r");
  Authenticator a(key);
  int ok = 0;
  for (const lcm::LogEvent* ev = f.readNextEvent(); ev; ev = f.readNextEvent()) {
    size_t n = 0;
    ok += a.verify(ev->channel, ev->data, static_cast<size_t>(ev->datalen), &n) == AuthVerdict::kOk;
  }
  EXPECT_EQ(ok, 5);
  fs::remove(log);
}

}  // namespace
}  // namespace haptree::bus
