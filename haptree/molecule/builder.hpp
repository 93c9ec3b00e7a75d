// Ideal-geometry builders for test molecules (the geometry of data/molecules/tools/build_models.py).
#pragma once

#include "haptree/molecule/structure.hpp"

namespace haptree::mol {

// ACE-(ALA)n-NME with all hydrogens (ff14SB names), Engh & Huber bond lengths and angles, torsions
// φ, ψ, ω (degrees) for every residue; -57/-47/180 = ideal right-handed α-helix. Heavy atoms are
// placed exactly as the shipped ala20_helix_h.pdb (NeRF from the same origin); hydrogens by ideal
// rules: amide H on the bisector of C–N–Cα (1.01 Å), Hα tetrahedral (1.09 Å), methyl H staggered
// (1.09 Å, 109.5°). Positions in nm. n ≥ 1; n residues give 2n torsional DOF.
Structure build_alanine_helix(int n, double phi_deg = -57.0, double psi_deg = -47.0,
                              double omega_deg = 180.0);

}  // namespace haptree::mol
