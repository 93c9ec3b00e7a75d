// What the fake vendor libraries share: a simulated mechanism (a point mass on a spring whose rest point
// follows a schedule), buttons on a schedule, injectable faults, and a log of every force written.
// Configured by environment variables, read when the device is opened:
//   FAKE_HAPTIC_LOG      file; one line per event, "<unix time s> <event> ...":
//                        open, close, enable, disable, force fx fy fz tx ty tz (vendor units), error CODE,
//                        calibrate STYLE (libHD)
//   FAKE_HAPTIC_PATH     "t:x,y,z;t:x,y,z;..." rest point (vendor units) from time t (s after open)
//   FAKE_HAPTIC_BUTTONS  "t:mask;t:mask;..." button bits from time t
//   FAKE_HAPTIC_FAULT    dead (no device) | error@T (vendor error code from T) | stop@T (the servo
//                        callback is no longer called from T; libHD only) | nan@T (non-finite position)
//   FAKE_HAPTIC_TYPE     libdhd: the system type dhdGetSystemType reports (default 33, omega.3)
//   FAKE_HAPTIC_DOF      libHD: HD_OUTPUT_DOF (default 3; 6 renders torque)
//   FAKE_HAPTIC_MAX_FORCE  libHD: HD_NOMINAL_MAX_FORCE, N (default 3.3, a Touch's)
//   FAKE_HAPTIC_CALIBRATION  libHD: ok (default) | manual (hdCheckCalibration: needs manual input, for
//                        ever) | update (needs an update until hdUpdateCalibration(HD_CALIBRATION_AUTO))
// Test code: plain and direct, async-signal-safe where the drivers' emergency stop calls in.
#pragma once

#include <fcntl.h>
#include <time.h>
#include <unistd.h>

#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

namespace fake {

inline double unix_now() {
  timespec ts;
  clock_gettime(CLOCK_REALTIME, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}
inline double mono_now() {
  timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

struct Step {
  double t;
  double v[3];
  int mask;
};

// "t:x,y,z;..." (vector) or "t:mask;..." (mask).
inline std::vector<Step> parse_schedule(const char* s, bool vector) {
  std::vector<Step> out;
  if (!s) return out;
  std::string str(s);
  size_t pos = 0;
  while (pos < str.size()) {
    size_t end = str.find(';', pos);
    if (end == std::string::npos) end = str.size();
    const std::string item = str.substr(pos, end - pos);
    Step st{};
    if (vector)
      std::sscanf(item.c_str(), "%lf:%lf,%lf,%lf", &st.t, &st.v[0], &st.v[1], &st.v[2]);
    else
      std::sscanf(item.c_str(), "%lf:%d", &st.t, &st.mask);
    out.push_back(st);
    pos = end + 1;
  }
  return out;
}

struct Fault {
  enum Kind { kNone, kDead, kError, kStop, kNan } kind = kNone;
  double at_s = 0;
};
inline Fault parse_fault(const char* s) {
  Fault f;
  if (!s || !*s) return f;
  std::string str(s);
  const size_t at = str.find('@');
  const std::string k = str.substr(0, at);
  if (at != std::string::npos) f.at_s = std::atof(str.c_str() + at + 1);
  if (k == "dead") f.kind = Fault::kDead;
  if (k == "error") f.kind = Fault::kError;
  if (k == "stop") f.kind = Fault::kStop;
  if (k == "nan") f.kind = Fault::kNan;
  return f;
}

// Point mass on a critically damped spring (SI inside; `scale` vendor units per metre on the outside).
struct Mechanism {
  double scale = 1;                 // 1000 for mm
  double mass = 0.1, k = 200, c = 2 * std::sqrt(200 * 0.1);
  double x[3] = {0, 0, 0}, v[3] = {0, 0, 0};
  std::atomic<double> f[3];         // applied force (N), written by the vendor's force calls
  std::vector<Step> path, buttons;
  Fault fault;
  double t0 = 0;                    // monotonic time of open
  double t_sim = 0;                 // simulated up to (s since open)
  int log_fd = -1;

  void open_from_env(double vendor_scale) {
    scale = vendor_scale;
    path = parse_schedule(std::getenv("FAKE_HAPTIC_PATH"), true);
    buttons = parse_schedule(std::getenv("FAKE_HAPTIC_BUTTONS"), false);
    fault = parse_fault(std::getenv("FAKE_HAPTIC_FAULT"));
    if (const char* log = std::getenv("FAKE_HAPTIC_LOG")) log_fd = ::open(log, O_WRONLY | O_CREAT | O_APPEND, 0644);
    for (auto& a : f) a.store(0);
    for (int i = 0; i < 3; ++i) x[i] = path.empty() ? 0 : path[0].v[i] / scale, v[i] = 0;
    t0 = mono_now();
    t_sim = 0;
  }
  double since_open() const { return mono_now() - t0; }
  bool faulted(Fault::Kind k) const { return fault.kind == k && since_open() >= fault.at_s; }
  void rest(double t, double out[3]) const {
    for (int i = 0; i < 3; ++i) out[i] = 0;
    for (const auto& s : path)
      if (s.t <= t)
        for (int i = 0; i < 3; ++i) out[i] = s.v[i] / scale;
  }
  int button_mask() const {
    const double t = since_open();
    int m = 0;
    for (const auto& s : buttons)
      if (s.t <= t) m = s.mask;
    return m;
  }
  // Advances the mass to `now` (s since open) in 0.5 ms substeps.
  void advance_to(double now) {
    const double h = 5e-4;
    if (now - t_sim > 0.5) t_sim = now - 0.5;
    while (t_sim + h <= now) {
      double r[3];
      rest(t_sim, r);
      for (int i = 0; i < 3; ++i) {
        const double a = (f[i].load() - k * (x[i] - r[i]) - c * v[i]) / mass;
        v[i] += h * a;
        x[i] += h * v[i];
      }
      t_sim += h;
    }
  }
  void position(double out[3]) const {
    for (int i = 0; i < 3; ++i) out[i] = faulted(Fault::kNan) ? NAN : x[i] * scale;
  }
  void velocity(double out[3]) const {
    for (int i = 0; i < 3; ++i) out[i] = v[i] * scale;
  }
  // One line to the log with write(2): atomic for short lines, safe from a signal handler.
  void log(const char* event, const double* vals = nullptr, int n = 0) const {
    if (log_fd < 0) return;
    char line[256];
    int len = std::snprintf(line, sizeof line, "%.6f %s", unix_now(), event);
    for (int i = 0; i < n && len < 200; ++i) len += std::snprintf(line + len, sizeof line - len, " %.9g", vals[i]);
    line[len++] = '\n';
    (void)!::write(log_fd, line, len);
  }
};

}  // namespace fake
