// Fuzz target: the mmCIF reader (read_structure on a .cif path: gemmi's CIF parser and mmCIF model).
#define HAPTREE_FUZZ_SUFFIX ".cif"
#include "structure_pdb.cpp"
