// Device interface (STYLE.md §6): a DeviceSpec published as data (after CHAI3D's cHapticDeviceInfo), and an
// open/read/write/close cycle returning a status with a reason (after ros2_control). read/write are the
// haptic loop's hot path: noexcept, no allocation.
#pragma once

#include <cstdint>
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

constexpr int32_t kButtonGrab = 1;  // bit 0 of DeviceReading::buttons

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

class Device {
 public:
  virtual ~Device() = default;
  virtual const DeviceSpec& spec() const noexcept = 0;
  virtual Status open() { return Status::Ok(); }
  // Fills out with the pose at time_s. Simulated devices are functions of time_s (deterministic);
  // hardware devices read the newest sample and may ignore time_s except to stamp it.
  virtual Status read(double time_s, DeviceReading& out) noexcept = 0;
  // Commands a force (device frame, N) and torque (N m). Non-finite input is refused with kError.
  virtual Status write(const Vec3& force_n, const Vec3& torque_nm) noexcept = 0;
  Status write_force(const Vec3& force_n) noexcept { return write(force_n, Vec3::Zero()); }
  virtual void close() noexcept {}
};

}  // namespace haptree::device
