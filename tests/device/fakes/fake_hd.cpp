// A fake OpenHaptics HD library (libHD.so) for tests without the hardware: the same C symbols with the
// documented semantics (mm, mm/s, N, mN m; a column-major HD_CURRENT_TRANSFORM; a scheduler thread
// calling the asynchronous callbacks at ~1 kHz inside frames; hdGetError by value, HD_INVALID_ENUM for a
// parameter it does not know) on the mechanism of fake_common.hpp. Values written from the public
// listings of the HD API (docs/devices.md), independently of the driver's own declarations.
// Built with FAKE_HD_OMIT_ASYNC, hdScheduleAsynchronous is missing (a library of the wrong kind).
#include <pthread.h>

#include <thread>

#include "tests/device/fakes/fake_common.hpp"

namespace {

struct ErrorInfo {
  unsigned int errorCode;
  int internalErrorCode;
  unsigned int hHD;
};
using Callback = unsigned int (*)(void*);

fake::Mechanism g_mech;
std::atomic<unsigned int> g_error{0};
std::atomic<bool> g_force_output{true};   // HD devices start with force output enabled
std::atomic<bool> g_running{false};
std::atomic<bool> g_initialized{false};
std::thread g_thread;
struct Scheduled {
  std::atomic<Callback> fn{nullptr};
  void* data = nullptr;
};
Scheduled g_cb[4];
double g_force[3] = {0, 0, 0}, g_torque[3] = {0, 0, 0};
int g_dof = 3;
double g_max_force = 3.3;   // HD_NOMINAL_MAX_FORCE (N)
// hdCheckCalibration's answer: HD_CALIBRATION_OK, _NEEDS_UPDATE (until hdUpdateCalibration with the
// device's style, HD_CALIBRATION_AUTO) or _NEEDS_MANUAL_INPUT (never cleared: nobody puts the stylus in).
std::atomic<unsigned int> g_calibration{0x5000};

void set_error(unsigned int code) {
  unsigned int expected = 0;
  g_error.compare_exchange_strong(expected, code);   // the first error sticks until read
}

void scheduler() {
  double next = fake::mono_now();
  while (g_running.load()) {
    next += 1e-3;
    g_mech.advance_to(g_mech.since_open());
    if (!g_mech.faulted(fake::Fault::kStop))
      for (auto& s : g_cb) {
        const Callback fn = s.fn.load();
        if (fn && fn(s.data) == 0) s.fn.store(nullptr);   // HD_CALLBACK_DONE
      }
    const double wait = next - fake::mono_now();
    if (wait > 0) {
      timespec ts{0, static_cast<long>(wait * 1e9)};
      nanosleep(&ts, nullptr);
    } else if (wait < -0.05) {
      next = fake::mono_now();
    }
  }
}

}  // namespace

