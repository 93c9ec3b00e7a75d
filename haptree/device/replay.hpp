// ReplayDevice: device poses read from an LCM log file (lcm-logger output) on one channel.
#pragma once

#include <string>
#include <vector>

#include "haptree/device/device.hpp"

namespace haptree::device {

class ReplayDevice final : public Device {
 public:
  // Loads every lcmt_device_state on `channel` (exact name) from the log. Sample times are the messages'
  // utime relative to the first one. Throws std::runtime_error naming the file (cannot open, no message
  // on the channel, undecodable messages are counted in rejected(), not thrown).
  ReplayDevice(const DeviceSpec& spec, const std::string& log_path, const std::string& channel,
               bool loop = false);
  const DeviceSpec& spec() const noexcept override { return spec_; }
  // The newest logged sample at or before time_s (relative to the log's first sample). After the end:
  // the last sample and kDeactivate("replay finished"), unless looping.
  Status read(double time_s, DeviceReading& out) noexcept override;
  Status write(const Vec3& force_n, const Vec3& torque_nm) noexcept override;
  double duration() const noexcept { return samples_.empty() ? 0.0 : samples_.back().time_s; }
  size_t size() const noexcept { return samples_.size(); }
  int64_t rejected() const noexcept { return rejected_; }
  const std::vector<DeviceReading>& samples() const noexcept { return samples_; }  // time_s relative
  const Vec3& last_force() const noexcept { return force_; }

 private:
  DeviceSpec spec_;
  std::vector<DeviceReading> samples_;
  bool loop_;
  int64_t rejected_ = 0;
  size_t cursor_ = 0;
  int64_t seq_ = 0;
  Vec3 force_ = Vec3::Zero();
};

}  // namespace haptree::device
