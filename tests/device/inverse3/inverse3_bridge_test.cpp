// The real `device_bridge --device-kind inverse3` against the fake Inverse Service, over LCM tcpq:// through a
// hub on 127.0.0.1 (no network, no root). The test plays the coupler: it reads DEVICE_STATE and
// publishes FEEDBACK; the fake logs every force the bridge's device sent.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <fstream>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/lcmt_device_state.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "tests/device/inverse3/fake_inverse_service.hpp"
#include "tests/device/vendor_test_util.hpp"
#include "tests/integration/spawn.hpp"
#include "launcher/tcpq_hub.hpp"

namespace haptree {
namespace {

using testing::FakeFault;
using testing::FakeInverseOptions;
using testing::FakeInverseService;
using Clock = std::chrono::steady_clock;
using vendor_test::free_port;
using vendor_test::sleep_s;
using vendor_test::slurp;

// The fake reads the bridge's last bytes on its own thread: after the bridge has exited, wait (up to 2 s)
// until its WebSocket is closed there, which comes after the last command on the same socket.
void wait_closed(const FakeInverseService& svc) {
  const auto end = Clock::now() + std::chrono::seconds(2);
  while (Clock::now() < end && svc.open_connections() > 0) sleep_s(0.005);
}

// The coupler's side of one device: DEVICE_STATE in, FEEDBACK out at 1 kHz with a settable force.
struct FakeCoupler {
  explicit FakeCoupler(const std::string& url, const std::string& suffix)
      : bus(url), suffix(suffix), id(bus::new_instance_id()) {
    bus.subscribe<lcmt_device_state>(bus::channel::device_state(0, suffix), [this](const lcmt_device_state& m, const std::string&) {
      std::lock_guard<std::mutex> lock(mu);
      states.push_back(m);
    });
    handler = std::make_unique<bus::HandlerThread>(bus);
  }
  ~FakeCoupler() {
    stop_feedback();
    handler->stop();
  }
  void start_feedback() {
    publishing = true;
    pub = std::thread([this] {
      int64_t seq = 0;
      while (publishing) {
        lcmt_feedback m{};
        bus::stamp(m, id);
        m.seq = ++seq;
        m.device_id = 0;
        {
          std::lock_guard<std::mutex> lock(mu);
          for (int i = 0; i < 3; ++i) m.force_n[i] = force[i];
          m.echo_device_seq = states.empty() ? 0 : states.back().seq;
        }
        bus.publish(bus::channel::feedback(0, suffix), m);
        sleep_s(1e-3);
      }
    });
  }
  void stop_feedback() {
    publishing = false;
    if (pub.joinable()) pub.join();
  }
  void set_force(const Vec3& f) {
    std::lock_guard<std::mutex> lock(mu);
    for (int i = 0; i < 3; ++i) force[i] = f[i];
  }
  size_t count() {
    std::lock_guard<std::mutex> lock(mu);
    return states.size();
  }
  lcmt_device_state last() {
    std::lock_guard<std::mutex> lock(mu);
    return states.empty() ? lcmt_device_state{} : states.back();
  }
  std::vector<lcmt_device_state> all() {
    std::lock_guard<std::mutex> lock(mu);
    return states;
  }
  bool wait_states(size_t n, double seconds) {
    const auto end = Clock::now() + std::chrono::duration<double>(seconds);
    while (Clock::now() < end && count() < n) sleep_s(0.01);
    return count() >= n;
  }

