#include "haptree/safety.hpp"

#include <algorithm>
#include <cmath>

namespace haptree {

Vec3 finite_or_zero(const Vec3& v, bool* replaced) noexcept {
  const bool bad = !v.allFinite();
  if (replaced) *replaced = bad;
  return bad ? Vec3::Zero() : v;
}

Vec3 clamp_norm(const Vec3& v, double max_norm, bool* clamped) noexcept {
  if (clamped) *clamped = false;
  if (!v.allFinite() || !(max_norm > 0)) {
    if (clamped) *clamped = v.allFinite() ? !v.isZero(0) : true;
    return Vec3::Zero();
  }
  const double n = v.norm();
  if (n <= max_norm) return v;
  if (clamped) *clamped = true;
  if (!std::isfinite(n)) {   // |v|^2 overflowed (e.g. 1e300): scale first, or the result would be zero
    const Vec3 u = v / v.cwiseAbs().maxCoeff();
    return u * (max_norm / u.norm());
  }
  return v * (max_norm / n);
}

Watchdog::Watchdog(const WatchdogParams& p) noexcept : p_(p) {}

void Watchdog::reset() noexcept {
  gain_ = 0;
  last_now_ = std::numeric_limits<double>::quiet_NaN();
  stale_ = true;
  trips_ = 0;
}

double Watchdog::update(double now_s, double input_age_s) noexcept {
  double dt = 0;
  if (std::isfinite(last_now_) && std::isfinite(now_s) && now_s > last_now_) dt = now_s - last_now_;
  if (std::isfinite(now_s) && !(std::isfinite(last_now_) && now_s < last_now_)) last_now_ = now_s;
  const bool stale = !(std::isfinite(input_age_s) && input_age_s >= 0 && input_age_s <= p_.stale_after_s);
  if (stale && !stale_) ++trips_;
  stale_ = stale;
  if (stale) {
    gain_ = p_.ramp_down_s > 0 ? std::max(0.0, gain_ - dt / p_.ramp_down_s) : 0.0;
  } else {
    // The first fresh call after construction has dt = 0: the gain starts rising from the next call.
    gain_ = p_.ramp_up_s > 0 ? std::min(1.0, gain_ + dt / p_.ramp_up_s) : 1.0;
  }
  return gain_;
}

ForceSafety::ForceSafety(const ForceLimits& limits, const WatchdogParams& watchdog) noexcept
    : limits_(limits), watchdog_(watchdog) {}

GuardedForce ForceSafety::apply(double now_s, double input_age_s, const Vec3& force, const Vec3& torque) noexcept {
  GuardedForce out;
  bool bad_f = false, bad_t = false;
  Vec3 f = finite_or_zero(force, &bad_f);
  Vec3 t = finite_or_zero(torque, &bad_t);
  if (bad_f || bad_t) {
    out.flags |= kSafetyNonFinite;
    ++nonfinite_events_;
  }
  // Clamp first, then the gain: the ramps then scale what the device feels, so they take at least
  // ramp_down_s from the clamp to zero. (Gain first let a force far above the clamp stay clamped until the
  // gain was small and then drop to zero within a fraction of the ramp: a step at the hand.)
  bool cf = false, ct = false;
  f = clamp_norm(f, limits_.max_force, &cf);
  t = clamp_norm(t, limits_.max_torque, &ct);
  if (cf || ct) {
    out.flags |= kSafetyClamped;
    ++clamp_events_;
  }
  const double g = watchdog_.update(now_s, input_age_s);
  if (watchdog_.stale()) out.flags |= kSafetyStale;
  if (g < 1.0) out.flags |= kSafetyWatchdog;
  out.force = g * f;
  out.torque = g * t;
  return out;
}

const Vec3& FeedbackRenderer::render(double now_s, double feedback_age_s, const Vec3& feedback) noexcept {
  const double g = watchdog_.update(now_s, feedback_age_s);
  const Vec3 target = g * clamp_norm(finite_or_zero(feedback), max_force_);
  const Vec3 d = target - rendered_;
  const double n = d.norm();
  const Vec3 f = n <= max_step_ ? target : Vec3(rendered_ + d * (max_step_ / n));
  max_step_seen_ = std::max(max_step_seen_, (f - rendered_).norm());
  rendered_ = f;
  return rendered_;
}

bool FeedbackRenderer::ramp_down() noexcept {
  rendered_ -= clamp_norm(rendered_, max_step_);
  return rendered_.norm() > 0;
}

void PassivityObserver::add_power(double power, double dt) noexcept {
  if (!std::isfinite(power) || !std::isfinite(dt) || dt < 0) {
    ++ignored_;
    return;
  }
  const double e = power * dt;
  if (e >= 0) in_ += e;
  else out_ -= e;
  min_ = std::min(min_, energy());
}

void PassivityObserver::add(const Vec3& f, const Vec3& v, double dt) noexcept { add_power(f.dot(v), dt); }

double PassivityObserver::suggested_damping(const Vec3& v, double dt) const noexcept {
  const double e = energy();
  const double vv = v.squaredNorm() * dt;
  if (e >= 0 || !(vv > 0)) return 0;
  return -e / vv;
}

}  // namespace haptree
