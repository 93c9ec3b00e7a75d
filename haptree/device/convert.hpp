// DeviceReading / feedback command <-> their LCM messages (lcmt_device_state, lcmt_feedback).
#pragma once

#include <cstdint>

#include "haptree/device/device.hpp"
#include "haptree/lcmt_device_state.hpp"
#include "haptree/lcmt_feedback.hpp"

namespace haptree::device {

// What the coupler sends to a device (device units, device frame).
struct FeedbackCommand {
  int64_t echo_device_seq = 0;    // seq of the DeviceReading this answers
  int64_t snapshot_version = -1;  // coupling snapshot it was computed from
  int64_t snapshot_instance = 0;  // instance_id of the server that sent that snapshot (0: none)
  int64_t echo_device_instance = 0;   // instance_id of the device that sent that reading
  Vec3 force_n = Vec3::Zero();
  Vec3 torque_nm = Vec3::Zero();
  int32_t flags = 0;              // lcmt_feedback::FLAG_* (= haptree::SafetyFlag bits)
};

// Sets every field; schema_version from the type, utime as given (bus::now_utime() for live data).
void to_lcmt(const DeviceReading& r, int32_t device_id, int64_t utime, lcmt_device_state& m) noexcept;
// time_s = utime * 1e-6 (seconds since the epoch).
void from_lcmt(const lcmt_device_state& m, DeviceReading& r) noexcept;

void to_lcmt(const FeedbackCommand& c, int32_t device_id, int64_t seq, int64_t utime, lcmt_feedback& m) noexcept;
void from_lcmt(const lcmt_feedback& m, FeedbackCommand& c) noexcept;

}  // namespace haptree::device
