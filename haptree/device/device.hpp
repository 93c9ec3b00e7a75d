// Device interface: a DeviceSpec published as data (after CHAI3D's cHapticDeviceInfo), and an
// open/read/write/close cycle returning a status with a reason (after ros2_control). read/write are the
// haptic loop's hot path: noexcept, no allocation.
#pragma once

#include <cstdint>
#include <limits>
#include <string>

#include "haptree/spatial.hpp"

namespace haptree::device {

// What a device can do, as data: the coupler's clamp, stiffness limit and workspace mapping read from here.
struct DeviceSpec {
  std::string name = "device";
  double max_force_n = 3.0;                // continuous force limit
  double max_torque_nm = 0.0;              // 0: the device renders no torque
  double workspace_radius_m = 0.08;        // reachable sphere around the origin of the device frame
  double max_stiffness_n_per_m = 1000.0;   // largest closed-loop stiffness it renders stably
  double rate_hz = 1000.0;                 // native servo rate
};

constexpr int32_t kButtonGrab = 1;    // bit 0 of DeviceReading::buttons: grab / release
constexpr int32_t kButtonClutch = 2;  // bit 1: clutch (indexing); device_bridge applies it for every kind

// What a device says about itself once open (a real device's own model and nominal limits), for
// `device_bridge --probe` and the gain checks. NaN = not reported: the --device-model table is the fallback.
struct DeviceDescription {
  static constexpr double kNotReported = std::numeric_limits<double>::quiet_NaN();
  std::string model;                               // the vendor's model name; "" if not reported
  std::string serial;                              // "" if the device has none or does not report it
  double max_force_n = kNotReported;               // nominal peak force
  double max_continuous_force_n = kNotReported;    // nominal sustained force
  double max_torque_nm = kNotReported;             // 0: no actuated rotation
  double max_stiffness_n_per_m = kNotReported;     // nominal largest stable stiffness
  double max_damping_n_s_per_m = kNotReported;     // nominal largest stable damping
  double workspace_radius_m = kNotReported;
  int buttons = 0;                                 // number of buttons; 0: none or not reported
  bool orientation = false;                        // reports a measured orientation
  bool torque = false;                             // renders torque (write()'s torque_nm is applied)
  std::string axes;                                // vendor axes -> haptree device frame ("y,z,x"; "" = none)
};

struct DeviceReading {
  double time_s = 0;                           // time of the reading (the clock passed to read())
  int64_t seq = 0;                             // +1 per successful read
  Vec3 position_m = Vec3::Zero();              // device frame
  Quat orientation = Quat::Identity();
  Vec3 linear_velocity_mps = Vec3::Zero();
  int32_t buttons = 0;                         // bit i = button i; kButtonGrab = grab
  int32_t grab_body = 0;                       // > 0: body picked on screen (browser device); 0: coupler picks
  int32_t grab_seq = 0;                        // +1 per press (browser device): a change = a new grab
};

// ros2_control's three outcomes: go on, failed (reason), or stop using this device (reason).
enum class StatusCode { kOk = 0, kError = 1, kDeactivate = 2 };

struct Status {
  StatusCode code = StatusCode::kOk;
  const char* reason = "";  // static string: no allocation on the hot path
  bool ok() const noexcept { return code == StatusCode::kOk; }
  static Status Ok() noexcept { return {}; }
  static Status Error(const char* why) noexcept { return {StatusCode::kError, why}; }
  static Status Deactivate(const char* why) noexcept { return {StatusCode::kDeactivate, why}; }
};

// Frames: a device reports and takes vectors in haptree's device frame (metres, newtons, N m): x to the
// user's right, y up, z towards the user (out of the screen), as the view's. A real device maps its
// vendor's axes onto it (AxisMap, option axes=).
//
// Life cycle of a real device: open() (force output OFF), read()/write() at the loop's rate,
// enable_force(true) once the first valid FEEDBACK is in, close(). close() writes zero force and
// torque, turns force output off, and releases the device; it is idempotent and also runs from the
// destructor, so an exception or an early return never leaves a force on.
class Device {
 public:
  virtual ~Device() = default;
  virtual const DeviceSpec& spec() const noexcept = 0;
  // Throws nothing; a failure (library or device missing) comes back as kError with a one-line reason.
  virtual Status open() { return Status::Ok(); }
  // Valid after open(). Simulated devices report nothing (every limit NaN).
  virtual DeviceDescription describe() const { return {}; }
  // Turns the device's force output on or off. A device opens with it off; writes before it is on are
  // not rendered. Devices without motors accept and ignore it.
  virtual Status enable_force(bool on) noexcept {
    (void)on;
    return Status::Ok();
  }
  // Fills out with the pose at time_s. Simulated devices are functions of time_s (deterministic);
  // hardware devices read the newest sample and may ignore time_s except to stamp it.
  virtual Status read(double time_s, DeviceReading& out) noexcept = 0;
  // Commands a force (device frame, N) and torque (N m; ignored by devices without actuated rotations).
  // Non-finite input is refused with kError. A kError/kDeactivate from read or write is a fault: the
  // caller writes zero, disables and closes.
  virtual Status write(const Vec3& force_n, const Vec3& torque_nm) noexcept = 0;
  Status write_force(const Vec3& force_n) noexcept { return write(force_n, Vec3::Zero()); }
  virtual void close() noexcept {}
};

}  // namespace haptree::device
