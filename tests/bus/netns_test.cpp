// Tests for haptree/bus/bus.hpp over udpm://, each inside a private network namespace (needs root).
#include <gtest/gtest.h>

#include <chrono>
#include <random>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "netns.hpp"

namespace haptree::bus {
namespace {

using haptree::testing::kNetnsMulticastSetup;
using haptree::testing::run_in_private_netns;
using namespace std::chrono_literals;

constexpr const char* kUrl = "udpm://239.255.76.67:7669?ttl=0";

TEST(Udpm, MissingMulticastRouteIsExplainedWithTheFix) {
  const auto r = run_in_private_netns("ip link set lo up", [](int fd) {
    try {
      Bus bus(kUrl);
      dprintf(fd, "Bus construction succeeded without a multicast route");
      return 1;
    } catch (const BusError& e) {
      dprintf(fd, "%s", e.what());
      return 0;
    }
  });
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("ip route add 224.0.0.0/4 dev lo"), std::string::npos) << r.output;
}

TEST(Udpm, RoundTripAndRejectedGarbageInsidePrivateNamespace) {
  const auto r = run_in_private_netns(kNetnsMulticastSetup, [](int fd) {
    try {
      Bus bus(kUrl);
      const std::string ch = channel::device_state(0);
      LatestValue<lcmt_device_state> box;
      auto& sub = bus.subscribe_latest<lcmt_device_state>(ch, box);
      std::mt19937 g(5);
      for (int k = 0; k < 20; ++k) {  // garbage first
        std::vector<uint8_t> b(1 + g() % 1000);
        for (auto& x : b) x = static_cast<uint8_t>(g());
        CHILD_CHECK(bus.publish_raw(ch, b.data(), static_cast<int>(b.size())) == 0, fd, "publish_raw failed");
      }
      lcmt_device_state m{};
      stamp(m, 7);
      m.seq = 77;
      m.position_m[0] = 0.125;
      CHILD_CHECK(bus.publish(ch, m) == 0, fd, "publish failed");
      const auto deadline = std::chrono::steady_clock::now() + 5s;
      lcmt_device_state got{};
      while (box.read(got) == 0 && std::chrono::steady_clock::now() < deadline) bus.handle_timeout(20);
      CHILD_CHECK(got.seq == 77 && got.position_m[0] == 0.125, fd, "message not received over udpm (seq %lld)",
                  static_cast<long long>(got.seq));
      CHILD_CHECK(sub.stats().rejected() == 20, fd, "rejected %lld of 20 garbage messages",
                  static_cast<long long>(sub.stats().rejected()));
      dprintf(fd, "ok");
      return 0;
    } catch (const std::exception& e) {
      dprintf(fd, "exception: %s", e.what());
      return 1;
    }
  });
  ASSERT_EQ(r.exit_code, 0) << r.output;
}

}  // namespace
}  // namespace haptree::bus