  bus::Bus bus;
  std::string suffix;
  int64_t id;
  std::mutex mu;
  std::vector<lcmt_device_state> states;
  double force[3] = {0, 0, 0};
  std::atomic<bool> publishing{false};
  std::thread pub;
  std::unique_ptr<bus::HandlerThread> handler;
};

struct Session {
  explicit Session(const FakeInverseOptions& o, std::vector<std::string> extra = {})
      : svc(o), hub(0), suffix("_I3_" + std::to_string(::getpid()) + "_" + std::to_string(counter()++)),
        log(::testing::TempDir() + "inverse3_bridge" + suffix + ".log"), coupler(hub.url(), suffix) {
    // timeout_s 0.5: a loaded test machine never looks like a lost link
    std::vector<std::string> args = {HAPTREE_DEVICE_BRIDGE, "--device-kind", "inverse3", "--device-option", "url=" + svc.url(),
                                     "--device-option", "timeout_s=0.5",
                                     "--lcm-url", hub.url(), "--channel-suffix", suffix, "--max-force-n", "2"};
    args.insert(args.end(), extra.begin(), extra.end());
    pid = testing::spawn_logged(args, log);
  }
  ~Session() {
    if (pid > 0 && ::kill(pid, 0) == 0) testing::stop_and_reap(pid);
  }
  static int& counter() {
    static int n = 0;
    return n;
  }
  FakeInverseService svc;
  launcher::TcpqHub hub;
  std::string suffix, log;
  FakeCoupler coupler;
  pid_t pid = -1;
};

Vec3 pos(const lcmt_device_state& m) { return Vec3(m.position_m[0], m.position_m[1], m.position_m[2]); }

double max_norm(const std::vector<testing::ForceRecord>& log) {
  double m = 0;
  for (const auto& r : log) m = std::max(m, r.force_n.norm());
  return m;
}

TEST(Inverse3Bridge, PosesInMetresForcesInNewtonsWithinTheMaxZeroLast) {
  FakeInverseOptions o;
  o.rest_m = Vec3(0.03, -0.12, 0.15);
  o.buttons = {{0.0, 0.5, 1}};
  Session s(o);
  ASSERT_GT(s.pid, 0);
  ASSERT_TRUE(s.coupler.wait_states(200, 5.0)) << slurp(s.log);
  // Before any FEEDBACK: the pose of the device at rest, in view axes and metres; the grab button of
  // the grip's schedule; and only zero forces sent.
  lcmt_device_state m = s.coupler.last();
  EXPECT_EQ(pos(m), Vec3(0.03, 0.15, 0.12));
  sleep_s(0.3);
  const auto before = s.svc.forces();
  ASSERT_GT(before.size(), 100u) << "the service gets a command every tick";
  EXPECT_EQ(max_norm(before), 0.0) << "no force before the first FEEDBACK";
  bool grab_seen = false;
  for (const auto& st : s.coupler.all()) grab_seen |= (st.buttons & 1) != 0;
  EXPECT_TRUE(grab_seen);

  // 1 N up in the view: device +z; the fake's 200 N/m spring settles 5 mm up, seen in DEVICE_STATE.
  // (The checks take the extreme over a window: a test thread stalled past the bridge's 10 ms FEEDBACK
  // watchdog on a loaded machine ramps the force down for a moment, by design.)
  s.coupler.set_force(Vec3(0, 1, 0));
  s.coupler.start_feedback();
  sleep_s(1.0);
  auto log = s.svc.forces();
  const size_t n_before = before.size();
  double fz_max = 0, off_axis = 0;
  for (size_t i = n_before; i < log.size(); ++i) {
    fz_max = std::max(fz_max, log[i].force_n.z());
    off_axis = std::max({off_axis, std::abs(log[i].force_n.x()), std::abs(log[i].force_n.y())});
  }
  EXPECT_EQ(fz_max, 1.0) << "1 N up in the view is 1 N along the Inverse3's +z";
  EXPECT_EQ(off_axis, 0.0);
  double y_max = 0;
  const auto states = s.coupler.all();
  for (size_t i = states.size() > 300 ? states.size() - 300 : 0; i < states.size(); ++i) {
    y_max = std::max(y_max, states[i].position_m[1]);
    EXPECT_NEAR(states[i].position_m[0], 0.03, 1e-6);
    EXPECT_NEAR(states[i].position_m[2], 0.12, 1e-6);
  }
  EXPECT_NEAR(y_max, 0.15 + 1.0 / 200, 3e-4) << "the spring's equilibrium, 5 mm up";
  EXPECT_EQ(s.coupler.last().buttons & 1, 0) << "the schedule released the grab button at 0.5 s";

  // 5 N towards the user: clamped to the bridge's --max-force-n 2, along device -y.
  s.coupler.set_force(Vec3(0, 0, 5));
  sleep_s(0.5);
  const size_t n_up = log.size();
  log = s.svc.forces();
  double fy_min = 0;
  for (size_t i = n_up; i < log.size(); ++i) fy_min = std::min(fy_min, log[i].force_n.y());
  EXPECT_NEAR(fy_min, -2.0, 1e-9) << "towards the user is the Inverse3's -y; clamped at 2 N";
  EXPECT_LE(max_norm(log), 2.0 + 1e-9);

  // SIGTERM: the bridge ramps down and closes; the service's last command is a zero force.
  int rc = -1;
  ::kill(s.pid, SIGTERM);
  ASSERT_TRUE((rc = vendor_test::reap(s.pid, 5.0)) != -1) << slurp(s.log);
  s.pid = -1;
  EXPECT_EQ(rc, 0) << slurp(s.log);
  wait_closed(s.svc);
  log = s.svc.forces();
  EXPECT_EQ(log.back().force_n, Vec3::Zero());
  EXPECT_TRUE(log.back().applied);
  sleep_s(0.1);
  EXPECT_EQ(s.svc.open_connections(), 0) << "the bridge closed its WebSocket";
}

// A link that fails while a force is rendered: the bridge's fail-safe ends it (exit 3) naming the cause;
// where the socket is still open the last command the service gets is a zero force, and nothing after.
TEST(Inverse3Bridge, CommLossEndsWithZeroForceAndExit3) {
  const std::pair<FakeFault, const char*> cases[] = {
      {FakeFault::kStopReplying, "device read failed: inverse3: no "},   // no reply / no state: whichever is first
      {FakeFault::kMalformed, "device read failed: inverse3: no "},
      {FakeFault::kClose, "closed the connection"}};
  for (const auto& c : cases) {
    FakeInverseOptions o;
    o.fault = c.first;
    o.fault_after_s = 1.0;
    Session s(o);
    ASSERT_GT(s.pid, 0);
    s.coupler.set_force(Vec3(1, 0, 0));
    s.coupler.start_feedback();
    int rc = -1;
    ASSERT_TRUE((rc = vendor_test::reap(s.pid, 8.0)) != -1) << c.second << "\n" << slurp(s.log);
    s.pid = -1;
    EXPECT_EQ(rc, 3) << slurp(s.log);
    const std::string out = slurp(s.log);
    EXPECT_NE(out.find(c.second), std::string::npos) << out;
    wait_closed(s.svc);
    const auto log = s.svc.forces();
    ASSERT_GT(log.size(), 50u) << out;
    double f_before = 0;
    for (const auto& r : log)
      if (r.t_s < 0.95) f_before = std::max(f_before, r.force_n.norm());
    EXPECT_NEAR(f_before, 1.0, 1e-9) << "a force was rendered before the fault";
    if (c.first != FakeFault::kClose) {
      EXPECT_EQ(log.back().force_n, Vec3::Zero()) << c.second;
      EXPECT_TRUE(log.back().applied);
    }
    sleep_s(0.2);
    EXPECT_EQ(s.svc.forces().size(), log.size()) << "nothing sent after the loss";
  }
}

// --probe: model, serial, limits (none reported), position and buttons, force output off throughout.
TEST(Inverse3Bridge, Probe) {
  FakeInverseOptions o;
  o.rest_m = Vec3(0.03, -0.12, 0.15);
  o.buttons = {{0.0, 10.0, 2}};
  FakeInverseService svc(o);
  const std::string log = ::testing::TempDir() + "inverse3_bridge_probe.log";
  const pid_t p = testing::spawn_logged(
      {HAPTREE_DEVICE_BRIDGE, "--device-kind", "inverse3", "--probe", "--device-option", "url=" + svc.url()}, log);
  ASSERT_GT(p, 0);
  int rc = -1;
  ASSERT_TRUE((rc = vendor_test::reap(p, 10.0)) != -1);
  const std::string out = slurp(log);
  EXPECT_EQ(rc, 0) << out;
  wait_closed(svc);
  for (const char* line : {"kind: inverse3", "model: Haply Inverse3 (version 7.4, right-handed)", "serial: 049D",
                           "max force: not reported", "axes: x,z,-y", "position: 0.030000 0.150000 0.120000 m",
                           "buttons: 2 (grab up, clutch down)"})
    EXPECT_NE(out.find(line), std::string::npos) << line << "\n" << out;
  const auto forces = svc.forces();
  ASSERT_FALSE(forces.empty());
  EXPECT_EQ(max_norm(forces), 0.0);
}

TEST(Inverse3Bridge, ServiceNotRunningOneLineExit1) {
  const std::string url = "ws://127.0.0.1:" + std::to_string(free_port());
  const std::string log = ::testing::TempDir() + "inverse3_bridge_no_service.log";
  const pid_t p = testing::spawn_logged({HAPTREE_DEVICE_BRIDGE, "--device-kind", "inverse3", "--device-option", "url=" + url,
                                         "--lcm-url", "memq://"},
                                        log);
  ASSERT_GT(p, 0);
  int rc = -1;
  ASSERT_TRUE((rc = vendor_test::reap(p, 10.0)) != -1);
  EXPECT_EQ(rc, 1);
  const std::string out = slurp(log);
  int lines = 0, about = 0;
  std::istringstream in(out);
  for (std::string line; std::getline(in, line);) {
    ++lines;
    if (line.find("cannot connect to the Inverse Service at " + url) != std::string::npos) ++about;
  }
  EXPECT_EQ(about, 1) << out;
  EXPECT_EQ(lines, 1) << out;
}

TEST(Inverse3Bridge, OlderServiceWithForceKeyValues) {
  FakeInverseOptions o;
  o.old_dialect = true;
  Session s(o, {"--device-option", "force_key=values"});
  ASSERT_GT(s.pid, 0);
  ASSERT_TRUE(s.coupler.wait_states(100, 5.0)) << slurp(s.log);
  s.coupler.set_force(Vec3(0.5, 0, 0));
  s.coupler.start_feedback();
  sleep_s(0.5);
  const auto log = s.svc.forces();
  double fx_max = 0;
  bool all_applied = true;
  for (const auto& r : log) {
    fx_max = std::max(fx_max, r.force_n.x());
    all_applied &= r.applied;
  }
  EXPECT_TRUE(all_applied) << "every command in the field an older service reads";
  EXPECT_EQ(fx_max, 0.5);
}

}  // namespace
}  // namespace haptree
