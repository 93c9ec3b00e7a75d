// Atom positions from body poses: what a process that only sees the session's scene state
// (HAPTREE_SCENE_STATE: one position + unit quaternion per Model body) needs to place every atom,
// with the torsion model it loaded once. Same result as TorsionModel::atom_positions after
// forward_kinematics, up to the quaternion round trip (~1e-16 relative).
#pragma once

#include <vector>

#include "haptree/molecule/torsion_tree.hpp"

namespace haptree::mol {

// body_r[k], body_q[k]: world position (nm) and orientation (w, x, y, z; normalised here) of Model
// body k, k = 0..model->nbodies-1. x is resized to the atom count. Throws std::invalid_argument when
// the pose count differs from the model's body count (a scene state from another model).
inline void atom_positions_from_body_poses(const TorsionModel& t, const std::vector<Vec3>& body_r,
                                           const std::vector<Quat>& body_q, std::vector<Vec3>& x) {
  const size_t nb = static_cast<size_t>(t.model->nbodies);
  if (body_r.size() != nb || body_q.size() != nb)
    throw std::invalid_argument("atom_positions_from_body_poses: " + std::to_string(body_r.size()) +
                                " poses for a model of " + std::to_string(nb) + " bodies");
  const size_t na = t.atom_model_body.size();
  x.resize(na);
  for (size_t a = 0; a < na; ++a) {
    const int b = t.atom_model_body[a];
    x[a] = body_r[b] + body_q[b].normalized() * t.atom_local[a];
  }
}

}  // namespace haptree::mol
