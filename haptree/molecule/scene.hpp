// Molecular scenes: a PDB/mmCIF file (or a named scene) -> haptree Model + atom tables + force field.
// Units: nm, ps, amu, kJ/mol, e; gravity zero (docs/molecules.md). 1 amu·nm²/ps² = 1 kJ/mol.
#pragma once

#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include "haptree/data.hpp"
#include "haptree/molecule/forcefield.hpp"
#include "haptree/molecule/structure.hpp"
#include "haptree/molecule/topology.hpp"
#include "haptree/molecule/torsion_tree.hpp"

namespace haptree::mol {

struct SceneOptions {
  ReadOptions read;
  TopologyOptions topology;
  TorsionOptions torsion;             // root_joint: kFixed (default) or kFree
  ff::NonbondedOptions nonbonded;
  std::string force_field_path;       // default: <data dir>/molecules/ff14sb.dat
  bool with_force_field = true;
};

struct MolecularScene {
  std::string name;                   // scene name or file stem
  std::string path;                   // resolved file
  Structure structure;                // atoms (nm), residues, CONECT bonds, reader messages
  Topology topology;                  // per-atom parameters, bonds, 1-4 pairs, torsions
  TorsionModel torsion;               // joints, bodies, per-atom body and local position
  std::shared_ptr<const Model> model; // = torsion.model
  std::unique_ptr<ff::Evaluator> force_field;   // null if !with_force_field
  std::vector<std::string> messages;  // everything worth logging once (reader + topology)

  int natoms() const { return topology.natoms; }
  int dof() const { return model->nv; }
  // Potential energy (kJ/mol) and f_ext (overwritten, one spatial force per body at r_k, world
  // axes) at the configuration in `data` (after forward_kinematics).
  double compute(const Data& data, std::vector<Vec6>& f_ext) {
    return force_field->compute(*model, data, f_ext);
  }
  void atom_positions(const Data& data, std::vector<Vec3>& x) const {
    torsion.atom_positions(data.R, data.r, x);
  }
  // World position of one atom (after forward_kinematics).
  Vec3 atom_position(const Data& data, int atom) const {
    const int b = torsion.atom_model_body[atom];
    return data.r[b] + data.R[b] * torsion.atom_local[atom];
  }
  // Adds a force F (kJ/mol/nm, world) acting on `atom` to f_ext (e.g. a haptic pull on one atom).
  void add_atom_force(const Data& data, int atom, const Vec3& F, std::vector<Vec6>& f_ext) const {
    const int b = torsion.atom_model_body[atom];
    f_ext[b].head<3>() += (data.R[b] * torsion.atom_local[atom]).cross(F);
    f_ext[b].tail<3>() += F;
  }
};

// Data directory: $HAPTREE_DATA_DIR if set; else <exe dir>/../data, <exe dir>/../../data,
// <exe dir>/../share/haptree/data (first that holds molecules/); else the compiled-in source
// data directory. Throws if none exists.
std::string data_dir();
// "bacteriorhodopsin" | "bR" -> molecules/1c3w_protein_h.pdb; "bacteriorhodopsin-raw" ->
// molecules/1c3w.pdb; "ala20" | "polyalanine" -> molecules/ala20_helix_h.pdb; "polyaniline" ->
// molecules/pani_leuco_20N_helix.pdb; anything else is a file path (must exist).
std::string resolve_molecule_path(const std::string& name_or_path);
std::vector<std::string> molecular_scene_names();

MolecularScene load_molecular_scene(const std::string& name_or_path, const SceneOptions& options = {});

// Multi-model PDB trajectory (MODEL/ENDMDL, coordinates in Å) readable by VMD and PyMOL.
class PdbTrajectoryWriter {
 public:
  // Keeps a reference to `s`: the Structure must outlive the writer.
  PdbTrajectoryWriter(const std::string& path, const Structure& s);
  void write_frame(const std::vector<Vec3>& x_nm);   // throws on I/O error
  void close();
  int frames() const { return frames_; }
  ~PdbTrajectoryWriter();

 private:
  const Structure& s_;
  std::ofstream out_;
  std::string path_;
  int frames_ = 0;
};

// Writes one structure (positions in nm) as PDB with CONECT for non-template bonds if given. Throws
// (naming the atom) if a coordinate does not fit PDB's fixed columns (-999.999 .. 9999.999 Å): use
// write_mmcif for those. PdbTrajectoryWriter::write_frame checks the same.
void write_pdb(const std::string& path, const Structure& s, const std::vector<Vec3>& x_nm);
// Index of the first atom whose coordinates do not fit PDB's columns, -1 if all fit.
int first_atom_outside_pdb_columns(const std::vector<Vec3>& x_nm);
// Writes one structure as mmCIF (_atom_site loop; any size). CONECT bonds are not written: only
// template residues (e.g. proteins) come back the same from it.
void write_mmcif(const std::string& path, const Structure& s, const std::vector<Vec3>& x_nm);

}  // namespace haptree::mol
