// The real launcher, `haptree_run --device-kind KIND`, with user 0 on a fake vendor device: the fake
// libHD.so and libdhd.so.3 (tests/device/fakes) and the fake Inverse Service (tests/device/inverse3),
// in --processes mode (sim_server, coupler and device_bridge as child processes) and in the embedded
// mode (all in the launcher's threads).
// The device holds its first button from 0.3 s after it is opened; the scene is a chain under gravity,
// so the grabbed body hangs on the coupling spring and pulls the hand with more than the force limit. Checked from the fake's log of every force written and from the launcher's --json status:
// the device's poses reach the coupler (the grab happens), the forces written are finite and never
// above the force limit (reached: the pull is larger), none is written before force output is
// enabled (on the first FEEDBACK: never before user 0's coupler existed) nor before the grab, the last force written is zero once the launcher
// ends (--duration-s or SIGTERM), then force output is off and the device closed, and no child process
// is left running.
#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <ctime>
#include <regex>
#include <cstdio>
#include <sstream>
#include <string>
#include <vector>

#include "tests/device/inverse3/fake_inverse_service.hpp"
#include "tests/device/vendor_test_util.hpp"

namespace haptree {
namespace {

using namespace vendor_test;

// The launcher's session: a chain of 6 bodies under gravity at 500 Hz, a 2 kHz coupler, the launcher's
// force limit (--max-force-n 3 N, below every fake's own maximum).
std::vector<std::string> launcher_args(bool processes, const std::string& kind, const std::vector<std::string>& options,
                                       double duration_s, const std::string& log_dir) {
  std::vector<std::string> a = {HAPTREE_RUN, "--json", "--viewer-port", "0", "--scene", "chain", "--n", "6", "--sim-rate-hz", "500",
                                "--coupler-rate-hz", "2000", "--device-kind", kind,
                                "--duration-s", std::to_string(duration_s)};
  for (const auto& o : options) a.insert(a.end(), {"--device-option", o});
  if (processes) a.insert(a.end(), {"--processes", "--log-dir", log_dir});
  return a;
}

struct Launch {
  int rc = -1;
  std::string out;
  std::vector<std::string> json;   // the --json status objects, one per line
  std::vector<pid_t> children;     // from the launcher's "  NAME pid N" lines (--processes)
};

// Runs the launcher; with stop_after_s > 0 it is stopped by SIGTERM then, else it ends by --duration-s.
Launch launch(const std::string& name, const std::vector<std::string>& args, const Env& env, double stop_after_s = 0) {
  Launch l;
  const std::string log = ::testing::TempDir() + "launcher_" + name + ".log";
  const pid_t p = spawn(args, env, log);
  if (p <= 0) return l;
  if (stop_after_s > 0) {
    sleep_s(stop_after_s);
    ::kill(p, SIGTERM);
  }
  l.rc = reap(p, 60);
  l.out = slurp(log);
  std::istringstream in(l.out);
  for (std::string line; std::getline(in, line);) {
    if (line.rfind("{\"t_s\":", 0) == 0) l.json.push_back(line);
    std::smatch m;
    static const std::regex child(R"(\[info\] +(sim_server|coupler_\d+|device_bridge_\d+) pid (\d+)\s*$)");
    if (std::regex_search(line, m, child)) l.children.push_back(std::stoi(m[2].str()));
  }
  return l;
}

// The body user 0 held in the status object `j` (0: none).
int grab_body(const std::string& j) {
  const auto u = j.find("\"user\":0,");
  const auto g = j.find("\"grab_body\":", u);
  if (u == std::string::npos || g == std::string::npos) return 0;
  return std::atoi(j.c_str() + g + 12);
}

// A process that is gone, or a zombie of someone else's (never ours: the launcher reaped them).
bool running(pid_t p) {
  const std::string cmd = slurp("/proc/" + std::to_string(p) + "/cmdline");
  return !cmd.empty();
}

// What every launcher run with a device must show (forces in the fake's log; max_n: the force limit,
// reached because the hanging chain pulls harder).
// The unix time of the first line of user 0's coupler (logged as it is constructed, before it can send
// any FEEDBACK), from its spdlog stamp (local time, ms truncated: at most the true time); -1 if none.
double coupler_constructed(const std::string& log_dir) {
  std::istringstream in(slurp(log_dir + "/coupler_0.log"));
  static const std::regex line(R"(^\[(\d+)-(\d+)-(\d+) (\d+):(\d+):(\d+)\.(\d+)\] \[info\] coupler 0: device)");
  for (std::string l; std::getline(in, l);) {
    std::smatch m;
    if (!std::regex_search(l, m, line)) continue;
    std::tm tm{};
    tm.tm_year = std::stoi(m[1].str()) - 1900;
    tm.tm_mon = std::stoi(m[2].str()) - 1;
    tm.tm_mday = std::stoi(m[3].str());
    tm.tm_hour = std::stoi(m[4].str());
    tm.tm_min = std::stoi(m[5].str());
    tm.tm_sec = std::stoi(m[6].str());
    tm.tm_isdst = -1;
    return static_cast<double>(std::mktime(&tm)) + 1e-3 * std::stoi(m[7].str());
  }
  return -1;
}

// log_dir: the launcher's --log-dir with --processes, "" embedded.
void expect_session(const Launch& l, const std::vector<Event>& ev, double max_n, const std::string& log_dir) {
  const bool processes = !log_dir.empty();
  EXPECT_EQ(l.rc, 0) << l.out;
  int grabbed = 0;
  for (const auto& j : l.json) grabbed = std::max(grabbed, grab_body(j));
  EXPECT_GT(grabbed, 0) << "the device's grab never reached the coupler\n" << l.out;
  double t_open = -1, fmax = 0, t_first_nonzero = -1;
  bool finite = true;
  for (const auto& e : ev) {
    if (e.what == "open" && t_open < 0) t_open = e.t;
    if (!e.is_force()) continue;
    finite &= e.finite();
    fmax = std::max(fmax, e.norm());
    if (e.norm() > 0 && t_first_nonzero < 0) t_first_nonzero = e.t;
  }
  ASSERT_GT(t_open, 0) << l.out;
  EXPECT_TRUE(finite) << "a non-finite force was written";
  // The fakes log 9 significant digits per component: |f| read back is within 1e-8 |f| of what was written.
  const double tol = 1e-8 * max_n;
  EXPECT_LE(fmax, max_n + tol) << "a force above the limit was written";
  EXPECT_GE(fmax, max_n - tol) << "the chain's pull should have been rendered at the limit";
  EXPECT_GE(t_first_nonzero, t_open + 0.3) << "a force before the grab button was pressed";
  const double t_enable = expect_no_force_before_enable(ev);
  expect_zero_last_then_off_then_closed(ev);
  if (processes) {
    // Force output comes on only with the first FEEDBACK, which the coupler sends once it exists.
    const double t_coupler = coupler_constructed(log_dir);
    ASSERT_GT(t_coupler, 0) << slurp(log_dir + "/coupler_0.log");
    EXPECT_GE(t_enable, t_coupler) << "force output enabled before user 0's coupler existed";
    EXPECT_EQ(l.children.size(), 3u) << l.out;
    for (pid_t c : l.children) EXPECT_FALSE(running(c)) << "child " << c << " still running\n" << l.out;
    EXPECT_NE(l.out.find("device_bridge_0 exit code 0"), std::string::npos) << l.out;
  }
}

std::string fresh_log(const std::string& name) {
  const std::string f = ::testing::TempDir() + "launcher_" + name + "_forces.log";
  std::remove(f.c_str());
  return f;
}

// The fake devices start at the point the launcher maps onto the grabbed body: (0, 0, 0.01) m in the view.
TEST(DeviceLauncher, OpenHapticsProcessesEndedByDuration) {
  const std::string flog = fresh_log("hd_processes");
  const std::string dir = ::testing::TempDir() + "launcher_hd_processes";
  const Launch l = launch("hd_processes", launcher_args(true, "openhaptics", {std::string("lib=") + FAKE_HD_LIB}, 3, dir),
                          {{"FAKE_HAPTIC_LOG", flog}, {"FAKE_HAPTIC_PATH", "0:0,0,10"}, {"FAKE_HAPTIC_BUTTONS", "0:0;0.3:1"}});
  expect_session(l, read_log_until_closed(flog), 3.0, dir);
}

TEST(DeviceLauncher, ForceDimensionProcessesEndedBySigterm) {
  // Vendor axes: x towards the user (the view's +z), y right, z up; metres.
  const std::string flog = fresh_log("dhd_processes");
  const std::string dir = ::testing::TempDir() + "launcher_dhd_processes";
  const Launch l = launch("dhd_processes", launcher_args(true, "forcedimension", {std::string("lib=") + FAKE_DHD_LIB}, 0, dir),
                          {{"FAKE_HAPTIC_LOG", flog}, {"FAKE_HAPTIC_PATH", "0:0.01,0,0"}, {"FAKE_HAPTIC_BUTTONS", "0:0;0.3:1"}},
                          3.5);
  EXPECT_NE(l.out.find("interrupted, stopping the children"), std::string::npos) << l.out;
  expect_session(l, read_log_until_closed(flog), 3.0, dir);
}

TEST(DeviceLauncher, OpenHapticsEmbedded) {
  const std::string flog = fresh_log("hd_embedded");
  const Launch l = launch("hd_embedded", launcher_args(false, "openhaptics", {std::string("lib=") + FAKE_HD_LIB}, 3, ""),
                          {{"FAKE_HAPTIC_LOG", flog}, {"FAKE_HAPTIC_PATH", "0:0,0,10"}, {"FAKE_HAPTIC_BUTTONS", "0:0;0.3:1"}});
  expect_session(l, read_log_until_closed(flog), 3.0, "");
}

// The gains are checked against the limits the device reports at open (here a max force of 2 N, below the
// launcher's --max-force-n 3), not only against --device-model's row (simulated: 1000 N), which passes.
// --processes: user 0's coupler waits for device_bridge's report and refuses to start (exit 2).
TEST(DeviceLauncher, ProcessesCouplerRefusesGainsAboveTheLimitsTheDeviceReports) {
  const std::string flog = fresh_log("hd_refuse");
  const Launch l = launch("hd_refuse", launcher_args(true, "openhaptics", {std::string("lib=") + FAKE_HD_LIB}, 10,
                                                     ::testing::TempDir() + "launcher_hd_refuse"),
                          {{"FAKE_HAPTIC_LOG", flog}, {"FAKE_HAPTIC_PATH", "0:0,0,10"}, {"FAKE_HAPTIC_BUTTONS", "0:1"},
                           {"FAKE_HAPTIC_MAX_FORCE", "2"}});
  EXPECT_EQ(l.rc, 1) << l.out;
  EXPECT_NE(l.out.find("child coupler_0"), std::string::npos) << l.out;
  EXPECT_NE(l.out.find("exit code 2"), std::string::npos) << l.out;
  const std::string clog = slurp(::testing::TempDir() + "launcher_hd_refuse/coupler_0.log");
  EXPECT_NE(clog.find("force clamp --max-force-n 3 N exceeds 2 N by a factor 1.5: the device's max force on device 0"),
            std::string::npos) << clog;
  EXPECT_NE(clog.find("refusing to start"), std::string::npos) << clog;
  for (pid_t c : l.children) EXPECT_FALSE(running(c)) << "child " << c << " still running\n" << l.out;
  double fmax = 0;
  bool enabled = false, closed = false;
  for (const auto& e : read_log_until_closed(flog)) {
    if (e.is_force()) fmax = std::max(fmax, e.norm());
    enabled |= e.what == "enable";
    closed |= e.what == "close";
  }
  EXPECT_EQ(fmax, 0.0);
  EXPECT_FALSE(enabled) << "force output on without a coupler";
  EXPECT_TRUE(closed);
}

// With --clamp-gains the coupler lowers the force clamp (and a stiffness above the device's reported
// 400 N/m: 100 x 10 x 0.5 = 500 N/m) to the device's limits and the session runs at them.
TEST(DeviceLauncher, ProcessesCouplerClampsGainsToTheLimitsTheDeviceReports) {
  const std::string flog = fresh_log("hd_clamp");
  const std::string dir = ::testing::TempDir() + "launcher_hd_clamp";
  std::vector<std::string> args = launcher_args(true, "openhaptics", {std::string("lib=") + FAKE_HD_LIB}, 3, dir);
  args.insert(args.end(), {"--stiffness", "100", "--clamp-gains"});
  const Launch l = launch("hd_clamp", args,
                          {{"FAKE_HAPTIC_LOG", flog}, {"FAKE_HAPTIC_PATH", "0:0,0,10"}, {"FAKE_HAPTIC_BUTTONS", "0:0;0.3:1"},
                           {"FAKE_HAPTIC_MAX_FORCE", "2"}});
  const std::string clog = slurp(dir + "/coupler_0.log");
  EXPECT_NE(clog.find("--clamp-gains: stiffness 100 -> 80, damping 0 -> 0, max force 3 -> 2 N"), std::string::npos) << clog;
  expect_session(l, read_log_until_closed(flog), 2.0, dir);
}

// Embedded: the launcher opens the device before the coupler and refuses (exit 2) the same way.
TEST(DeviceLauncher, EmbeddedRefusesGainsAboveTheLimitsTheDeviceReports) {
  const std::string flog = fresh_log("hd_embedded_refuse");
  const Launch l = launch("hd_embedded_refuse", launcher_args(false, "openhaptics", {std::string("lib=") + FAKE_HD_LIB}, 10, ""),
                          {{"FAKE_HAPTIC_LOG", flog}, {"FAKE_HAPTIC_MAX_FORCE", "2"}});
  EXPECT_EQ(l.rc, 2) << l.out;
  EXPECT_NE(l.out.find("haptree_run: unsafe gains: force clamp --max-force-n 3 N exceeds 2 N"), std::string::npos) << l.out;
  EXPECT_NE(l.out.find("refusing to start"), std::string::npos) << l.out;
  bool enabled = false, closed = false;
  for (const auto& e : read_log_until_closed(flog)) enabled |= e.what == "enable", closed |= e.what == "close";
  EXPECT_FALSE(enabled);
  EXPECT_TRUE(closed) << "the device was not closed after the refusal";
}

TEST(DeviceLauncher, Inverse3ProcessesEndedByDuration) {
  // Haply axes: x right, y away from the user, z up. The service reports no force limit.
  testing::FakeInverseOptions o;
  o.rest_m = Vec3(0, -0.01, 0);
  o.buttons = {{0.3, 1e9, 1}};
  testing::FakeInverseService svc(o);
  const Launch l = launch("i3_processes", launcher_args(true, "inverse3", {"url=" + svc.url(), "timeout_s=0.5"}, 3,
                                                        ::testing::TempDir() + "launcher_i3_processes"),
                          {});
  EXPECT_EQ(l.rc, 0) << l.out;
  int grabbed = 0;
  for (const auto& j : l.json) grabbed = std::max(grabbed, grab_body(j));
  EXPECT_GT(grabbed, 0) << "the device's grab never reached the coupler\n" << l.out;
  for (int i = 0; i < 200 && svc.open_connections() > 0; ++i) sleep_s(0.01);   // the last command read
  const auto forces = svc.forces();
  ASSERT_GT(forces.size(), 100u) << l.out;
  double fmax = 0, t_first_nonzero = -1;
  for (const auto& r : forces) {
    EXPECT_TRUE(r.force_n.allFinite());
    fmax = std::max(fmax, r.force_n.norm());
    if (r.force_n.norm() > 0 && t_first_nonzero < 0) t_first_nonzero = r.t_s;
  }
  EXPECT_LE(fmax, 3.0 + 1e-9) << "a force above the limit was sent";
  EXPECT_GE(fmax, 3.0 - 1e-9) << "the chain's pull should have been rendered at the limit";
  EXPECT_GE(t_first_nonzero, 0.3) << "a force before the grab button was pressed";
  EXPECT_EQ(forces.back().force_n, Vec3::Zero()) << "the last command is not a zero force";
  EXPECT_TRUE(forces.back().applied);
  EXPECT_EQ(l.children.size(), 3u) << l.out;
  for (pid_t c : l.children) EXPECT_FALSE(running(c)) << "child " << c << " still running\n" << l.out;
}

}  // namespace
}  // namespace haptree
