// Fuzz target: the PDB reader (haptree/molecule/structure.*: our line scan for serials and CONECT, then
// gemmi). Any input must either give a Structure whose indices are consistent or throw StructureError.
#include "fuzz/fuzz_target.hpp"
#include "haptree/molecule/structure.hpp"

#ifndef HAPTREE_FUZZ_SUFFIX
#define HAPTREE_FUZZ_SUFFIX ".pdb"
#endif

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static haptree::fuzz::ScratchFile file(HAPTREE_FUZZ_SUFFIX);
  const std::string& path = file.write(data, size);
  for (const bool keep : {false, true}) {
    haptree::mol::ReadOptions opt;
    opt.keep_hetero = opt.keep_water = keep;
    try {
      const haptree::mol::Structure s = haptree::mol::read_structure(path, opt);
      FUZZ_CHECK(!s.atoms.empty());
      int n = 0;
      for (const auto& r : s.residues) {
        FUZZ_CHECK(r.first_atom == n && r.natoms > 0);
        n += r.natoms;
      }
      FUZZ_CHECK(n == static_cast<int>(s.atoms.size()));
      for (const auto& [i, j] : s.conect) FUZZ_CHECK(0 <= i && i < j && j < n);
      for (const auto& a : s.atoms) FUZZ_CHECK(a.pos.allFinite());
    } catch (const haptree::mol::StructureError&) {
      // a clear refusal is a correct answer
    }
  }
  return 0;
}
