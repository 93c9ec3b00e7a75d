/// @file
/// Safety layer between the coupling and a device (docs/security.md): NaN/Inf guard, force clamp,
/// staleness watchdog with linear ramps, and a Ryu–Hannaford passivity observer reported as telemetry.
/// Eigen only; everything is noexcept and allocation-free (it runs inside the 10 kHz coupler loop).
/// Times are seconds of whatever clock the caller uses (simulated time in tests, steady clock in the coupler).
#pragma once

#include <cstdint>
#include <limits>

#include "haptree/spatial.hpp"

namespace haptree {

/// Bits of the `flags` of a guarded force; the same values as lcmt_feedback::FLAG_*.
enum SafetyFlag : int32_t {
  kSafetyClamped = 1,    ///< the norm was limited
  kSafetyWatchdog = 2,   ///< the watchdog gain was below 1 (ramping down, at zero, or ramping back up)
  kSafetyStale = 4,      ///< the inputs were stale at this call
  kSafetyNonFinite = 8,  ///< a NaN/Inf was replaced by zero
};

/// Whether every entry of v is finite.
template <class Derived>
bool all_finite(const Eigen::MatrixBase<Derived>& v) noexcept {
  return v.allFinite();
}
/// v if every entry is finite, otherwise zero (and *replaced = true).
Vec3 finite_or_zero(const Vec3& v, bool* replaced = nullptr) noexcept;
/// v scaled down to norm max_norm if it is longer (*clamped = true). max_norm <= 0 or NaN gives zero;
/// a non-finite v gives zero (clamping cannot make NaN safe).
Vec3 clamp_norm(const Vec3& v, double max_norm, bool* clamped = nullptr) noexcept;

/// Times of a Watchdog, s.
struct WatchdogParams {
  double stale_after_s = 0.005;  ///< an input older than this is stale
  double ramp_down_s = 0.005;    ///< time from full force to zero once stale
  double ramp_up_s = 0.100;      ///< time from zero back to full force once fresh again
};

/// Gain in [0, 1] that falls linearly to 0 within ramp_down_s after the inputs go stale and rises linearly
/// back to 1 over ramp_up_s once they are fresh. Starts at 0 (no force before the first fresh input), so
/// a coupler ramps in gently. Full force is therefore gone at most stale_after_s + ramp_down_s after the
/// last fresh input (plus one call interval).
class Watchdog {
 public:
  explicit Watchdog(const WatchdogParams& p = WatchdogParams{}) noexcept;   ///< starts stale, gain 0
  /// input_age_s: age of the oldest input the force depends on; NaN, Inf or negative count as stale.
  /// Returns the gain to apply at now_s. Calls must have non-decreasing now_s (earlier ones act as dt = 0).
  double update(double now_s, double input_age_s) noexcept;
  double gain() const noexcept { return gain_; }                 ///< the last gain returned
  bool stale() const noexcept { return stale_; }                 ///< whether the last input was stale
  int64_t trips() const noexcept { return trips_; }              ///< fresh → stale transitions
  const WatchdogParams& params() const noexcept { return p_; }   ///< the times it was made with
  void reset() noexcept;                                         ///< back to the initial state (stale, gain 0)

 private:
  WatchdogParams p_;
  double gain_ = 0, last_now_ = std::numeric_limits<double>::quiet_NaN();
  bool stale_ = true;
  int64_t trips_ = 0;
};

/// Limits of the force a device renders.
struct ForceLimits {
  double max_force = std::numeric_limits<double>::infinity();   ///< device units (N)
  double max_torque = std::numeric_limits<double>::infinity();  ///< device units (N m)
};

/// What ForceSafety::apply returns: the force to render and what was done to it.
struct GuardedForce {
  Vec3 force = Vec3::Zero();    ///< device units (N)
  Vec3 torque = Vec3::Zero();   ///< device units (N m)
  int32_t flags = 0;  ///< SafetyFlag bits
};

/// The whole chain in the order the coupler needs it: non-finite -> zero, clamp, times the watchdog gain
/// (in [0, 1], so the result stays within the limits, and a ramp takes the felt force from the clamp to zero
/// in no less than ramp_down_s). Whatever goes in, what comes out is finite and within the limits.
class ForceSafety {
 public:
  ForceSafety(const ForceLimits& limits, const WatchdogParams& watchdog) noexcept;   ///< watchdog starts stale
  /// The guarded force at now_s for inputs of age input_age_s (see the class description).
  GuardedForce apply(double now_s, double input_age_s, const Vec3& force, const Vec3& torque) noexcept;
  const Watchdog& watchdog() const noexcept { return watchdog_; }        ///< its watchdog
  const ForceLimits& limits() const noexcept { return limits_; }         ///< its limits
  int64_t clamp_events() const noexcept { return clamp_events_; }        ///< calls that clamped
  int64_t nonfinite_events() const noexcept { return nonfinite_events_; }   ///< calls that replaced NaN/Inf

