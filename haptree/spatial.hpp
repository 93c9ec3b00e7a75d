/// @file
/// Spatial algebra (docs/algorithms.md §1): Plücker vectors [angular; linear], world-aligned axes,
/// expressed at an explicit reference point. Plain Eigen fixed-size types and free functions.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <Eigen/Cholesky>

namespace haptree {

using Vec3 = Eigen::Vector3d;                 ///< a point, direction or 3-vector
using Mat3 = Eigen::Matrix3d;                 ///< a rotation or 3×3 inertia
using Vec6 = Eigen::Matrix<double, 6, 1>;     ///< a spatial vector [angular; linear]
using Mat6 = Eigen::Matrix<double, 6, 6>;     ///< a spatial operator (inertia, mobility)
using Quat = Eigen::Quaterniond;              ///< a unit quaternion (spherical and free joints)

/// The cross-product matrix: skew(a) b = a × b.
inline Mat3 skew(const Vec3& a) {
  Mat3 s;
  s << 0, -a.z(), a.y(), a.z(), 0, -a.x(), -a.y(), a.x(), 0;
  return s;
}

/// crm(v) m = v × m (motion cross product).
inline Mat6 crm(const Vec6& v) {
  Mat6 X = Mat6::Zero();
  X.topLeftCorner<3, 3>() = skew(v.head<3>());
  X.bottomRightCorner<3, 3>() = skew(v.head<3>());
  X.bottomLeftCorner<3, 3>() = skew(v.tail<3>());
  return X;
}
/// crf(v) f = v ×* f = -crm(v)^T f.
inline Mat6 crf(const Vec6& v) { return -crm(v).transpose(); }

/// v × m without forming crm(v).
inline Vec6 cross_motion(const Vec6& v, const Vec6& m) {
  Vec6 r;
  const Vec3 w = v.head<3>(), u = v.tail<3>();
  r.head<3>() = w.cross(m.head<3>());
  r.tail<3>() = w.cross(m.tail<3>()) + u.cross(m.head<3>());
  return r;
}
/// v ×* f without forming crf(v).
inline Vec6 cross_force(const Vec6& v, const Vec6& f) {
  Vec6 r;
  const Vec3 w = v.head<3>(), u = v.tail<3>();
  r.head<3>() = w.cross(f.head<3>()) + u.cross(f.tail<3>());
  r.tail<3>() = w.cross(f.tail<3>());
  return r;
}

/// Point shifts with d = b - a (world axes).
/// Motion at a -> same motion at b:  [w; v_a + w × d].
inline Vec6 shift_motion(const Vec6& m, const Vec3& d) {
  Vec6 r;
  r.head<3>() = m.head<3>();
  r.tail<3>() = m.tail<3>() + m.head<3>().cross(d);
  return r;
}
/// Force at a -> same force at b:  [n_a - d × f; f].
inline Vec6 shift_force(const Vec6& f, const Vec3& d) {
  Vec6 r;
  r.head<3>() = f.head<3>() - d.cross(f.tail<3>());
  r.tail<3>() = f.tail<3>();
  return r;
}
/// M(a→b) as a matrix.
inline Mat6 motion_shift_matrix(const Vec3& d) {
  Mat6 M = Mat6::Identity();
  M.bottomLeftCorner<3, 3>() = -skew(d);
  return M;
}

/// Rigid-body inertia at a point P: mass m, COM offset c from P, rotational inertia Ic about the
/// COM, all in world axes. Built directly at the body point; never shifted from a far origin.
inline Mat6 spatial_inertia(double m, const Vec3& c, const Mat3& Ic) {
  Mat6 I;
  const Mat3 C = skew(c);
  I.topLeftCorner<3, 3>() = Ic + m * C * C.transpose();
  I.topRightCorner<3, 3>() = m * C;
  I.bottomLeftCorner<3, 3>() = m * C.transpose();
  I.bottomRightCorner<3, 3>() = m * Mat3::Identity();
  return I;
}

/// Inverse of a spatial inertia in closed form (SPD for m > 0 and Ic > 0):
/// I^{-1} = [[Ic^{-1}, -Ic^{-1} C], [C Ic^{-1}, 1/m - C Ic^{-1} C]] with C = [c]×.
inline Mat6 spatial_inertia_inverse(double m, const Vec3& c, const Mat3& Ic) {
  const Mat3 Ji = Ic.inverse();
  const Mat3 C = skew(c);
  Mat6 Ii;
  Ii.topLeftCorner<3, 3>() = Ji;
  Ii.topRightCorner<3, 3>() = -Ji * C;
  Ii.bottomLeftCorner<3, 3>() = C * Ji;
  Ii.bottomRightCorner<3, 3>() = Mat3::Identity() / m - C * Ji * C;
  return Ii;
}

/// Gravity (acceleration g) as a spatial force on a body with COM offset c from the reference point.
inline Vec6 gravity_force(double m, const Vec3& c, const Vec3& g) {
  Vec6 f;
  f.head<3>() = c.cross(m * g);
  f.tail<3>() = m * g;
  return f;
}

}  // namespace haptree
