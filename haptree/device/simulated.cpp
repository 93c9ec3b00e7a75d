#include "haptree/device/simulated.hpp"

#include <cmath>
#include <stdexcept>

#include "haptree/safety.hpp"

namespace haptree::device {

ScriptedDevice::ScriptedDevice(const DeviceSpec& spec, Trajectory script)
    : spec_(spec), script_(std::move(script)) {}

Status ScriptedDevice::read(double t, DeviceReading& out) noexcept {
  if (!std::isfinite(t)) return Status::Error("ScriptedDevice::read: time is not finite");
  out.time_s = t;
  out.seq = ++seq_;
  out.position_m = script_.position(t);
  out.orientation = Quat::Identity();
  out.linear_velocity_mps = script_.velocity(t);
  out.buttons = script_.buttons(t);
  return Status::Ok();
}

Status ScriptedDevice::write(const Vec3& f, const Vec3& tau) noexcept {
  if (!f.allFinite() || !tau.allFinite()) return Status::Error("ScriptedDevice::write: non-finite force");
  force_ = f;
  return Status::Ok();
}

VirtualHand::VirtualHand(const DeviceSpec& spec, const VirtualHandParams& params, Trajectory target)
    : spec_(spec), p_(params), target_(std::move(target)), x_(target_.position(0)) {
  if (!(p_.mass_kg > 0) || !(p_.stiffness_n_per_m >= 0) || !(p_.damping_n_s_per_m >= 0) ||
      !(p_.max_substep_s > 0))
    throw std::invalid_argument("VirtualHand: mass and substep must be > 0, stiffness and damping >= 0");
}

Status VirtualHand::read(double t, DeviceReading& out) noexcept {
  if (!std::isfinite(t)) return Status::Error("VirtualHand::read: time is not finite");
  if (!started_) {
    started_ = true;
    t_ = t;
    x_ = target_.position(t);
    v_ = target_.velocity(t);
  }
  if (t > t_) {
    const double span = t - t_;
    const int n = static_cast<int>(std::ceil(span / p_.max_substep_s));
    const double h = span / n;
    for (int i = 0; i < n; ++i) {
      const double ti = t_ + (i + 1) * h;
      const Vec3 a = (p_.stiffness_n_per_m * (target_.position(ti) - x_) +
                      p_.damping_n_s_per_m * (target_.velocity(ti) - v_) + f_) /
                     p_.mass_kg;
      v_ += h * a;  // semi-implicit Euler: velocity first, then position with the new velocity
      x_ += h * v_;
    }
    t_ = t;
  }
  if (!x_.allFinite() || !v_.allFinite()) return Status::Error("VirtualHand: state became non-finite");
  out.time_s = t;
  out.seq = ++seq_;
  out.position_m = x_;
  out.orientation = Quat::Identity();
  out.linear_velocity_mps = v_;
  out.buttons = target_.buttons(t);
  return Status::Ok();
}

Status VirtualHand::write(const Vec3& f, const Vec3& tau) noexcept {
  if (!f.allFinite() || !tau.allFinite()) return Status::Error("VirtualHand::write: non-finite force");
  f_ = clamp_norm(f, spec_.max_force_n);
  return Status::Ok();
}

}  // namespace haptree::device
