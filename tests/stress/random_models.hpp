// Random articulated models for the origin-independence property, shared by
// tests/stress/origin_independence_test.cpp (a small sweep) and tools/stress_report (a larger one).
// A ModelSpec is a plain list of bodies; it is placed in the world by a rigid transform (Rw, t)
// applied to the joints that attach to the ground (and to gravity), and built either directly or
// through URDF text (haptree::io), so the same physical model can be compared at the origin and
// 10⁶ m away, rotated, with and without lumped fixed joints.
#pragma once

#include <cmath>
#include <cstdio>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "haptree/model.hpp"
#include "tests/support/oracle.hpp"

namespace haptree::stress {

struct BodySpec {
  int parent;   // 0 = ground
  JointType type;
  Vec3 offset;
  Mat3 rotation;
  Vec3 axis;
  double mass;
  Vec3 com;
  Mat3 Ic;
};

struct ModelSpec {
  std::vector<BodySpec> bodies;   // body k + 1 is bodies[k]
  Vec3 gravity{0, 0, -9.81};
  int max_children = 0;
};

struct RandomModelOptions {
  int n = 20;                   // bodies
  double fixed_fraction = 0.1;  // share of fixed joints below the root
  double mass_ratio = 1;        // masses log-uniform in [1, mass_ratio] kg
  double weld_length = 0;       // > 0: some welds sit this far from their parent's frame
  bool urdf_joints = false;     // no spherical joints (URDF has none)
};

inline Mat3 random_rotation(std::mt19937& rng) {
  std::normal_distribution<double> n(0, 1);
  Eigen::Vector4d q(n(rng), n(rng), n(rng), n(rng));
  q.normalize();
  return Quat(q(0), q(1), q(2), q(3)).toRotationMatrix();
}
inline Vec3 random_direction(std::mt19937& rng) {
  std::normal_distribution<double> n(0, 1);
  return Vec3(n(rng), n(rng), n(rng)).normalized();
}

// A random tree: the root is held by a fixed joint (a fixed root with its own inertia, massive when
// mass_ratio > 1), a free, a revolute or a spherical joint; below it every joint type, chains of
// welds (a fixed body often hangs from the previous body), welded massive links, and, with
// weld_length > 0, the first weld below the root (the mount) and some others far from their
// parent's frame.
inline ModelSpec random_model_spec(std::mt19937& rng, const RandomModelOptions& o) {
  std::uniform_real_distribution<double> u(0, 1);
  auto log_uniform = [&](double hi) { return std::exp(u(rng) * std::log(std::max(hi, 1.0))); };
  ModelSpec s;
  s.gravity = Vec3(0, 0, -9.81);
  bool mounted = false;
  for (int k = 1; k <= o.n; ++k) {
    BodySpec b;
    b.parent = k == 1 ? 0 : (u(rng) < 0.35 ? k - 1 : 1 + static_cast<int>(u(rng) * (k - 1)));
    if (k == 1) {
      const double r = u(rng);
      b.type = r < 0.4 ? JointType::kFixed : r < 0.6 ? JointType::kFree
               : r < 0.8 || o.urdf_joints ? JointType::kRevolute : JointType::kSpherical;
    } else if (u(rng) < o.fixed_fraction) {
      b.type = JointType::kFixed;
    } else {
      const double r = u(rng);
      b.type = r < 0.45 ? JointType::kRevolute : r < 0.65 ? JointType::kPrismatic
               : r < 0.85 && !o.urdf_joints ? JointType::kSpherical : JointType::kFree;
      if (b.type == JointType::kFree && u(rng) < 0.5) b.type = JointType::kRevolute;
    }
    b.offset = Vec3(u(rng) - 0.5, u(rng) - 0.5, u(rng) - 0.5) * 0.6;
    if (b.type == JointType::kFixed && b.parent > 0 && o.weld_length > 0 &&
        (!mounted || u(rng) < 0.3)) {
      b.offset = o.weld_length * (0.5 + 0.5 * u(rng)) * random_direction(rng);
      mounted = true;
    }
    b.rotation = random_rotation(rng);
    b.axis = random_direction(rng);
    b.mass = log_uniform(o.mass_ratio);
    if ((k == 1 || b.type == JointType::kFixed) && u(rng) < 0.4) b.mass = o.mass_ratio;  // massive
    b.com = Vec3(u(rng) - 0.5, u(rng) - 0.5, u(rng) - 0.5) * 0.3;
    // Box inertia (always physical), randomly oriented.
    const Vec3 dim(0.05 + 0.3 * u(rng), 0.05 + 0.3 * u(rng), 0.05 + 0.3 * u(rng));
    const Vec3 mom(dim.y() * dim.y() + dim.z() * dim.z(), dim.x() * dim.x() + dim.z() * dim.z(),
                   dim.x() * dim.x() + dim.y() * dim.y());
    const Mat3 Rb = random_rotation(rng);
    b.Ic = Rb * Mat3((b.mass / 12 * mom).asDiagonal()) * Rb.transpose();
    s.bodies.push_back(b);
  }
  s.max_children = u(rng) < 0.3 ? 2 : 0;   // degree reduction adds welded hub pieces
  return s;
}

// The spec with its ground joints moved by x ↦ Rw x + t, gravity rotated with it.
inline ModelSpec placed(const ModelSpec& s, const Mat3& Rw, const Vec3& t) {
  ModelSpec p = s;
  for (auto& b : p.bodies)
    if (b.parent == 0) {
      b.offset = Rw * b.offset + t;
      b.rotation = Rw * b.rotation;
    }
  p.gravity = Rw * s.gravity;
  return p;
}

inline std::shared_ptr<const Model> build_model(const ModelSpec& s) {
  ModelBuilder b;
  b.set_gravity(s.gravity);
  for (std::size_t k = 0; k < s.bodies.size(); ++k) {
    const BodySpec& x = s.bodies[k];
    b.add_body("l" + std::to_string(k + 1), x.parent, x.type, x.offset, x.rotation, x.axis, x.mass,
               x.com, x.Ic, "j" + std::to_string(k + 1));
  }
  BuildOptions bo;
  bo.max_children = s.max_children;
  return b.build(bo);
}

// URDF text of the spec: link "world" is the ground; every number printed with %.17g (exact).
// Spherical joints have no URDF form (the spec must not hold any).
inline std::string to_urdf(const ModelSpec& s) {
  auto num = [](double v) {
    char buf[40];
    std::snprintf(buf, sizeof buf, "%.17g", v);
    return std::string(buf);
  };
  auto vec = [&](const Vec3& v) { return num(v.x()) + " " + num(v.y()) + " " + num(v.z()); };
  auto rpy = [&](const Mat3& R) {   // URDF: R = Rz(yaw) Ry(pitch) Rx(roll)
    const double pitch = std::asin(std::max(-1.0, std::min(1.0, -R(2, 0))));
    const double roll = std::atan2(R(2, 1), R(2, 2)), yaw = std::atan2(R(1, 0), R(0, 0));
    return num(roll) + " " + num(pitch) + " " + num(yaw);
  };
  std::string x = "<robot name=\"random\">\n<link name=\"world\"/>\n";
  for (std::size_t k = 0; k < s.bodies.size(); ++k) {
    const BodySpec& b = s.bodies[k];
    const std::string name = "l" + std::to_string(k + 1);
    x += "<link name=\"" + name + "\"><inertial><origin xyz=\"" + vec(b.com) +
         "\" rpy=\"0 0 0\"/><mass value=\"" + num(b.mass) + "\"/><inertia ixx=\"" +
         num(b.Ic(0, 0)) + "\" ixy=\"" + num(b.Ic(0, 1)) + "\" ixz=\"" + num(b.Ic(0, 2)) +
         "\" iyy=\"" + num(b.Ic(1, 1)) + "\" iyz=\"" + num(b.Ic(1, 2)) + "\" izz=\"" +
         num(b.Ic(2, 2)) + "\"/></inertial></link>\n";
    const char* type = b.type == JointType::kRevolute    ? "continuous"
                       : b.type == JointType::kPrismatic ? "prismatic"
                       : b.type == JointType::kFree      ? "floating"
                                                         : "fixed";
    const std::string parent = b.parent == 0 ? "world" : "l" + std::to_string(b.parent);
    // Joint names sort like the body order (urdfdom visits children by joint name).
    char jn[16];
    std::snprintf(jn, sizeof jn, "j%04zu", k + 1);
    x += std::string("<joint name=\"") + jn + "\" type=\"" + type + "\"><parent link=\"" + parent +
         "\"/><child link=\"" + name + "\"/><origin xyz=\"" + vec(b.offset) + "\" rpy=\"" +
         rpy(b.rotation) + "\"/>";
    if (b.type == JointType::kRevolute || b.type == JointType::kPrismatic)
      x += "<axis xyz=\"" + vec(b.axis) + "\"/>";
    if (b.type == JointType::kPrismatic)
      x += "<limit lower=\"-1\" upper=\"1\" effort=\"1\" velocity=\"1\"/>";
    x += "</joint>\n";
  }
  return x + "</robot>\n";
}

// Same state with its world-axes external forces rotated by Rw (joint coordinates are local).
inline State rotated_state(const Model& m, const State& st, const Mat3& Rw) {
  State r = st;
  for (int k = 0; k < m.nbodies; ++k) {
    r.f_ext[k].head<3>() = Rw * st.f_ext[k].head<3>();
    r.f_ext[k].tail<3>() = Rw * st.f_ext[k].tail<3>();
  }
  return r;
}

// A hard case for welds far from the origin: a binary tree of 127 joints, ≈ 10 % of them fixed, mounted
// `mount` metres from a 1000 kg root link (itself fixed to the ground) through a fixed joint.
// Shared by OriginIndependence.BinaryTreeMountedOneKilometreOffAMassiveRootLink and
// stress_report --sections welds.
inline ModelSpec mounted_binary_tree(double mount) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(0, 1);
  ModelSpec s;
  s.bodies.push_back({0, JointType::kFixed, Vec3::Zero(), Mat3::Identity(), Vec3::UnitZ(), 1000,
                      Vec3(0.05, 0, 0), Mat3(Vec3(100, 120, 140).asDiagonal())});
  for (int k = 1; k <= 127; ++k) {
    const JointType t = k == 1 || u(rng) < 0.1 ? JointType::kFixed : JointType::kRevolute;
    const int parent = k == 1 ? 1 : k / 2 + 1;
    const double m = 0.5 + 1.5 * u(rng);
    s.bodies.push_back({parent, t, k == 1 ? mount * Vec3(1, 2, 3).normalized() : Vec3(0.3, 0, 0),
                        Mat3(Eigen::AngleAxisd(k % 2 ? 0.5 : -0.5, Vec3::UnitZ())),
                        random_direction(rng), m, Vec3(0.15, 0.01, 0),
                        Mat3((m / 12 * Vec3(0.0032, 0.0916, 0.0916)).asDiagonal())});
  }
  return s;
}

}  // namespace haptree::stress
