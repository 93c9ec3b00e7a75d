#include "haptree/device/convert.hpp"

namespace haptree::device {

void to_lcmt(const DeviceReading& r, int32_t device_id, int64_t utime, lcmt_device_state& m) noexcept {
  m.schema_version = lcmt_device_state::SCHEMA_VERSION;
  m.utime = utime;
  m.seq = r.seq;
  m.device_id = device_id;
  for (int i = 0; i < 3; ++i) {
    m.position_m[i] = r.position_m[i];
    m.linear_velocity_mps[i] = r.linear_velocity_mps[i];
  }
  m.orientation[0] = r.orientation.w();
  m.orientation[1] = r.orientation.x();
  m.orientation[2] = r.orientation.y();
  m.orientation[3] = r.orientation.z();
  m.buttons = r.buttons;
  m.grab_body = r.grab_body;
  m.grab_seq = r.grab_seq;
}

void from_lcmt(const lcmt_device_state& m, DeviceReading& r) noexcept {
  r.time_s = static_cast<double>(m.utime) * 1e-6;
  r.seq = m.seq;
  for (int i = 0; i < 3; ++i) {
    r.position_m[i] = m.position_m[i];
    r.linear_velocity_mps[i] = m.linear_velocity_mps[i];
  }
  r.orientation = Quat(m.orientation[0], m.orientation[1], m.orientation[2], m.orientation[3]);
  r.buttons = m.buttons;
  r.grab_body = m.grab_body;
  r.grab_seq = m.grab_seq;
}

void to_lcmt(const FeedbackCommand& c, int32_t device_id, int64_t seq, int64_t utime, lcmt_feedback& m) noexcept {
  m.schema_version = lcmt_feedback::SCHEMA_VERSION;
  m.utime = utime;
  m.seq = seq;
  m.device_id = device_id;
  m.echo_device_seq = c.echo_device_seq;
  m.snapshot_version = c.snapshot_version;
  m.snapshot_instance_id = c.snapshot_instance;
  m.echo_device_instance_id = c.echo_device_instance;
  for (int i = 0; i < 3; ++i) {
    m.force_n[i] = c.force_n[i];
    m.torque_nm[i] = c.torque_nm[i];
  }
  m.flags = c.flags;
}

void from_lcmt(const lcmt_feedback& m, FeedbackCommand& c) noexcept {
  c.echo_device_seq = m.echo_device_seq;
  c.snapshot_version = m.snapshot_version;
  c.snapshot_instance = m.snapshot_instance_id;
  c.echo_device_instance = m.echo_device_instance_id;
  for (int i = 0; i < 3; ++i) {
    c.force_n[i] = m.force_n[i];
    c.torque_nm[i] = m.torque_nm[i];
  }
  c.flags = m.flags;
}

}  // namespace haptree::device
