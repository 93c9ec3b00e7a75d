// A fake Force Dimension DHD library (libdhd.so.3) for tests without the hardware: the same C symbols
// (the device ID, a char, last) with the documented semantics (m, m/s, N, N m; -1 on error with
// dhdErrorGetLastStr; dhdSetForce* returning DHD_MOTOR_SATURATED above the device's force) on the
// mechanism of fake_common.hpp, advanced on every call. Values written from the public listings of the
// DHD API (docs/devices.md), independently of the driver's own declarations.
#include <mutex>

#include "tests/device/fakes/fake_common.hpp"

namespace {

fake::Mechanism g_mech;
std::recursive_mutex g_mutex;   // DHD calls come from the device loop and, on a crash, a signal handler
bool g_open = false, g_force_on = false;
int g_type = 33;                // DHD_DEVICE_OMEGA3
const char* g_last_error = "no error";
constexpr double kMaxForce = 12.0;   // omega.3

// Reads fail from the fault's time on (error@T); force, enable and close calls still reach the device.
bool check(char id, bool read = false) {
  if (!g_open || id != 0) {
    g_last_error = "invalid device ID (fake)";
    return false;
  }
  if (read && g_mech.faulted(fake::Fault::kError)) {
    g_last_error = "communication error: device not responding (fake)";
    const double code = 2;
    g_mech.log("error", &code, 1);
    return false;
  }
  g_mech.advance_to(g_mech.since_open());
  return true;
}

int set(double fx, double fy, double fz, double tx, double ty, double tz, char id) {
  if (!check(id)) return -1;
  const double l[6] = {fx, fy, fz, tx, ty, tz};
  g_mech.log(g_force_on ? "force" : "force_off", l, 6);
  const double n = std::sqrt(fx * fx + fy * fy + fz * fz);
  const double s = g_force_on ? (n > kMaxForce ? kMaxForce / n : 1.0) : 0.0;
  g_mech.f[0].store(s * fx);
  g_mech.f[1].store(s * fy);
  g_mech.f[2].store(s * fz);
  return n > kMaxForce ? 2 : 0;   // DHD_MOTOR_SATURATED
}

}  // namespace

extern "C" {

int dhdGetDeviceCount() {
  const char* f = std::getenv("FAKE_HAPTIC_FAULT");
  return f && std::strncmp(f, "dead", 4) == 0 ? 0 : 1;
}

int dhdOpen() {
  std::lock_guard<std::recursive_mutex> lock(g_mutex);
  g_mech.open_from_env(1.0);   // m
  const char* type = std::getenv("FAKE_HAPTIC_TYPE");
  g_type = type ? std::atoi(type) : 33;
  if (g_mech.fault.kind == fake::Fault::kDead) {
    g_last_error = "no device found (fake)";
    return -1;
  }
  g_open = true;
  g_force_on = true;   // the SDK opens with forces enabled
  g_mech.log("open");
  return 0;
}
int dhdOpenID(char id) {
  if (id != 0) {
    g_last_error = "no device with this ID (fake)";
    return -1;
  }
  return dhdOpen();
}
int dhdClose(char id) {
  std::lock_guard<std::recursive_mutex> lock(g_mutex);
  if (!g_open || id != 0) return -1;
  g_open = false;
  g_mech.log("close");
  return 0;
}

int dhdGetSystemType(char id) { return g_open && id == 0 ? g_type : -1; }
const char* dhdGetSystemName(char id) {
  if (!g_open || id != 0) return nullptr;
  switch (g_type) {
    case 33: return "omega.3 (fake)";
    case 104: return "sigma.7 (fake)";
    case 60: return "Falcon (fake)";
    default: return "Force Dimension device (fake)";
  }
}
int dhdGetSerialNumber(unsigned short* sn, char id) {
  if (!g_open || id != 0) return -1;
  *sn = 4242;
  return 0;
}
const char* dhdErrorGetLastStr() { return g_last_error; }
int dhdErrorGetLast() { return 0; }

int dhdEnableForce(unsigned char on, char id) {
  std::lock_guard<std::recursive_mutex> lock(g_mutex);
  if (!check(id)) return -1;
  g_force_on = on != 0;   // DHD_ON = 1, DHD_OFF = 0
  g_mech.log(g_force_on ? "enable" : "disable");
  if (!g_force_on)
    for (auto& f : g_mech.f) f.store(0);
  return 0;
}

int dhdGetPosition(double* x, double* y, double* z, char id) {
  std::lock_guard<std::recursive_mutex> lock(g_mutex);
  if (!check(id, true)) return -1;
  double p[3];
  g_mech.position(p);
  *x = p[0], *y = p[1], *z = p[2];
  return 0;
}
int dhdGetLinearVelocity(double* x, double* y, double* z, char id) {
  std::lock_guard<std::recursive_mutex> lock(g_mutex);
  if (!check(id, true)) return -1;
  double v[3];
  g_mech.velocity(v);
  *x = v[0], *y = v[1], *z = v[2];
  return 0;
}
int dhdGetOrientationFrame(double m[3][3], char id) {
  std::lock_guard<std::recursive_mutex> lock(g_mutex);
  if (!check(id)) return -1;
  // A quarter turn about the vendor's vertical (z), rows of the rotation matrix.
  const double R[3][3] = {{0, -1, 0}, {1, 0, 0}, {0, 0, 1}};
  std::memcpy(m, R, sizeof R);
  return 0;
}
int dhdGetButton(int index, char id) {
  std::lock_guard<std::recursive_mutex> lock(g_mutex);
  if (!check(id, true) || index < 0 || index > 31) return -1;
  return (g_mech.button_mask() >> index) & 1;   // DHD_ON / DHD_OFF
}
unsigned int dhdGetButtonMask(char id) {
  std::lock_guard<std::recursive_mutex> lock(g_mutex);
  return check(id) ? static_cast<unsigned int>(g_mech.button_mask()) : 0u;
}
int dhdSetForce(double fx, double fy, double fz, char id) {
  std::lock_guard<std::recursive_mutex> lock(g_mutex);
  return set(fx, fy, fz, 0, 0, 0, id);
}
int dhdSetForceAndTorque(double fx, double fy, double fz, double tx, double ty, double tz, char id) {
  std::lock_guard<std::recursive_mutex> lock(g_mutex);
  return set(fx, fy, fz, tx, ty, tz, id);
}

}  // extern "C"
