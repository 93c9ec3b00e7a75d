#include "haptree/device/buttons.hpp"

namespace haptree::device {

void ButtonStage::apply(DeviceReading& r) noexcept {
  const bool grab = (r.buttons & kButtonGrab) != 0;
  if (grab && !grab_prev_) ++presses_;
  grab_prev_ = grab;
  if (r.grab_seq == 0) r.grab_seq = presses_;
  const bool clutch = (r.buttons & kButtonClutch) != 0;
  if (clutch && !clutched_) held_ = r.position_m + offset_;   // where the proxy stays
  clutched_ = clutch;
  if (clutched_) {
    offset_ = held_ - r.position_m;
    r.linear_velocity_mps.setZero();
    r.position_m = held_;   // exactly where it was, not device + offset rounded
    return;
  }
  r.position_m += offset_;
}

}  // namespace haptree::device
