// Writes an ideal ACE-(ALA)n-NME peptide (α-helix by default) with hydrogens as PDB.
//   molecule_helix --residues 20 --phi-deg -57 --psi-deg -47 --out ala20.pdb
#include <cstdio>
#include <string>

#include <CLI/CLI.hpp>

#include "haptree/molecule/builder.hpp"
#include "haptree/molecule/scene.hpp"

int main(int argc, char** argv) {
  CLI::App app{"ideal ACE-(ALA)n-NME builder (PDB out, Å)"};
  int n = 20;
  double phi = -57, psi = -47, omega = 180;
  std::string out = "ala_helix.pdb";
  app.add_option("--residues", n, "number of alanines")->capture_default_str();
  app.add_option("--phi-deg", phi, "backbone φ (deg)")->capture_default_str();
  app.add_option("--psi-deg", psi, "backbone ψ (deg)")->capture_default_str();
  app.add_option("--omega-deg", omega, "peptide ω (deg)")->capture_default_str();
  app.add_option("--out", out, "output PDB")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  try {
    const auto s = haptree::mol::build_alanine_helix(n, phi, psi, omega);
    std::vector<haptree::Vec3> x(s.atoms.size());
    for (size_t i = 0; i < x.size(); ++i) x[i] = s.atoms[i].pos;
    haptree::mol::write_pdb(out, s, x);
    std::printf("%s: %zu atoms, %d residues + caps, %d torsional DOF (phi, psi)\n", out.c_str(),
                s.atoms.size(), n, 2 * n);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "molecule_helix: %s\n", e.what());
    return 1;
  }
  return 0;
}