extern "C" {

unsigned int hdInitDevice(const char* name) {
  g_mech.open_from_env(1000.0);   // mm
  const char* dof = std::getenv("FAKE_HAPTIC_DOF");
  g_dof = dof ? std::atoi(dof) : 3;
  const char* fmax = std::getenv("FAKE_HAPTIC_MAX_FORCE");
  g_max_force = fmax ? std::atof(fmax) : 3.3;
  const char* cal = std::getenv("FAKE_HAPTIC_CALIBRATION");
  g_calibration = !cal ? 0x5000 : std::strcmp(cal, "manual") == 0 ? 0x5002 : std::strcmp(cal, "update") == 0 ? 0x5001 : 0x5000;
  if (g_mech.fault.kind == fake::Fault::kDead || (name && std::strcmp(name, "no such device") == 0)) {
    set_error(0x0302);   // HD_COMM_ERROR
    return 0xFFFFFFFFu;  // HD_INVALID_HANDLE
  }
  g_initialized = true;
  g_force_output = true;
  g_mech.log("open");
  return 1;
}

void hdDisableDevice(unsigned int) {
  g_mech.log("close");
  g_initialized = false;
}
void hdMakeCurrentDevice(unsigned int) {}
unsigned int hdGetCurrentDevice() { return 1; }
void hdBeginFrame(unsigned int) {}
void hdEndFrame(unsigned int) {
  if (g_mech.faulted(fake::Fault::kError)) set_error(0x0302);   // HD_COMM_ERROR
  for (int i = 0; i < 3; ++i) g_mech.f[i].store(g_force_output.load() ? g_force[i] : 0.0);
}

void hdEnable(unsigned int cap) {
  if (cap != 0x4000) return set_error(0x0100);   // HD_FORCE_OUTPUT; else HD_INVALID_ENUM
  g_force_output = true;
  g_mech.log("enable");
}
void hdDisable(unsigned int cap) {
  if (cap != 0x4000) return set_error(0x0100);
  g_force_output = false;
  g_mech.log("disable");
}

void hdGetDoublev(unsigned int what, double* v) {
  switch (what) {
    case 0x2050: g_mech.position(v); break;                      // HD_CURRENT_POSITION (mm)
    case 0x2051: g_mech.velocity(v); break;                      // HD_CURRENT_VELOCITY (mm/s)
    case 0x2052: {                                               // HD_CURRENT_TRANSFORM, column-major
      // A stylus turned 90 degrees about the vertical (y): columns are the stylus axes in the base frame.
      const double R[9] = {0, 0, -1, 0, 1, 0, 1, 0, 0};         // R(r, c) = R[c * 3 + r]
      for (int c = 0; c < 3; ++c) {
        for (int r = 0; r < 3; ++r) v[c * 4 + r] = R[c * 3 + r];
        v[c * 4 + 3] = 0;
      }
      g_mech.position(v + 12);
      v[15] = 1;
      break;
    }
    case 0x2603: *v = g_max_force; break;   // HD_NOMINAL_MAX_FORCE (N)
    case 0x2604: *v = 0.88; break;    // HD_NOMINAL_MAX_CONTINUOUS_FORCE (N)
    case 0x2602: *v = 0.4; break;     // HD_NOMINAL_MAX_STIFFNESS (N/mm)
    case 0x2609: *v = 0.004; break;   // HD_NOMINAL_MAX_DAMPING (N s/mm)
    case 0x2551: {                    // HD_USABLE_WORKSPACE_DIMENSIONS (mm)
      const double ws[6] = {-80, -60, -35, 80, 60, 35};
      std::memcpy(v, ws, sizeof ws);
      break;
    }
    case 0x2700: std::memcpy(v, g_force, sizeof g_force); break;   // HD_CURRENT_FORCE
    default: set_error(0x0100);       // HD_INVALID_ENUM
  }
}

void hdGetIntegerv(unsigned int what, int* v) {
  switch (what) {
    case 0x2000: *v = g_mech.button_mask(); break;   // HD_CURRENT_BUTTONS
    case 0x2554: *v = g_dof; break;                  // HD_OUTPUT_DOF
    case 0x2553: *v = 6; break;                      // HD_INPUT_DOF
    case 0x2555: *v = 1 << 1; break;                 // HD_CALIBRATION_STYLE: HD_CALIBRATION_AUTO
    default: set_error(0x0100);
  }
}

void hdSetDoublev(unsigned int what, const double* v) {
  if (what == 0x2700) {   // HD_CURRENT_FORCE (N)
    std::memcpy(g_force, v, sizeof g_force);
    const double l[6] = {v[0], v[1], v[2], g_torque[0], g_torque[1], g_torque[2]};
    g_mech.log(g_force_output.load() ? "force" : "force_off", l, 6);
    return;
  }
  if (what == 0x2701 && g_dof >= 6) {   // HD_CURRENT_TORQUE (mN m)
    std::memcpy(g_torque, v, sizeof g_torque);
    const double l[6] = {g_force[0], g_force[1], g_force[2], v[0], v[1], v[2]};
    g_mech.log(g_force_output.load() ? "force" : "force_off", l, 6);
    return;
  }
  set_error(0x0100);
}

const char* hdGetString(unsigned int what) {
  switch (what) {
    case 0x2501: return "Touch (fake)";   // HD_DEVICE_MODEL_TYPE
    case 0x2504: return "FAKE-0001";      // HD_DEVICE_SERIAL_NUMBER
    case 0x2503: return "haptree tests";  // HD_DEVICE_VENDOR
    default: set_error(0x0100); return nullptr;
  }
}

ErrorInfo hdGetError() {
  const unsigned int e = g_error.exchange(0);
  if (e) {
    const double code = e;
    g_mech.log("error", &code, 1);
  }
  return ErrorInfo{e, e ? -7 : 0, 1};
}

const char* hdGetErrorString(unsigned int code) {
  switch (code) {
    case 0: return "no error";
    case 0x0100: return "invalid enum (fake)";
    case 0x0302: return "communication error (fake)";
    default: return "error (fake)";
  }
}

void hdStartScheduler() {
  if (g_running.exchange(true)) return;
  g_thread = std::thread(scheduler);
}
void hdStopScheduler() {
  if (!g_running.exchange(false)) return;
  if (g_thread.joinable() && g_thread.get_id() != std::this_thread::get_id()) g_thread.join();
}

#ifndef FAKE_HD_OMIT_ASYNC
unsigned long hdScheduleAsynchronous(Callback fn, void* data, unsigned short) {
  for (unsigned long i = 0; i < 4; ++i)
    if (!g_cb[i].fn.load()) {
      g_cb[i].data = data;
      g_cb[i].fn.store(fn);
      return i + 1;
    }
  set_error(0x0501);   // HD_SCHEDULER_FULL
  return 0;
}
#endif
void hdUnschedule(unsigned long h) {
  if (h >= 1 && h <= 4) g_cb[h - 1].fn.store(nullptr);
}

unsigned int hdCheckCalibration() { return g_calibration.load(); }
void hdUpdateCalibration(unsigned int style) {
  const double s = style;
  g_mech.log("calibrate", &s, 1);
  if (style != (1 << 1)) return set_error(0x0100);   // the fake's only style is HD_CALIBRATION_AUTO
  unsigned int needs = 0x5001;
  g_calibration.compare_exchange_strong(needs, 0x5000);
}

}  // extern "C"
