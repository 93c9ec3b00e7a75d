/// @file
/// Procedural scenes: chains, binary trees, random trees, stars and the 857-DOF protein-like tree.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "haptree/model.hpp"

namespace haptree {

/// Options of the procedural scenes.
struct SceneOptions {
  int n = 16;                     ///< bodies (besides the ground)
  std::uint32_t seed = 0;         ///< 0: regular geometry; otherwise random links (0.2–0.5 m, 0.5–2 kg)
  bool mixed_joints = false;      ///< chains, random trees, stars: revolute/prismatic/spherical/fixed mix
  bool free_root = false;         ///< attach the root body with a free joint instead of a revolute
  Vec3 base_offset = Vec3::Zero();   ///< where the root joint sits in the world (far-origin tests)
  Vec3 gravity{0, 0, -9.81};         ///< m/s²
  BuildOptions build;             ///< e.g. build.max_children for stars
};

/// Serial chain of n revolute links.
std::shared_ptr<const Model> make_chain(const SceneOptions& o);
/// Complete binary tree in breadth-first order: body k's parent is (k-1)/2 (body 1 on the ground).
std::shared_ptr<const Model> make_binary_tree(const SceneOptions& o);
/// Random recursive tree: body k hangs from a uniformly random earlier body.
std::shared_ptr<const Model> make_random_tree(const SceneOptions& o);
/// One hub body (spherical, or free with free_root) with n-1 leaf links (revolute, or the random
/// mix with mixed_joints). Set build.max_children (e.g. 4) from a few dozen leaves on: the
/// unsplit hub's assembly needs O(n^3) memory; the split one is exact (docs/algorithms.md §4.4).
std::shared_ptr<const Model> make_star(const SceneOptions& o);
/// Backbone of 343 bodies (the first welded to the ground), a side chain of 2, 3, 4, 2, 3, 4 …
/// bodies on every odd backbone body: 857 revolute DOF.
std::shared_ptr<const Model> make_protein_like(const SceneOptions& o);

/// Builds a scene from a name: chain, binary_tree, random_tree, star, protein_like.
std::shared_ptr<const Model> make_scene(const std::string& name, const SceneOptions& o);

}  // namespace haptree
