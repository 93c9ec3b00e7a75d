// Torsion-angle model (docs/molecules.md): rigid groups of atoms between rotatable bonds, as a tree
// of revolute joints rooted at the N-terminal (first-atom) body of every bonded segment.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "haptree/model.hpp"
#include "haptree/molecule/structure.hpp"
#include "haptree/molecule/topology.hpp"

namespace haptree::mol {

struct TorsionOptions {
  bool omega = false;           // make peptide C-N bonds rotatable too
  bool with_h_rotors = false;   // also joints whose moving side holds only hydrogens (OH, NH3+, CH3)
  // Root attachment of every segment's root body (fixed = welded to the world; free = 6 DOF).
  JointType root_joint = JointType::kFixed;
  // Every atom is a uniform sphere of this radius for the body inertia (keeps 2-atom / collinear
  // bodies such as {Cα, Hα} positive definite; adds 0.4 m a² per atom). nm.
  double atom_radius_nm = 0.01;
  BuildOptions build;           // passed to ModelBuilder::build (bodies are re-mapped by name)
};

struct TorsionJoint {
  int atom1 = -1, atom2 = -1;   // atom1 on the parent side; axis atom1 -> atom2
  int parent_body = -1, child_body = -1;   // molecular body ids (TorsionModel::body_*)
  std::string label;            // phi, psi, omega, chi1..chi4, tor
  int residue = -1;             // residue index of atom1
  int model_body = -1;          // Model body (= joint) id
};

struct TorsionModel {
  // Molecular bodies, in parent-before-child order (body b's parent has a smaller id; -1 = root).
  int nbodies = 0;
  std::vector<int> body_parent;
  std::vector<int> body_joint;              // index into joints, -1 for segment roots
  std::vector<std::vector<int>> body_atoms;
  std::vector<Vec3> body_origin;            // world position of the frame origin at q = 0 (nm)
  std::vector<int> model_body;              // molecular body -> Model body id
  std::vector<int> roots;                   // molecular body ids of the segment roots
  std::vector<TorsionJoint> joints;
  // Per atom.
  std::vector<int> atom_body;               // molecular body
  std::vector<int> atom_model_body;         // Model body id
  std::vector<Vec3> atom_local;             // position in its body frame (nm)
  std::shared_ptr<const Model> model;
  int dof() const { return model ? model->nv : 0; }
  // World atom positions from kinematics (Data::R, Data::r after forward_kinematics).
  void atom_positions(const std::vector<Mat3>& R, const std::vector<Vec3>& r,
                      std::vector<Vec3>& x) const;
};

// Builds the torsion tree and the haptree Model (revolute joints about atom1->atom2, child body
// frame at atom2 with world axes at q = 0; q = 0 is the input conformation). Gravity is zero.
TorsionModel build_torsion_model(const Structure& s, const Topology& t,
                                 const TorsionOptions& options = {});

}  // namespace haptree::mol
