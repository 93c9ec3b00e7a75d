// A keyed session over udpm:// inside a private network namespace (needs root; label netns): a keyed
// receiver takes only the session's messages, whoever else can send multicast; an unkeyed session
// that crosses hosts (ttl > 0) warns loudly.
#include <gtest/gtest.h>

#include <chrono>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "netns.hpp"

namespace haptree::bus {
namespace {

using haptree::testing::kNetnsMulticastSetup;
using haptree::testing::run_in_private_netns;
using namespace std::chrono_literals;

constexpr const char* kUrl = "udpm://239.255.76.67:7671?ttl=0";

TEST(KeyedUdpm, StrangersOtherKeysReplaysAndTamperingAreDroppedAndCounted) {
  const auto r = run_in_private_netns(kNetnsMulticastSetup, [](int fd) {
    try {
      const auto key = session_key_from_bytes("udpm session key: 32 bytes or more, really");
      Bus server(kUrl, key);          // the sim_server's side: receives USER_FORCE
      Bus workstation(kUrl, key);     // the coupler: same key
      Bus stranger(kUrl, nullptr);    // anyone on the LAN
      Bus other(kUrl, session_key_from_bytes("another session's key, 32 bytes long..."));
      const std::string ch = channel::user_force(0);
      std::vector<double> got;
      auto& sub = server.subscribe<lcmt_user_force>(ch, [&](const lcmt_user_force& m, const std::string&) {
        got.push_back(m.force[5]);
      });
      // Raw copies of what the workstation sends, to replay and tamper with.
      std::vector<std::vector<uint8_t>> wire;
      stranger.lcm().subscribeFunction(
          ch,
          +[](const lcm::ReceiveBuffer* rb, const std::string&, std::vector<std::vector<uint8_t>>* w) {
            const auto* d = static_cast<const uint8_t*>(rb->data);
            w->emplace_back(d, d + rb->data_size);
          },
          &wire);
      lcmt_user_force m{};
      stamp(m, 1);
      m.active = true;
      auto pump = [&] {
        const auto until = std::chrono::steady_clock::now() + 300ms;
        while (std::chrono::steady_clock::now() < until) {
          server.handle_timeout(10);
          stranger.handle_timeout(0);
          workstation.handle_timeout(0);
          other.handle_timeout(0);
        }
      };
      m.force[5] = 100;
      CHILD_CHECK(stranger.publish(ch, m) == 0, fd, "stranger publish failed");
      CHILD_CHECK(other.publish(ch, m) == 0, fd, "other-key publish failed");
      m.force[5] = 1.5;
      CHILD_CHECK(workstation.publish(ch, m) == 0, fd, "workstation publish failed");
      pump();
      CHILD_CHECK(got.size() == 1 && got[0] == 1.5, fd, "server accepted %zu messages (want 1: 1.5)", got.size());
      // wire holds the stranger's own, the other key's and the workstation's: replay the last, tampered too.
      CHILD_CHECK(wire.size() == 3, fd, "captured %zu messages", wire.size());
      const std::vector<uint8_t> good = wire.back();
      stranger.lcm().publish(ch, good.data(), static_cast<unsigned>(good.size()));   // replay
      std::vector<uint8_t> bad = good;
      bad[30] ^= 0x40;   // inside the force array
      stranger.lcm().publish(ch, bad.data(), static_cast<unsigned>(bad.size()));
      m.force[5] = 2.5;
      CHILD_CHECK(workstation.publish(ch, m) == 0, fd, "workstation publish failed");
      pump();
      CHILD_CHECK(got.size() == 2 && got[1] == 2.5, fd, "server accepted %zu messages (want 2)", got.size());
      const AuthStats& s = server.authenticator()->stats();
      CHILD_CHECK(s.no_trailer.load() == 1 && s.wrong_key.load() == 1 && s.replayed.load() == 1 &&
                      s.bad_mac.load() == 1 && s.accepted.load() == 2,
                  fd, "counts: no trailer %lld, wrong key %lld, replay %lld, bad MAC %lld, accepted %lld",
                  (long long)s.no_trailer.load(), (long long)s.wrong_key.load(), (long long)s.replayed.load(),
                  (long long)s.bad_mac.load(), (long long)s.accepted.load());
      CHILD_CHECK(sub.stats().auth_rejects.load() == 4, fd, "subscription counted %lld",
                  (long long)sub.stats().auth_rejects.load());
      dprintf(fd, "ok");
      return 0;
    } catch (const std::exception& e) {
      dprintf(fd, "exception: %s", e.what());
      return 1;
    }
  });
  ASSERT_EQ(r.exit_code, 0) << r.output;
}

TEST(KeyedUdpm, UnkeyedSessionAcrossHostsWarnsLoudlyAndKeyedOneShowsOnlyTheFingerprint) {
  const auto r = run_in_private_netns(kNetnsMulticastSetup, [](int fd) {
    const std::string secret = "the secret bytes of this key, 32+ long";
    ::testing::internal::CaptureStderr();
    {
      Bus open_bus("udpm://239.255.76.67:7672?ttl=1", nullptr);
      Bus keyed("udpm://239.255.76.67:7672?ttl=1", session_key_from_bytes(secret));
      Bus local("udpm://239.255.76.67:7672?ttl=0", nullptr);
    }
    const std::string err = ::testing::internal::GetCapturedStderr();
    const auto fp = session_key_from_bytes(secret)->fingerprint;
    CHILD_CHECK(err.find("WITHOUT a session key: anyone on the LAN can push forces into this session") !=
                    std::string::npos, fd, "no warning in: %s", err.c_str());
    CHILD_CHECK(err.find("session key " + fp) != std::string::npos, fd, "no fingerprint in: %s", err.c_str());
    CHILD_CHECK(err.find(secret) == std::string::npos, fd, "the key itself was logged");
    size_t warnings = 0;
    for (size_t p = err.find("WARNING"); p != std::string::npos; p = err.find("WARNING", p + 1)) ++warnings;
    CHILD_CHECK(warnings == 1, fd, "%zu warnings (want 1: ttl=0 and keyed sessions do not warn)", warnings);
    dprintf(fd, "ok");
    return 0;
  });
  ASSERT_EQ(r.exit_code, 0) << r.output;
}

}  // namespace
}  // namespace haptree::bus
