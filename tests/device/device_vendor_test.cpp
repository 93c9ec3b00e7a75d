// The real device_bridge executable against fake vendor libraries built in the test suite
// (tests/device/fakes: libHD.so and libdhd.so.3 exporting the vendors' C symbols, a point mass on a
// spring, buttons on a schedule, injectable faults, a log of every force written). This test plays the
// coupler over LCM tcpq:// (a hub on 127.0.0.1): it reads DEVICE_STATE and publishes FEEDBACK.
// Checked: poses in metres with the right axes, forces in newtons within the device's maximum, grab and
// clutch, no force before the first FEEDBACK, zero force written last (then force off, then closed) on
// every fault, a clear line and exit 1 when the library, a symbol or the device is missing, --probe.
#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <memory>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/lcmt_device_state.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "haptree/spatial.hpp"
#include "tests/device/vendor_test_util.hpp"
#include "launcher/tcpq_hub.hpp"

namespace haptree {
namespace {

using namespace vendor_test;

// The coupler's side of the link: DEVICE_STATE in, FEEDBACK out at 1 kHz while a force is set.
class FakeCoupler {
 public:
  FakeCoupler(const std::string& url, const std::string& suffix)
      : bus_(url), handler_(bus_), ch_fb_(bus::channel::feedback(0, suffix)), id_(bus::new_instance_id()) {
    bus_.subscribe<lcmt_device_state>(bus::channel::device_state(0, suffix),
                                      [this](const lcmt_device_state& m, const std::string&) {
                                        std::lock_guard<std::mutex> l(mu_);
                                        states_.push_back(m);
                                        last_seq_ = m.seq;
                                      });
    sender_ = std::thread([this] {
      int64_t seq = 0;
      while (!quit_) {
        if (on_) {
          lcmt_feedback fb{};
          fb.schema_version = lcmt_feedback::SCHEMA_VERSION;
          fb.utime = bus::now_utime();
          fb.instance_id = id_;
          fb.seq = ++seq;
          fb.device_id = 0;
          {
            std::lock_guard<std::mutex> l(mu_);
            fb.echo_device_seq = last_seq_;
            for (int i = 0; i < 3; ++i) fb.force_n[i] = f_[i], fb.torque_nm[i] = tau_[i];
          }
          if (first_sent_ < 0) first_sent_ = unix_now();
          bus_.publish(ch_fb_, fb);
        }
        sleep_s(1e-3);
      }
    });
  }
  ~FakeCoupler() {
    quit_ = true;
    sender_.join();
    handler_.stop();
  }
  // Starts (or changes) the FEEDBACK force; returns the unix time of the change.
  double feedback(const Vec3& f, const Vec3& tau = Vec3::Zero()) {
    {
      std::lock_guard<std::mutex> l(mu_);
      f_ = f;
      tau_ = tau;
    }
    const double t = unix_now();
    on_ = true;
    return t;
  }
  void silence() { on_ = false; }
  double first_sent() const { return first_sent_; }
  std::vector<lcmt_device_state> states() {
    std::lock_guard<std::mutex> l(mu_);
    return states_;
  }
  bool wait_states(size_t n, double timeout_s = 5) {
    for (double t = 0; t < timeout_s; t += 0.01) {
      if (states().size() >= n) return true;
      sleep_s(0.01);
    }
    return false;
  }

