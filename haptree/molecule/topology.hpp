// Force-field parameters (AMBER ff14SB converted from OpenMM's XML by tools/molecule_convert_ff14sb.py)
// and the molecular topology: atom typing by residue templates, bonds, chain segments, exclusions,
// 1-4 pairs and proper torsions. Units: nm, kJ/mol, e, amu, rad (docs/molecules.md).
#pragma once

#include <array>
#include <map>
#include <string>
#include <vector>

#include "haptree/molecule/structure.hpp"

namespace haptree::ff {

struct AtomType {
  std::string name, cls, element;
  double mass = 0, sigma = 0, epsilon = 0;   // amu, nm, kJ/mol
};
struct TemplateAtom {
  std::string name;
  int type = -1;
  double charge = 0;
};
struct ResidueTemplate {
  std::string name;
  std::vector<TemplateAtom> atoms;
  std::vector<std::pair<int, int>> bonds;   // indices into atoms
  std::vector<int> external;                // atoms with an inter-residue bond
  int find(const std::string& atom_name) const;   // -1 if absent
};
struct TorsionTerm {
  int periodicity = 0;
  double phase = 0, k = 0;   // rad, kJ/mol
};
struct ProperDef {
  std::array<int, 4> type{};   // -1 = wildcard
  std::vector<TorsionTerm> terms;
};

struct ForceFieldParams {
  std::string source;
  double coulomb14scale = 1.0 / 1.2, lj14scale = 0.5;
  std::vector<AtomType> types;
  std::map<std::string, int> type_index;
  std::map<std::string, ResidueTemplate> templates;
  std::vector<ProperDef> propers;   // file order (OpenMM's matching rule depends on it)
  int type_id(const std::string& name) const;   // throws if absent
};

// Reads data/molecules/ff14sb.dat (format documented in the converter). Throws with file:line.
ForceFieldParams load_force_field(const std::string& path);

}  // namespace haptree::ff

namespace haptree::mol {

struct Torsion {
  int i, j, k, l;
  int periodicity;
  double phase, k_kJmol;
};
struct Pair14 {
  int i, j;
  double qq, sigma, epsilon;   // already scaled: qq = q_i q_j / 1.2, epsilon = 0.5 sqrt(e_i e_j)
};

struct TopologyOptions {
  // Structures without any hydrogen (e.g. the raw crystal entry 1c3w.pdb) are typed with the
  // heavy atoms of the all-atom templates; their hydrogens are simply absent (not ff14SB any more:
  // a message says so). With require_hydrogens such a file is rejected instead.
  bool require_hydrogens = false;
  double peptide_bond_max_nm = 0.2;   // C(i)-N(i+1) longer than this = chain break
  double disulfide_max_nm = 0.25;
};

struct Topology {
  int natoms = 0;
  std::vector<double> mass, charge, sigma, epsilon;   // per atom (amu, e, nm, kJ/mol)
  std::vector<std::string> atom_class;                // ff class ("CT") or generic type name
  std::vector<bool> heavy;
  std::vector<std::string> residue_template;          // per residue: template used ("NTHR"), "" generic
  std::vector<int> atom_residue;                      // per atom: index into Structure::residues
  std::vector<std::pair<int, int>> bonds;             // i < j
  std::vector<std::vector<int>> adjacency;            // per atom
  std::vector<int> segment;                           // per atom: bonded component id (0 = first)
  int nsegments = 0;
  std::vector<std::pair<int, int>> excluded;          // 1-2 and 1-3 pairs, i < j
  std::vector<Pair14> pairs14;
  std::vector<Torsion> torsions;                      // one row per Fourier term (k != 0)
  std::vector<int> chain_breaks;                      // residue index that starts a new segment
  bool typed_by_templates = false;                    // ff14SB (protein mode)
  bool hydrogens_present = true;
  std::vector<std::string> messages;
};

// Builds the topology. Protein mode (Structure::protein_mode): residue templates give types,
// charges and bonds; C(i)-N(i+1) is bonded when ≤ peptide_bond_max_nm, otherwise the chain breaks
// there. Other molecules: bonds from CONECT (or covalent radii r ≤ r_a + r_b + 0.045 nm if the file
// has none) and generic LJ types (docs/molecules.md), zero charges, no torsion terms.
// Throws StructureError with the file, residue and the missing/unknown atom names.
Topology build_topology(const Structure& s, const ff::ForceFieldParams& p,
                        const TopologyOptions& options = {});

}  // namespace haptree::mol
