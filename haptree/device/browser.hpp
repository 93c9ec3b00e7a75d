// The mouse in a web page as a haptic device: the viewer turns the pointer on the page into
// lcmt_pointer messages (device metres) on HAPTREE_POINTER_<device>; this device reads the newest one
// each tick, so the pointer goes through the same coupler, clamp and watchdog as any device.
// Safety: a pointer message with a non-finite or absurd position is dropped (the device holds its last
// good pose); no message for `timeout_s` (closed tab, dropped WebSocket, dead viewer) releases the grab
// button and holds the last pose. A page grab takes the device over from the optional scripted
// fallback (the user's scripted device, running until the page's first press): the grab button is
// held up for `switch_s` at every change of source, so the coupler sees a release and a fresh grab.
#pragma once

#include <memory>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/latest_value.hpp"
#include "haptree/device/device.hpp"
#include "haptree/lcmt_pointer.hpp"

namespace haptree::device {

struct BrowserParams {
  double timeout_s = 0.5;       // no pointer message for this long: released
  double smoothing_s = 0.02;    // first-order filter on the ~60 Hz pointer (the coupler runs at 10 kHz)
  double switch_s = 0.02;       // grab button held up when the source changes
  double max_abs_m = 1e3;       // |position| above this (device metres) is refused as absurd
};

class BrowserDevice final : public Device {
 public:
  // Subscribes to channel on bus (the subscription lives as long as the bus; it writes into a mailbox
  // shared with this device, so either may go first). fallback may be null.
  BrowserDevice(const DeviceSpec& spec, const BrowserParams& p, bus::Bus& bus, const std::string& channel,
                std::unique_ptr<Device> fallback);
  const DeviceSpec& spec() const noexcept override { return spec_; }
  Status read(double time_s, DeviceReading& out) noexcept override;
  Status write(const Vec3& force_n, const Vec3& torque_nm) noexcept override;
  bool page_owns() const noexcept { return page_owns_; }
  int64_t refused() const noexcept { return refused_; }

 private:
  DeviceSpec spec_;
  BrowserParams p_;
  std::shared_ptr<bus::LatestValue<lcmt_pointer>> box_;
  std::unique_ptr<Device> fallback_;
  lcmt_pointer last_{};
  double last_time_s_ = -1;     // time of the newest good pointer message (device clock)
  bool page_owns_ = false;
  bool prev_page_ = false;
  double switch_until_s_ = -1;
  bool have_pose_ = false;
  Vec3 x_ = Vec3::Zero(), target_ = Vec3::Zero();
  double prev_t_ = -1;
  bool prev_button_ = false;
  int64_t seq_ = 0, refused_ = 0;
  int32_t grab_seq_ = 0;
  DeviceReading fb_reading_;
};

}  // namespace haptree::device
