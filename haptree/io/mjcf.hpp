// haptree::Model -> MuJoCo MJCF text, so MuJoCo can serve as an external oracle (tests) and
// people can cross-check haptree with MuJoCo. No MuJoCo dependency here: text only.
//
// Each body k becomes <body name=body_name[k] pos=joint_offset quat=joint_rotation> nested in its
// parent, with <joint name=joint_name[k] type=hinge|slide|ball|free pos="0 0 0" axis=joint_axis>
// (no element for fixed joints), <inertial pos=com quat=principal axes diaginertia mass>, zero
// damping/armature/stiffness, no geoms, no limits. <option gravity=model.gravity> with contacts and
// constraints disabled. Numbers are printed with 17 significant digits.
//
// Coordinate conventions (qpos/qvel/qfrc per joint; MuJoCo orders joints depth-first in the
// XML, so map by joint name):
//   hinge/slide: identical to haptree (angle / displacement along the axis).
//   ball: qpos quaternion (w,x,y,z) = haptree q; qvel = angular velocity in the child frame =
//         haptree q̇; qacc = haptree q̈.
//   free (only on bodies whose parent is the ground, a MuJoCo rule): haptree q = [p, Q] places the
//         body at joint_offset + Rj p with rotation Rj·R(Q); MuJoCo qpos = [that position, quat(Rj)⊗Q].
//         haptree q̇ = [ω_b; v_b] (body axes, v_b = velocity of the body origin), MuJoCo qvel =
//         [R v_b (world); ω_b]. Accelerations: MuJoCo qacc = [R (v̇_b + ω_b × v_b); ω̇_b].
//         Forces: haptree τ = [n_b; f_b] (body axes) -> MuJoCo qfrc = [R f_b; n_b].
//   External forces: haptree f_ext = [moment; force] at the body origin r_k (world axes);
//         MuJoCo xfrc_applied = [force; moment about the COM] = [f; n + (r_k − c_k) × f].
#pragma once

#include <string>

#include "haptree/model.hpp"

namespace haptree::io {

struct MjcfOptions {
  std::string model_name = "haptree";
  double timestep = 1e-3;
};

// Throws ModelError for a free joint whose parent is not the ground.
std::string to_mjcf(const Model& model, const MjcfOptions& options = {});

}  // namespace haptree::io
