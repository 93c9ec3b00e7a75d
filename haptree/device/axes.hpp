// A vendor's device axes onto haptree's device frame (x right, y up, z towards the user): a signed
// permutation, written as the vendor axis that becomes each of haptree's x, y, z. Examples:
//   "x,y,z"  identity (OpenHaptics: x right, y up, z towards the user)
//   "y,z,x"  Force Dimension (x towards the user, y right, z up): haptree x = vendor y, y = vendor z,
//            z = vendor x
// Only rotations (determinant +1): a mirror would turn a right-handed stylus frame left-handed.
#pragma once

#include <string>

#include "haptree/spatial.hpp"

namespace haptree::device {

struct DeviceConfig;

class AxisMap {
 public:
  AxisMap() = default;   // identity
  // "A,B,C" with each of A, B, C one of x, y, z, -x, -y, -z (optionally +), every axis once, det +1.
  // Throws std::invalid_argument naming the text and what is wrong.
  static AxisMap parse(const std::string& spec);
  Vec3 to_frame(const Vec3& vendor) const noexcept { return R_ * vendor; }      // positions, velocities
  Vec3 to_vendor(const Vec3& frame) const noexcept { return R_.transpose() * frame; }   // forces, torques
  // An orientation measured in vendor axes (vendor base -> stylus, stylus axes also the vendor's),
  // expressed in haptree's: R R_v R^T.
  Mat3 to_frame(const Mat3& vendor_rotation) const noexcept { return R_ * vendor_rotation * R_.transpose(); }
  const Mat3& matrix() const noexcept { return R_; }
  const std::string& str() const noexcept { return text_; }

 private:
  Mat3 R_ = Mat3::Identity();   // haptree = R · vendor
  std::string text_ = "x,y,z";
};

// The option axes= of a device (its family's default when absent), parsed; errors name the option.
AxisMap axis_map_option(const DeviceConfig& c, const std::string& family_default);

}  // namespace haptree::device
