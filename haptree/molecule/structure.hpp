// Molecular structures in: PDB / mmCIF through gemmi, plus CONECT records (gemmi 0.5.7 ignores them).
// Units: nm (coordinates are converted from the file's Å on reading). See docs/molecules.md.
#pragma once

#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "haptree/spatial.hpp"

namespace haptree::mol {

struct StructureError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

struct AtomRecord {
  std::string name;      // PDB atom name, trimmed ("CA")
  std::string element;   // "C", "H", ... (upper case; from the element column or the name)
  std::string resname;   // "ALA"
  std::string chain;     // "A"
  int resid = 0;         // residue sequence number
  char icode = ' ';      // insertion code
  bool hetero = false;   // HETATM record
  int serial = 0;        // serial number in the file (PDB), 0 if none
  int line = 0;          // 1-based line in the file (PDB), 0 if unknown (mmCIF)
  double occupancy = 1;
  Vec3 pos = Vec3::Zero();   // nm
};

struct ResidueRecord {
  std::string name, chain;
  int resid = 0;
  char icode = ' ';
  bool hetero = false;
  int first_atom = 0, natoms = 0;   // atoms [first_atom, first_atom + natoms) of Structure::atoms
  std::string label() const;        // "THR A 5"
};

struct ReadOptions {
  // Residue policy (docs/molecules.md): a file that contains polymer residues known to the force
  // field ("protein mode") keeps them and drops every other residue (waters, ions, ligands, lipids,
  // hetero groups), counting them in `messages`. A file without such residues (e.g. polyaniline)
  // keeps all non-water residues. keep_hetero keeps non-water hetero groups in protein mode too.
  bool keep_hetero = false;
  bool keep_water = false;
};

struct Structure {
  std::string path;
  std::vector<AtomRecord> atoms;
  std::vector<ResidueRecord> residues;
  std::vector<std::pair<int, int>> conect;   // bonds from CONECT, 0-based indices into atoms, i < j
  std::vector<std::string> messages;         // what the reader dropped or changed, for the log
  bool protein_mode = false;
  int dropped_waters = 0, dropped_hetero_residues = 0, dropped_hetero_atoms = 0;
  int dropped_altloc_atoms = 0;
  bool has_hydrogens() const;
  std::string atom_label(int i) const;        // "CA THR A 5 (line 12)"
};

// Reads .pdb/.ent (and .cif/.mmcif when built with PEGTL). Throws StructureError naming the file,
// the line or residue and what is wrong. Alternate locations: for every atom the conformer with
// the highest occupancy is kept (the first one on ties); the others are counted and dropped.
Structure read_structure(const std::string& path, const ReadOptions& options = {});

// Throws StructureError naming both atoms (with their lines) if two atoms are closer than
// min_distance_nm (default 0.1 Å; the shortest real bond, H-H, is 0.74 Å). read_structure calls it.
void check_no_coincident_atoms(const Structure& s, double min_distance_nm = 0.01);

// Residue names of the standard amino acids and caps that the protein templates know.
bool is_protein_residue_name(const std::string& resname);
bool is_water_residue_name(const std::string& resname);

}  // namespace haptree::mol
