// Piecewise-linear, time-scripted device trajectory with button states: the script of a ScriptedDevice
// and the target of a VirtualHand.
#pragma once

#include <cstdint>
#include <vector>

#include "haptree/spatial.hpp"

namespace haptree::device {

struct Waypoint {
  double t_s = 0;
  Vec3 position_m = Vec3::Zero();
  int32_t buttons = 0;  // held from this waypoint's time until the next one's
};

class Trajectory {
 public:
  Trajectory() = default;
  // Waypoints in strictly increasing time; throws std::invalid_argument naming the bad index otherwise.
  explicit Trajectory(std::vector<Waypoint> waypoints);
  // Position, velocity, buttons at t: linear between waypoints, constant before the first/after the last.
  Vec3 position(double t_s) const noexcept;
  Vec3 velocity(double t_s) const noexcept;
  int32_t buttons(double t_s) const noexcept;
  double duration() const noexcept { return w_.empty() ? 0.0 : w_.back().t_s; }
  const std::vector<Waypoint>& waypoints() const noexcept { return w_; }

 private:
  size_t segment(double t_s) const noexcept;  // i such that w_[i].t <= t < w_[i+1].t, clamped
  std::vector<Waypoint> w_;
};

// Approach the grab point, press grab, pull along a direction, hold, release, rest.
struct GrabPullRelease {
  Vec3 start_m = Vec3::Zero();
  Vec3 grab_m = Vec3(0.0, 0.0, 0.01);
  double approach_s = 0.5;   // start -> grab point, button up
  double settle_s = 0.2;     // at the grab point, button down
  Vec3 pull_direction = Vec3::UnitX();  // normalised here
  double pull_distance_m = 0.03;
  double pull_s = 1.0;       // grab point -> grab point + distance * direction, button down
  double hold_s = 0.5;       // still pulled, button down
  double rest_s = 0.3;       // released (button up), still
};
Trajectory make_grab_pull_release(const GrabPullRelease& p);

}  // namespace haptree::device
