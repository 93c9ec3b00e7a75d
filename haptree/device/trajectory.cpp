#include "haptree/device/trajectory.hpp"

#include "haptree/device/device.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace haptree::device {

Trajectory::Trajectory(std::vector<Waypoint> waypoints) : w_(std::move(waypoints)) {
  for (size_t i = 0; i < w_.size(); ++i) {
    if (!std::isfinite(w_[i].t_s) || !w_[i].position_m.allFinite())
      throw std::invalid_argument("Trajectory: waypoint " + std::to_string(i) + " is not finite");
    if (i > 0 && !(w_[i].t_s > w_[i - 1].t_s))
      throw std::invalid_argument("Trajectory: waypoint " + std::to_string(i) + " time " +
                                  std::to_string(w_[i].t_s) + " s is not after waypoint " +
                                  std::to_string(i - 1) + "'s " + std::to_string(w_[i - 1].t_s) + " s");
  }
}

size_t Trajectory::segment(double t) const noexcept {
  // Last waypoint with t_i <= t (0 if t is before the first).
  auto it = std::upper_bound(w_.begin(), w_.end(), t, [](double v, const Waypoint& w) { return v < w.t_s; });
  return it == w_.begin() ? 0 : static_cast<size_t>(it - w_.begin()) - 1;
}

Vec3 Trajectory::position(double t) const noexcept {
  if (w_.empty()) return Vec3::Zero();
  if (t <= w_.front().t_s) return w_.front().position_m;
  if (t >= w_.back().t_s) return w_.back().position_m;
  const size_t i = segment(t);
  const auto& a = w_[i];
  const auto& b = w_[i + 1];
  const double s = (t - a.t_s) / (b.t_s - a.t_s);
  return a.position_m + s * (b.position_m - a.position_m);
}

Vec3 Trajectory::velocity(double t) const noexcept {
  if (w_.size() < 2 || t < w_.front().t_s || t >= w_.back().t_s) return Vec3::Zero();
  const size_t i = segment(t);
  return (w_[i + 1].position_m - w_[i].position_m) / (w_[i + 1].t_s - w_[i].t_s);
}

int32_t Trajectory::buttons(double t) const noexcept {
  if (w_.empty() || t < w_.front().t_s) return 0;
  return w_[segment(t)].buttons;
}

Trajectory make_grab_pull_release(const GrabPullRelease& p) {
  const Vec3 dir = p.pull_direction.norm() > 0 ? p.pull_direction.normalized() : Vec3::UnitX();
  const Vec3 pulled = p.grab_m + p.pull_distance_m * dir;
  double t = 0;
  std::vector<Waypoint> w;
  w.push_back({t, p.start_m, 0});
  t += p.approach_s;
  w.push_back({t, p.grab_m, kButtonGrab});
  t += p.settle_s;
  w.push_back({t, p.grab_m, kButtonGrab});
  t += p.pull_s;
  w.push_back({t, pulled, kButtonGrab});
  t += p.hold_s;
  w.push_back({t, pulled, 0});
  t += p.rest_s;
  w.push_back({t, pulled, 0});
  return Trajectory(std::move(w));
}

}  // namespace haptree::device