 private:
  bus::Bus bus_;
  bus::HandlerThread handler_;
  std::string ch_fb_;
  int64_t id_;
  std::mutex mu_;
  std::vector<lcmt_device_state> states_;
  int64_t last_seq_ = 0;
  Vec3 f_ = Vec3::Zero(), tau_ = Vec3::Zero();
  std::atomic<bool> on_{false}, quit_{false};
  std::atomic<double> first_sent_{-1};
  std::thread sender_;
};

Vec3 pos(const lcmt_device_state& s) { return Vec3(s.position_m[0], s.position_m[1], s.position_m[2]); }
Quat quat(const lcmt_device_state& s) {
  return Quat(s.orientation[0], s.orientation[1], s.orientation[2], s.orientation[3]);
}

// One device_bridge run against a fake: hub, fake coupler, bridge process, files.
struct Session {
  launcher::TcpqHub hub{0};
  std::string suffix, dir, bridge_log, force_log;
  std::unique_ptr<FakeCoupler> coupler;
  pid_t pid = -1;
  Session(const std::string& name, const std::vector<std::string>& bridge_args, Env env) {
    suffix = "_V" + std::to_string(::getpid()) + name;
    dir = ::testing::TempDir();
    bridge_log = dir + "vendor_" + name + "_bridge.log";
    force_log = dir + "vendor_" + name + "_forces.log";
    std::remove(force_log.c_str());
    env["FAKE_HAPTIC_LOG"] = force_log;
    coupler = std::make_unique<FakeCoupler>(hub.url(), suffix);
    std::vector<std::string> args = {HAPTREE_DEVICE_BRIDGE, "--lcm-url", hub.url(), "--channel-suffix", suffix};
    args.insert(args.end(), bridge_args.begin(), bridge_args.end());
    pid = spawn(args, env, bridge_log);
  }
  int stop(int sig = SIGTERM) {
    ::kill(pid, sig);
    const int rc = reap(pid);
    EXPECT_NE(::kill(pid, 0), 0) << "device_bridge still running";
    return rc;
  }
  std::string log() const { return slurp(bridge_log); }
  std::vector<Event> events() const { return read_log_until_closed(force_log); }
};

std::vector<std::string> hd_args(std::vector<std::string> extra = {}) {
  std::vector<std::string> a = {"--device-kind", "openhaptics", "--device-option", std::string("lib=") + FAKE_HD_LIB};
  a.insert(a.end(), extra.begin(), extra.end());
  return a;
}
std::vector<std::string> dhd_args(std::vector<std::string> extra = {}) {
  std::vector<std::string> a = {"--device-kind", "forcedimension", "--device-option", std::string("lib=") + FAKE_DHD_LIB};
  a.insert(a.end(), extra.begin(), extra.end());
  return a;
}

// The largest force written in (t0, t1): with a steady FEEDBACK, exactly the commanded force. (These runs
// set the device's FEEDBACK watchdog to 0.5 s: a busy host delaying one FEEDBACK past the default 10 ms
// would ramp the force down and back up. Never above the command, so the largest value is the command.)
const Event* max_force_between(const std::vector<Event>& ev, double t0, double t1) {
  const Event* f = nullptr;
  for (const auto& e : ev)
    if (e.is_force() && e.t > t0 && e.t < t1 && (!f || e.norm() > f->norm())) f = &e;
  return f;
}

// The mass (k = 200 N/m) pushed by F from `rest` moved along F by about |F|/k: newtons, not mN, along the
// right axes. Loose in magnitude only because a busy host may have ramped the force for a moment.
void expect_pushed(const Vec3& x, const Vec3& rest, const Vec3& F) {
  const Vec3 d = x - rest;
  EXPECT_GT(d.normalized().dot(F.normalized()), 0.99) << d.transpose();
  EXPECT_GT(d.norm(), 0.3 * F.norm() / 200.0) << d.transpose();
  EXPECT_LT(d.norm(), 1.05 * F.norm() / 200.0) << d.transpose();
}

// ---------------------------------------------------------------------------------------------------

TEST(DeviceVendor, OpenHapticsPosesInMetresForcesInNewtonsWithinTheDeviceMaximum) {
  // Rest point 10, 20, -30 mm (HD frame = haptree's). --max-force-n 50: the device's 3.3 N must win.
  Session s("hd_basic", hd_args({"--max-force-n", "50", "--feedback-timeout-s", "0.5"}), {{"FAKE_HAPTIC_PATH", "0:10,20,-30"}});
  ASSERT_GT(s.pid, 0);
  ASSERT_TRUE(s.coupler->wait_states(200)) << s.log();
  sleep_s(0.3);   // no FEEDBACK yet: no force may be written
  const lcmt_device_state rest = s.coupler->states().back();
  EXPECT_NEAR(rest.position_m[0], 0.010, 1e-9);
  EXPECT_NEAR(rest.position_m[1], 0.020, 1e-9);
  EXPECT_NEAR(rest.position_m[2], -0.030, 1e-9);
  // The fake's stylus is turned a quarter turn about the vertical (y).
  EXPECT_NEAR(quat(rest).angularDistance(Quat(Eigen::AngleAxisd(M_PI / 2, Vec3::UnitY()))), 0.0, 1e-9);
  const Vec3 F(1.0, -2.0, 0.5);
  const double t_fb = s.coupler->feedback(F);
  sleep_s(0.6);
  expect_pushed(pos(s.coupler->states().back()), Vec3(0.010, 0.020, -0.030), F);
  const double t_big = s.coupler->feedback(Vec3(100, 0, 0));
  sleep_s(0.3);
  EXPECT_EQ(s.stop(), 0) << s.log();
  const auto ev = s.events();
  expect_no_force_before_feedback(ev, t_fb);
  const Event* steady = max_force_between(ev, t_fb, t_big);
  ASSERT_NE(steady, nullptr);
  EXPECT_NEAR(steady->v[0], 1.0, 1e-12);
  EXPECT_NEAR(steady->v[1], -2.0, 1e-12);
  EXPECT_NEAR(steady->v[2], 0.5, 1e-12);
  double fmax = 0;
  for (const auto& e : ev) fmax = std::max(fmax, e.norm());
  EXPECT_LE(fmax, 3.3 + 1e-9) << "a force above the device's nominal maximum was written";
  EXPECT_GE(fmax, 3.3 - 1e-9) << "the 100 N request should have been rendered at the device maximum";
  expect_zero_last_then_off_then_closed(ev);
  EXPECT_NE(s.log().find("reports a max force of 3.3 N"), std::string::npos) << s.log();
}

TEST(DeviceVendor, ForceDimensionAxesMappedToTheViewAndTorqueOnAnActiveWrist) {
  // Vendor frame: x towards the user, y right, z up; rest (0.01, 0.02, 0.03) m. A sigma.7 (type 104)
  // has an actuated wrist: torque is written.
  Session s("dhd_axes", dhd_args({"--feedback-timeout-s", "0.5"}), {{"FAKE_HAPTIC_PATH", "0:0.01,0.02,0.03"}, {"FAKE_HAPTIC_TYPE", "104"}});
  ASSERT_GT(s.pid, 0);
  ASSERT_TRUE(s.coupler->wait_states(200)) << s.log();
  const lcmt_device_state rest = s.coupler->states().back();
  EXPECT_NEAR(rest.position_m[0], 0.02, 1e-12);   // right
  EXPECT_NEAR(rest.position_m[1], 0.03, 1e-12);   // up
  EXPECT_NEAR(rest.position_m[2], 0.01, 1e-12);   // towards the user
  // A quarter turn about the vendor's vertical is one about the view's vertical.
  EXPECT_NEAR(quat(rest).angularDistance(Quat(Eigen::AngleAxisd(M_PI / 2, Vec3::UnitY()))), 0.0, 1e-9);
  const double t_fb = s.coupler->feedback(Vec3(1.0, -2.0, 0.5), Vec3(0.1, 0, 0));
  sleep_s(0.5);
  // Vendor (0.01, 0.02, 0.03) m pushed by (1, -2, 0.5) N in haptree's frame.
  expect_pushed(pos(s.coupler->states().back()), Vec3(0.02, 0.03, 0.01), Vec3(1.0, -2.0, 0.5));
  EXPECT_EQ(s.stop(), 0) << s.log();
  const auto ev = s.events();
  expect_no_force_before_feedback(ev, t_fb);
  const Event* steady = max_force_between(ev, t_fb, unix_now());
  ASSERT_NE(steady, nullptr);
  // Vendor force = (towards the user, right, up) = (f.z, f.x, f.y); torque likewise.
  EXPECT_NEAR(steady->v[0], 0.5, 1e-12);
  EXPECT_NEAR(steady->v[1], 1.0, 1e-12);
  EXPECT_NEAR(steady->v[2], -2.0, 1e-12);
  EXPECT_NEAR(steady->v[3], 0.0, 1e-12);
  EXPECT_NEAR(steady->v[4], 0.1, 1e-12);
  EXPECT_NEAR(steady->v[5], 0.0, 1e-12);
  expect_zero_last_then_off_then_closed(ev);
}

TEST(DeviceVendor, OpenHapticsSixDofWritesTorqueInMilliNewtonMetresWithinTheLimit) {
  // A Premium-6DOF-like fake (HD_OUTPUT_DOF 6): torque in mN m along the HD axes (= haptree's), clamped
  // to the 6-DOF torque limit the HD API does not report (the device table's Premium 6DOF, 0.188 N m).
  Session s("hd_6dof", hd_args({"--feedback-timeout-s", "0.5"}), {{"FAKE_HAPTIC_DOF", "6"}});
  ASSERT_GT(s.pid, 0);
  ASSERT_TRUE(s.coupler->wait_states(10)) << s.log();
  const double t_fb = s.coupler->feedback(Vec3(0.5, 0, 0), Vec3(0.1, -0.05, 0.02));
  sleep_s(0.5);
  const double t_big = s.coupler->feedback(Vec3(0.5, 0, 0), Vec3(0, 0, 1.0));
  sleep_s(0.4);
  EXPECT_EQ(s.stop(), 0) << s.log();
  const auto ev = s.events();
  expect_no_force_before_feedback(ev, t_fb);
  const Event* steady = max_force_between(ev, t_fb, t_big);
  ASSERT_NE(steady, nullptr);
  double steady_tau[3] = {0, 0, 0};   // the largest torque written while (0.1, -0.05, 0.02) N m was asked
  for (const auto& e : ev)
    if (e.is_force() && e.t > t_fb && e.t < t_big && e.torque_norm() > Vec3(steady_tau[0], steady_tau[1], steady_tau[2]).norm())
      for (int i = 0; i < 3; ++i) steady_tau[i] = e.v[3 + i];
  EXPECT_NEAR(steady_tau[0], 100.0, 1e-9);
  EXPECT_NEAR(steady_tau[1], -50.0, 1e-9);
  EXPECT_NEAR(steady_tau[2], 20.0, 1e-9);
  double tau_max = 0, tau_z_max = 0;
  for (const auto& e : ev) {
    tau_max = std::max(tau_max, e.torque_norm());
    if (e.t > t_big) tau_z_max = std::max(tau_z_max, e.v[5]);
  }
  EXPECT_LE(tau_max, 188.0 + 1e-9) << "a torque above the 6-DOF limit was written";
  EXPECT_NEAR(tau_z_max, 188.0, 1e-9) << "1 N m asked: written at the limit, 0.188 N m";
  expect_zero_last_then_off_then_closed(ev);
  // The same command on a 3-DOF device: no torque is ever written.
  Session s3("hd_3dof", hd_args({"--feedback-timeout-s", "0.5"}), {});
  ASSERT_GT(s3.pid, 0);
  ASSERT_TRUE(s3.coupler->wait_states(10)) << s3.log();
  s3.coupler->feedback(Vec3(0.5, 0, 0), Vec3(0.1, -0.05, 0.02));
  sleep_s(0.3);
  EXPECT_EQ(s3.stop(), 0) << s3.log();
  double f3 = 0, tau3 = 0;
  for (const auto& e : s3.events()) f3 = std::max(f3, e.norm()), tau3 = std::max(tau3, e.torque_norm());
  EXPECT_NEAR(f3, 0.5, 1e-12);
  EXPECT_EQ(tau3, 0.0) << "torque written to a 3-DOF device";
}

TEST(DeviceVendor, OpenHapticsAutoCalibrationIsAppliedBeforeForceOutput) {
  // hdCheckCalibration: HD_CALIBRATION_NEEDS_UPDATE; the device's style is HD_CALIBRATION_AUTO, so the
  // driver calls hdUpdateCalibration(HD_CALIBRATION_AUTO) in the servo loop, and forces work after it.
  Session s("hd_cal_update", hd_args({"--feedback-timeout-s", "0.5"}), {{"FAKE_HAPTIC_CALIBRATION", "update"}});
  ASSERT_GT(s.pid, 0);
  ASSERT_TRUE(s.coupler->wait_states(10)) << s.log();
  const double t_fb = s.coupler->feedback(Vec3(0.5, 0, 0));
  sleep_s(0.3);
  EXPECT_EQ(s.stop(), 0) << s.log();
  const auto ev = s.events();
  int calibrate = -1, enable = -1, calibrations = 0;
  for (int i = 0; i < static_cast<int>(ev.size()); ++i) {
    if (ev[i].what == "calibrate") {
      ++calibrations;
      if (calibrate < 0) calibrate = i;
      EXPECT_EQ(ev[i].v[0], 2.0) << "hdUpdateCalibration with a style other than HD_CALIBRATION_AUTO";
    }
    if (ev[i].what == "enable" && enable < 0) enable = i;
  }
  ASSERT_GE(calibrate, 0) << "hdUpdateCalibration was never called";
  EXPECT_EQ(calibrations, 1) << "calibrated again although the device said it was calibrated";
  ASSERT_GE(enable, 0) << s.log();
  EXPECT_LT(calibrate, enable);
  expect_no_force_before_feedback(ev, t_fb);
  expect_zero_last_then_off_then_closed(ev);
}

TEST(DeviceVendor, OpenHapticsDeviceNeedingCalibrationByHandIsRefusedWithOneLine) {
  // HD_CALIBRATION_NEEDS_MANUAL_INPUT (the stylus never goes into its inkwell): poses still flow, but at
  // the first FEEDBACK the bridge refuses to turn force output on: exit 3, one line saying why, and the
  // device never rendered a force.
  Session s("hd_cal_manual", hd_args(), {{"FAKE_HAPTIC_CALIBRATION", "manual"}});
  ASSERT_GT(s.pid, 0);
  ASSERT_TRUE(s.coupler->wait_states(10)) << s.log();
  s.coupler->feedback(Vec3(1.0, 0, 0));
  EXPECT_EQ(reap(s.pid, 5), 3) << s.log();
  const std::string log = s.log();
  int lines_why = 0;
  std::istringstream in(log);
  for (std::string line; std::getline(in, line);)
    lines_why += line.find("needs calibration by hand") != std::string::npos;
  EXPECT_EQ(lines_why, 1) << log;
  EXPECT_NE(log.find("put the stylus in its inkwell"), std::string::npos) << log;
  const auto ev = s.events();
  bool closed = false;
  for (const auto& e : ev) {
    EXPECT_NE(e.what, "enable") << "force output turned on for an uncalibrated device";
    EXPECT_NE(e.what, "calibrate") << "a device that needs calibration by hand was not asked for it";
    if (e.is_force()) {
      EXPECT_EQ(e.norm(), 0.0);
    }
    closed |= e.what == "close";
  }
  EXPECT_TRUE(closed);
}

TEST(DeviceVendor, GrabCountsPressesAndClutchIndexesTheWorkspace) {
  // Button 0 pressed twice (grab), then button 1 (clutch) held 1.1-1.6 s while the hand moves +40 mm;
  // at 2.0 s the hand comes back: the proxy ends 40 mm behind where it started.
  Session s("hd_buttons", hd_args({"--feedback-timeout-s", "0.5"}),
            {{"FAKE_HAPTIC_PATH", "0:0,0,0;1.3:40,0,0;2.0:0,0,0"},
             {"FAKE_HAPTIC_BUTTONS", "0:0;0.3:1;0.5:0;0.7:1;0.9:0;1.1:2;1.6:0"}});
  ASSERT_GT(s.pid, 0);
  ASSERT_TRUE(s.coupler->wait_states(10)) << s.log();
  s.coupler->feedback(Vec3(0.5, 0, 0));
  sleep_s(2.6);
  EXPECT_EQ(s.stop(), 0) << s.log();
  const auto st = s.coupler->states();
  int32_t max_seq = 0;
  bool grab_seen = false, clutch_seen = false;
  Vec3 held = Vec3::Zero();
  double clutch_drift = 0;
  for (const auto& m : st) {
    EXPECT_EQ(m.grab_body, 0) << "a hardware device lets the coupler pick the body";
    if (m.buttons & 1) {
      grab_seen = true;
      max_seq = std::max(max_seq, m.grab_seq);
    }
    if (m.buttons & 2) {
      if (!clutch_seen) held = pos(m);
      clutch_seen = true;
      clutch_drift = std::max(clutch_drift, (pos(m) - held).norm());
      EXPECT_EQ(m.linear_velocity_mps[0], 0.0);
    }
  }
  EXPECT_TRUE(grab_seen);
  EXPECT_EQ(max_seq, 2) << "two presses of the grab button";
  ASSERT_TRUE(clutch_seen);
  EXPECT_EQ(clutch_drift, 0.0) << "the proxy moved while the clutch was held";
  // The hand moved 40 mm with the clutch held (no force then), and the 0.5 N pushes it 0.5/200 m before and
  // after: the proxy ends 40 mm behind where the clutch was pressed, plus that same 2.5 mm.
  EXPECT_NEAR(pos(st.back()).x(), held.x() - 0.040 + 0.5 / 200, 5e-4) << "the clutch stroke did not index the workspace";
  // While the clutch is held no force reaches the hand (ramped out within a few ms).
  const auto ev = s.events();
  double t_open = 0;
  for (const auto& e : ev)
    if (e.what == "open") t_open = e.t;
  double clutch_fmax = 0, free_fmax = 0;
  for (const auto& e : ev) {
    if (!e.is_force()) continue;
    if (e.t > t_open + 1.2 && e.t < t_open + 1.55) clutch_fmax = std::max(clutch_fmax, e.norm());
    if (e.t > t_open + 0.5 && e.t < t_open + 1.0) free_fmax = std::max(free_fmax, e.norm());
  }
  EXPECT_NEAR(free_fmax, 0.5, 1e-12);
  EXPECT_EQ(clutch_fmax, 0.0);
  expect_zero_last_then_off_then_closed(ev);
}

// Faults: each ends with zero force written last, then force output off, then the device closed, and
// exit code 3 with one line saying why.
void fault_run(const std::string& name, std::vector<std::string> args, Env env, const std::string& why) {
  Session s(name, args, env);
  ASSERT_GT(s.pid, 0);
  ASSERT_TRUE(s.coupler->wait_states(10)) << s.log();
  s.coupler->feedback(Vec3(1.0, 0.5, -0.5));
  const int rc = reap(s.pid, 5);
  EXPECT_EQ(rc, 3) << s.log();
  const std::string log = s.log();
  EXPECT_NE(log.find(why), std::string::npos) << log;
  EXPECT_NE(log.find("zero force and torque written, force output off, device closed"), std::string::npos) << log;
  expect_zero_last_then_off_then_closed(s.events());
}

TEST(DeviceVendor, OpenHapticsErrorCodeEndsWithZeroForce) {
  fault_run("hd_error", hd_args(), {{"FAKE_HAPTIC_FAULT", "error@0.7"}}, "OpenHaptics error 0x0302");
}
TEST(DeviceVendor, OpenHapticsServoCallbackThatStopsEndsWithZeroForce) {
  fault_run("hd_stop", hd_args(), {{"FAKE_HAPTIC_FAULT", "stop@0.7"}}, "servo loop stopped");
}
TEST(DeviceVendor, OpenHapticsNonFinitePoseEndsWithZeroForce) {
  fault_run("hd_nan", hd_args(), {{"FAKE_HAPTIC_FAULT", "nan@0.7"}}, "non-finite pose");
}
TEST(DeviceVendor, ForceDimensionFailedReadEndsWithZeroForce) {
  fault_run("dhd_error", dhd_args(), {{"FAKE_HAPTIC_FAULT", "error@0.7"}}, "dhdGetPosition failed: communication error");
}

TEST(DeviceVendor, CrashOfTheBridgeStillWritesZeroForceLast) {
  for (const auto& kind : {std::string("hd"), std::string("dhd")}) {
    Session s("crash_" + kind, kind == "hd" ? hd_args() : dhd_args(), {});
    ASSERT_GT(s.pid, 0);
    ASSERT_TRUE(s.coupler->wait_states(10)) << s.log();
    s.coupler->feedback(Vec3(1.0, 0.5, -0.5));
    sleep_s(0.4);
    EXPECT_EQ(s.stop(SIGSEGV), 128 + SIGSEGV) << s.log();
    const auto ev = s.events();
    int last_force = -1, last_nonzero = -1, disable = -1;
    for (int i = 0; i < static_cast<int>(ev.size()); ++i) {
      if (ev[i].is_force()) last_force = i;
      if (ev[i].is_force() && ev[i].norm() > 0) last_nonzero = i;
      if (ev[i].what == "disable") disable = i;
    }
    ASSERT_GE(last_nonzero, 0) << kind;
    EXPECT_EQ(ev[last_force].norm(), 0.0) << kind << ": a crash left a force on the device";
    EXPECT_GT(disable, last_nonzero) << kind << ": force output not turned off after the crash";
  }
}

TEST(DeviceVendor, FeedbackWatchdogRampsTheDeviceToZero) {
  Session s("hd_watchdog", hd_args(), {});
  ASSERT_GT(s.pid, 0);
  ASSERT_TRUE(s.coupler->wait_states(10)) << s.log();
  const double t_fb = s.coupler->feedback(Vec3(2.0, 0, 0));
  sleep_s(0.5);
  s.coupler->silence();
  const double t_silent = unix_now();
  sleep_s(0.4);
  EXPECT_EQ(s.stop(), 0) << s.log();
  const auto ev = s.events();
  // Feedback timeout 10 ms + ramp 5 ms: zero from 50 ms after the silence on (generous for a loaded host).
  double after = 0, before = 0;
  for (const auto& e : ev) {
    if (!e.is_force()) continue;
    if (e.t > t_silent + 0.05 && e.t < t_silent + 0.35) after = std::max(after, e.norm());
    if (e.t > t_fb && e.t < t_silent) before = std::max(before, e.norm());
  }
  EXPECT_GT(before, 0.5) << "no force rendered while FEEDBACK came";   // 2 N unless a busy host tripped the watchdog
  EXPECT_LE(before, 2.0 + 1e-12);
  EXPECT_EQ(after, 0.0) << "FEEDBACK stopped but the device still renders a force";
  expect_zero_last_then_off_then_closed(ev);
}

// ---- start-up errors and --probe (no bus needed) ----

struct Result {
  int rc;
  std::string out;
};
Result run(const std::vector<std::string>& args, const Env& env, const std::string& name) {
  const std::string log = ::testing::TempDir() + "vendor_" + name + ".log";
  std::vector<std::string> a = {HAPTREE_DEVICE_BRIDGE, "--lcm-url", "memq://"};
  a.insert(a.end(), args.begin(), args.end());
  const pid_t p = spawn(a, env, log);
  return {reap(p, 10), slurp(log)};
}
int lines(const std::string& s) { return static_cast<int>(std::count(s.begin(), s.end(), '\n')); }

TEST(DeviceVendor, MissingLibrarySymbolOrDeviceIsOneClearLineAndExit1) {
  Result r = run({"--device-kind", "openhaptics", "--device-option", "lib=/nonexistent/libHD.so"}, {}, "nolib_hd");
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_EQ(lines(r.out), 1) << r.out;
  EXPECT_NE(r.out.find("cannot load /nonexistent/libHD.so"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("install 3D Systems' OpenHaptics runtime"), std::string::npos) << r.out;
  // The default names, in order, when none is given and none is installed.
  r = run({"--device-kind", "forcedimension"}, {{"LD_LIBRARY_PATH", "/nonexistent"}}, "nolib_dhd");
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_EQ(lines(r.out), 1) << r.out;
  EXPECT_NE(r.out.find("cannot load libdrd.so.3, libdhd.so.3"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("Force Dimension SDK"), std::string::npos) << r.out;
  r = run({"--device-kind", "openhaptics", "--device-option", std::string("lib=") + FAKE_HD_PARTIAL_LIB}, {}, "nosym");
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_EQ(lines(r.out), 1) << r.out;
  EXPECT_NE(r.out.find("has no symbol hdScheduleAsynchronous"), std::string::npos) << r.out;
  r = run(hd_args(), {{"FAKE_HAPTIC_FAULT", "dead"}}, "nodev_hd");
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_EQ(lines(r.out), 1) << r.out;
  EXPECT_NE(r.out.find("no OpenHaptics device 'default'"), std::string::npos) << r.out;
  r = run(dhd_args(), {{"FAKE_HAPTIC_FAULT", "dead"}}, "nodev_dhd");
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_EQ(lines(r.out), 1) << r.out;
  EXPECT_NE(r.out.find("no Force Dimension device found (dhdOpen: no device found (fake))"), std::string::npos) << r.out;
  r = run(hd_args({"--device-option", "axes=x,x,z"}), {}, "badaxes");
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_NE(r.out.find("axes 'x,x,z': axis x used twice"), std::string::npos) << r.out;
}

TEST(DeviceVendor, ProbePrintsModelSerialLimitsPositionButtonsAndRendersNoForce) {
  const std::string flog = ::testing::TempDir() + "vendor_probe_forces.log";
  std::remove(flog.c_str());
  Result r = run(hd_args({"--probe"}),
                 {{"FAKE_HAPTIC_PATH", "0:10,20,-30"}, {"FAKE_HAPTIC_BUTTONS", "0:1"}, {"FAKE_HAPTIC_LOG", flog}},
                 "probe_hd");
  EXPECT_EQ(r.rc, 0) << r.out;
  for (const char* want : {"model: Touch (fake)", "serial: FAKE-0001", "max force: 3.3 N", "max continuous force: 0.88 N",
                           "max stiffness: 400 N/m", "max damping: 4 N s/m", "workspace radius: 0.035 m",
                           "axes: x,y,z", "position: 0.010000 0.020000 -0.030000 m", "buttons: 1 (grab down, clutch up)"})
    EXPECT_NE(r.out.find(want), std::string::npos) << want << "\n" << r.out;
  for (const auto& e : read_log(flog)) {
    EXPECT_NE(e.what, "enable") << "--probe turned force output on";
    if (e.is_force()) {
      EXPECT_EQ(e.norm(), 0.0);
    }
  }
  // Force Dimension, found by its default name on the loader path (libdrd.so.3 absent, libdhd.so.3 found).
  r = run({"--device-kind", "forcedimension", "--probe"},
          {{"LD_LIBRARY_PATH", FAKE_DHD_DIR}, {"FAKE_HAPTIC_PATH", "0:0.01,0.02,0.03"}, {"FAKE_HAPTIC_BUTTONS", "0:2"}},
          "probe_dhd");
  EXPECT_EQ(r.rc, 0) << r.out;
  for (const char* want : {"model: omega.3 (fake)", "serial: 4242", "max force: 12 N", "axes: y,z,x",
                           "position: 0.020000 0.030000 0.010000 m", "buttons: 2 (grab up, clutch down)",
                           "orientation: no, torque output: no"})
    EXPECT_NE(r.out.find(want), std::string::npos) << want << "\n" << r.out;
}

}  // namespace
}  // namespace haptree
