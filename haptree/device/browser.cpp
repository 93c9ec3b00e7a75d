#include "haptree/device/browser.hpp"

#include <cmath>

namespace haptree::device {

BrowserDevice::BrowserDevice(const DeviceSpec& spec, const BrowserParams& p, bus::Bus& bus,
                             const std::string& channel, std::unique_ptr<Device> fallback)
    : spec_(spec), p_(p), box_(std::make_shared<bus::LatestValue<lcmt_pointer>>()), fallback_(std::move(fallback)) {
  auto box = box_;   // the bus's callback keeps the mailbox alive
  bus.subscribe<lcmt_pointer>(channel, [box](const lcmt_pointer& m, const std::string&) { box->write(m); });
}

Status BrowserDevice::read(double t, DeviceReading& out) noexcept {
  // Newest pointer message; a non-finite or absurd one is refused (counted), never forwarded.
  if (box_->update()) {
    const lcmt_pointer& m = box_->front();
    const Vec3 x(m.position_m[0], m.position_m[1], m.position_m[2]);
    if (x.allFinite() && x.cwiseAbs().maxCoeff() <= p_.max_abs_m) {
      last_ = m;
      last_time_s_ = t;
    } else {
      ++refused_;
    }
  }
  const bool live = last_time_s_ >= 0 && t - last_time_s_ <= p_.timeout_s;
  const bool page_button = live && (last_.buttons & kButtonGrab) != 0;
  if (page_button) page_owns_ = true;   // the first press takes the user over from the script
  if (!live) page_owns_ = false;        // tab gone: back to the script (if any)
  const bool page = page_owns_ || !fallback_;
  if (page != prev_page_) switch_until_s_ = t + p_.switch_s;
  prev_page_ = page;

  out.time_s = t;
  out.seq = ++seq_;
  out.orientation = Quat::Identity();
  if (!page) {
    const Status s = fallback_->read(t, fb_reading_);
    if (!s.ok()) return s;
    x_ = fb_reading_.position_m;
    out.position_m = x_;
    out.linear_velocity_mps = fb_reading_.linear_velocity_mps;
    out.buttons = t < switch_until_s_ ? 0 : fb_reading_.buttons;
    out.grab_body = fb_reading_.grab_body;
    prev_t_ = t;
    have_pose_ = true;
    prev_button_ = false;
    return Status::Ok();
  }
  if (live) target_ = Vec3(last_.position_m[0], last_.position_m[1], last_.position_m[2]);
  const bool button = page_button && t >= switch_until_s_;
  const double dt = prev_t_ >= 0 ? t - prev_t_ : 0.0;
  const Vec3 x_prev = x_;
  if (button && !prev_button_) ++grab_seq_;
  out.grab_seq = grab_seq_;
  if (!have_pose_ || (button && !prev_button_)) {
    x_ = target_;   // a press grabs exactly the picked point
  } else if (dt > 0) {
    x_ += (target_ - x_) * (1.0 - std::exp(-dt / p_.smoothing_s));
  }
  out.position_m = x_;
  out.linear_velocity_mps = dt > 0 && have_pose_ && !(button && !prev_button_) ? Vec3((x_ - x_prev) / dt) : Vec3::Zero();
  out.buttons = button ? kButtonGrab : 0;
  out.grab_body = button ? last_.grab_body : 0;
  have_pose_ = true;
  prev_button_ = button;
  prev_t_ = t;
  return Status::Ok();
}

Status BrowserDevice::write(const Vec3& force_n, const Vec3& torque_nm) noexcept {
  if (!force_n.allFinite() || !torque_nm.allFinite()) return Status::Error("non-finite force");
  if (fallback_) fallback_->write(force_n, torque_nm);
  return Status::Ok();   // a mouse renders no force: the page shows it (arrow, bar, numbers)
}

}  // namespace haptree::device
