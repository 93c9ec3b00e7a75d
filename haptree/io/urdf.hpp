// URDF -> haptree::Model through Debian's liburdfdom (parser only; the mapping is ours).
//
// Mapping (URDF semantics, docs in the header so the CLI and tests share one description):
//  * joint types: revolute, continuous -> kRevolute; prismatic -> kPrismatic; fixed -> kFixed;
//    floating -> kFree (q = [x,y,z, qw,qx,qy,qz] of the child frame in the joint frame,
//    q̇ = [ω; v] in the child's own axes). planar -> error (unsupported).
//  * joint <origin> is the child link frame in the parent link frame: it becomes the joint's
//    offset/rotation; the child body frame (origin = joint point) is the URDF child link frame.
//    <axis> is in that frame (urdfdom's default (1,0,0) when absent). Limits, dynamics (damping,
//    friction), mimic, safety controllers, visuals and collisions are ignored.
//  * <inertial>: mass, <origin xyz rpy> relative to the link frame, tensor in the rotated
//    inertial frame; it is rotated into the link frame: I_link = R I R^T, COM = xyz.
//  * root: a root link named "world" is the ground (its child joints attach to the ground with
//    their own types, e.g. "floating" -> free base). Any other root link is attached to the ground
//    by a joint named `root_joint_name`: fixed, or free when options.floating_base is set.
//  * massless links (no <inertial>, or mass 0) attached by a fixed joint are pure frames: they are
//    lumped into their parent body (their children re-attach to it with composed transforms).
//    A massless link on a moving joint (haptree needs positive mass on every moving body) is an
//    error naming the file and the link. With options.lump_fixed, links with mass on fixed
//    joints are lumped too (mass, COM and inertia combined by the parallel-axis theorem), as
//    MuJoCo's fusestatic does.
//  * joint names are kept; a body's name is its URDF link name. Children are visited in
//    urdfdom's order (sorted by joint name), depth first, so parent ids precede child ids.
// Errors: io::UrdfError, one line "<file>: <element> '<name>': <what>".
#pragma once

#include <memory>
#include <string>

#include "haptree/model.hpp"

namespace haptree::io {

struct UrdfError : ModelError {
  using ModelError::ModelError;
};

struct UrdfOptions {
  bool floating_base = false;                 // attach a non-"world" root link by a free joint
  bool lump_fixed = false;                    // also lump massive links on fixed joints
  std::string root_joint_name = "root_joint"; // name of the joint that holds a non-"world" root
  Vec3 gravity{0, 0, -9.81};
  BuildOptions build;
};

// Reads and converts a URDF file. Throws UrdfError (missing file, XML/URDF parse error, massless
// moving link, negative mass, bad inertia, planar/unknown joint).
std::shared_ptr<const Model> load_urdf(const std::string& path, const UrdfOptions& options = {});
// Same from XML text; `source` names it in error messages.
std::shared_ptr<const Model> parse_urdf(const std::string& xml, const std::string& source,
                                        const UrdfOptions& options = {});

}  // namespace haptree::io
