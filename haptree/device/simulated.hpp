// Simulated devices ("mock components"): a scripted trajectory and a virtual hand.
#pragma once

#include "haptree/device/device.hpp"
#include "haptree/device/trajectory.hpp"

namespace haptree::device {

// Plays a Trajectory: read(t) returns its position, velocity and buttons at t. Forces written are kept
// (last_force()) but do not move it. Deterministic.
class ScriptedDevice final : public Device {
 public:
  ScriptedDevice(const DeviceSpec& spec, Trajectory script);
  const DeviceSpec& spec() const noexcept override { return spec_; }
  Status read(double time_s, DeviceReading& out) noexcept override;
  Status write(const Vec3& force_n, const Vec3& torque_nm) noexcept override;
  const Vec3& last_force() const noexcept { return force_; }
  const Trajectory& script() const noexcept { return script_; }

 private:
  DeviceSpec spec_;
  Trajectory script_;
  int64_t seq_ = 0;
  Vec3 force_ = Vec3::Zero();
};

struct VirtualHandParams {
  double mass_kg = 0.2;               // hand + handle
  double stiffness_n_per_m = 200.0;   // arm spring towards the target
  double damping_n_s_per_m = 8.0;     // on the velocity relative to the target's
  double max_substep_s = 1e-4;        // integration substep (semi-implicit Euler)
};

// A mass–spring–damper hand following a target Trajectory, that feels the force written to it:
//   m ẍ = k (x_target − x) + c (ẋ_target − ẋ) + f_device
// with f_device the last written force, saturated at spec.max_force_n like a real device. Integrated
// from the previous read() time to the new one. For closed-loop stability tests of the coupling.
class VirtualHand final : public Device {
 public:
  VirtualHand(const DeviceSpec& spec, const VirtualHandParams& params, Trajectory target);
  const DeviceSpec& spec() const noexcept override { return spec_; }
  Status read(double time_s, DeviceReading& out) noexcept override;
  Status write(const Vec3& force_n, const Vec3& torque_nm) noexcept override;
  const Vec3& position() const noexcept { return x_; }
  const Vec3& velocity() const noexcept { return v_; }
  const Vec3& applied_force() const noexcept { return f_; }
  const VirtualHandParams& params() const noexcept { return p_; }

 private:
  DeviceSpec spec_;
  VirtualHandParams p_;
  Trajectory target_;
  Vec3 x_, v_ = Vec3::Zero(), f_ = Vec3::Zero();
  double t_ = 0;
  bool started_ = false;
  int64_t seq_ = 0;
};

}  // namespace haptree::device