 private:
  ForceLimits limits_;
  Watchdog watchdog_;
  int64_t clamp_events_ = 0, nonfinite_events_ = 0;
};

/// What a device renders each tick from the latest FEEDBACK: NaN -> 0, clamped, times the device's own
/// watchdog gain on the feedback's age (stale: ramp to zero; fresh again: ramp back in), and never changing by
/// more than max_step per tick, a jerk guard at the hand (docs/network_faults.md). The device_bridge renders with it, and
/// the chaos soak's monitor renders the same way.
class FeedbackRenderer {
 public:
  FeedbackRenderer() = default;
  /// max_force: clamp (N); max_step: largest change of the rendered force per tick (N).
  FeedbackRenderer(const WatchdogParams& watchdog, double max_force, double max_step) noexcept
      : watchdog_(watchdog), max_force_(max_force), max_step_(max_step) {}
  /// feedback_age_s: NaN/Inf (no feedback yet) counts as stale.
  const Vec3& render(double now_s, double feedback_age_s, const Vec3& feedback) noexcept;
  /// One tick towards zero at the rate limit (stopping); true while not yet zero.
  bool ramp_down() noexcept;
  const Vec3& rendered() const noexcept { return rendered_; }         ///< the last rendered force
  double max_step_seen() const noexcept { return max_step_seen_; }   ///< largest per-tick change so far
  double max_step() const noexcept { return max_step_; }             ///< the per-tick limit
  const Watchdog& watchdog() const noexcept { return watchdog_; }    ///< its feedback watchdog

 private:
  Watchdog watchdog_;
  double max_force_ = 0, max_step_ = 0, max_step_seen_ = 0;
  Vec3 rendered_ = Vec3::Zero();
};

/// Passivity observer after Ryu & Hannaford (2002): integrates the power flowing INTO the coupling through
/// its ports, E(t) = Σ ∫ f·v dt, where f is the force the outside exerts on the coupling at a port and v
/// that port's velocity. For the device port that is f = −f_feed (the device pushes back on the coupling
/// with the opposite of the force it renders) and v = device velocity. E ≥ 0 at every instant means the
/// coupling has not produced energy (passive); E < 0 means it has produced −E, which a passivity controller
/// would dissipate with the damping suggested_damping(). Telemetry only: nothing here changes the force.
class PassivityObserver {
 public:
  void add(const Vec3& f, const Vec3& v, double dt) noexcept;  ///< non-finite input is ignored and counted
  void add_power(double power, double dt) noexcept;   ///< power · dt into the coupling; non-finite ignored and counted
  double energy() const noexcept { return in_ - out_; }   ///< E(t)
  double energy_in() const noexcept { return in_; }     ///< Σ of the positive power increments
  double energy_out() const noexcept { return out_; }   ///< Σ of the negative ones, as a positive number
  double min_energy() const noexcept { return min_; }   ///< most negative E seen (0 if always passive)
  bool passive(double tol = 0) const noexcept { return energy() >= -tol; }   ///< E ≥ −tol
  /// Ryu–Hannaford damping α = −E / (Σ v² dt over the last step) that would dissipate the produced energy
  /// at a port moving with v during dt; 0 while passive.
  double suggested_damping(const Vec3& v, double dt) const noexcept;
  int64_t ignored() const noexcept { return ignored_; }       ///< non-finite inputs ignored
  void reset() noexcept { *this = PassivityObserver{}; }      ///< back to E = 0

 private:
  double in_ = 0, out_ = 0, min_ = 0;
  int64_t ignored_ = 0;
};

}  // namespace haptree
