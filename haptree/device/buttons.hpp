// The two buttons every device shares, applied once after any device's read() (device_bridge does it for
// every kind): button 0 grabs and releases (the coupler picks the body on the press; grab_seq counts the
// presses so that a release lost between two latest-value mailboxes is still seen as a new grab), button
// 1 is the clutch (indexing): while it is held the device moves and the proxy it drives stays where it
// was; on release the proxy follows the device again from there, so a small workspace reaches a large
// scene. Orientation is not clutched.
#pragma once

#include <cstdint>

#include "haptree/device/device.hpp"

namespace haptree::device {

class ButtonStage {
 public:
  // Rewrites r in place: position = device position + offset (frozen at the press while clutched),
  // velocity zero while clutched, grab_seq = presses of button 0 counted here when the device counts none.
  void apply(DeviceReading& r) noexcept;
  bool clutched() const noexcept { return clutched_; }
  const Vec3& offset() const noexcept { return offset_; }   // proxy - device position (m)
  int32_t presses() const noexcept { return presses_; }

 private:
  bool clutched_ = false, grab_prev_ = false;
  Vec3 offset_ = Vec3::Zero(), held_ = Vec3::Zero();
  int32_t presses_ = 0;
};

}  // namespace haptree::device
