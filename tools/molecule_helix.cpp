// Writes an ideal ACE-(ALA)n-NME peptide (α-helix by default) with hydrogens as PDB, or as mmCIF when the
// output ends in .cif / --format cif, or when the helix does not fit PDB's fixed coordinate columns.
//   molecule_helix --residues 20 --phi-deg -57 --psi-deg -47 --out ala20.pdb
#include <cstdio>
#include <string>

#include <CLI/CLI.hpp>

#include "haptree/molecule/builder.hpp"
#include "haptree/molecule/scene.hpp"

namespace {
bool ends_with(const std::string& s, const std::string& t) {
  return s.size() >= t.size() && s.compare(s.size() - t.size(), t.size(), t) == 0;
}
}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"ideal ACE-(ALA)n-NME builder (PDB or mmCIF out, Å)"};
  int n = 20;
  double phi = -57, psi = -47, omega = 180;
  std::string out = "ala_helix.pdb", format = "auto";
  app.add_option("--residues", n, "number of alanines")->check(CLI::Range(1, 100000))->capture_default_str();
  app.add_option("--phi-deg", phi, "backbone φ (deg)")->capture_default_str();
  app.add_option("--psi-deg", psi, "backbone ψ (deg)")->capture_default_str();
  app.add_option("--omega-deg", omega, "peptide ω (deg)")->capture_default_str();
  app.add_option("--out", out, "output file (.pdb or .cif)")->capture_default_str();
  app.add_option("--format", format,
                 "auto: mmCIF if --out ends in .cif, else PDB unless a coordinate does not fit PDB's fixed "
                 "columns (-999.999 .. 9999.999 Å), then mmCIF next to it (<out>.cif); pdb: PDB or an error; cif")
      ->check(CLI::IsMember({"auto", "pdb", "cif"}))
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  try {
    const auto s = haptree::mol::build_alanine_helix(n, phi, psi, omega);
    std::vector<haptree::Vec3> x(s.atoms.size());
    for (size_t i = 0; i < x.size(); ++i) x[i] = s.atoms[i].pos;
    bool cif = format == "cif" || (format == "auto" && (ends_with(out, ".cif") || ends_with(out, ".mmcif")));
    const int bad = haptree::mol::first_atom_outside_pdb_columns(x);
    if (!cif && bad >= 0 && format == "auto") {
      const std::string stem = ends_with(out, ".pdb") ? out.substr(0, out.size() - 4) : out;
      std::fprintf(stderr,
                   "molecule_helix: atom %d at (%.3f, %.3f, %.3f) Å does not fit PDB's fixed coordinate columns; "
                   "writing mmCIF to %s.cif instead of %s\n",
                   bad + 1, 10 * x[bad].x(), 10 * x[bad].y(), 10 * x[bad].z(), stem.c_str(), out.c_str());
      out = stem + ".cif";
      cif = true;
    }
    if (cif) haptree::mol::write_mmcif(out, s, x);
    else haptree::mol::write_pdb(out, s, x);   // throws, naming the atom, if it does not fit
    std::printf("%s: %zu atoms, %d residues + caps, %d torsional DOF (phi, psi), %s\n", out.c_str(), s.atoms.size(),
                n, 2 * n, cif ? "mmCIF" : "PDB");
  } catch (const std::exception& e) {
    std::fprintf(stderr, "molecule_helix: %s\n", e.what());
    return 1;
  }
  return 0;
}
