// Long helices overflow PDB's fixed coordinate columns. The writers refuse (naming the
// atom) and molecule_helix writes mmCIF instead; the PDB reader treats shifted columns as an error naming
// the line; two coincident atoms are refused at load time, naming both.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "haptree/molecule/builder.hpp"
#include "haptree/molecule/scene.hpp"

namespace haptree::mol {
namespace {

std::vector<Vec3> positions(const Structure& s) {
  std::vector<Vec3> x(s.atoms.size());
  for (size_t i = 0; i < x.size(); ++i) x[i] = s.atoms[i].pos;
  return x;
}

std::vector<std::string> lines_of(const std::string& path) {
  std::ifstream in(path);
  std::vector<std::string> v;
  for (std::string l; std::getline(in, l);) v.push_back(l);
  return v;
}

void write_lines(const std::string& path, const std::vector<std::string>& v) {
  std::ofstream out(path);
  for (const auto& l : v) out << l << "\n";
}

std::string load_error(const std::string& path) {
  try {
    read_structure(path);
  } catch (const StructureError& e) {
    return e.what();
  }
  return "";
}

TEST(MoleculeColumns, LongHelixGoesToMmcifAndLoadsAsOneSegment) {
  const Structure s = build_alanine_helix(1000);
  const std::vector<Vec3> x = positions(s);
  const int bad = first_atom_outside_pdb_columns(x);
  ASSERT_GE(bad, 0) << "a 1000-residue helix is 1500 Å long: it cannot fit";
  const std::string dir = ::testing::TempDir();
  try {
    write_pdb(dir + "helix1000.pdb", s, x);
    ADD_FAILURE() << "write_pdb wrote coordinates that overflow the columns";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("atom " + std::to_string(bad + 1) + " ("), std::string::npos) << e.what();
  }
  write_mmcif(dir + "helix1000.cif", s, x);
  SceneOptions o;
  o.with_force_field = false;
  const MolecularScene sc = load_molecular_scene(dir + "helix1000.cif", o);
  EXPECT_EQ(sc.natoms(), static_cast<int>(s.atoms.size()));
  EXPECT_EQ(sc.dof(), 2000);
  EXPECT_EQ(sc.torsion.roots.size(), 1u);
  // The atoms come back where they were written (mmCIF keeps 4 decimals in Å: 5e-5 Å = 5e-6 nm).
  double dmax = 0;
  for (size_t i = 0; i < x.size(); ++i) dmax = std::max(dmax, (sc.structure.atoms[i].pos - x[i]).cwiseAbs().maxCoeff());
  EXPECT_LE(dmax, 5e-6 + 1e-12);
}

TEST(MoleculeColumns, MoleculeHelixWritesMmcifWhenPdbCannotHoldIt) {
  const std::string dir = ::testing::TempDir();
  const std::string pdb = dir + "helix_tool.pdb", cif = dir + "helix_tool.cif";
  std::remove(pdb.c_str());
  std::remove(cif.c_str());
  const std::string cmd = std::string(HAPTREE_MOLECULE_HELIX) + " --residues 1000 --out " + pdb + " 2>&1";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  EXPECT_EQ(::access(cif.c_str(), F_OK), 0) << "no mmCIF written";
  EXPECT_NE(::access(pdb.c_str(), F_OK), 0) << "a PDB with overflowing columns was written";
  const std::string strict = std::string(HAPTREE_MOLECULE_HELIX) + " --residues 1000 --format pdb --out " + pdb + " 2>&1";
  const int st = std::system(strict.c_str());
  EXPECT_TRUE(WIFEXITED(st) && WEXITSTATUS(st) == 1);
  EXPECT_NE(::access(pdb.c_str(), F_OK), 0);
}

// The line the old writer produced for atom 9092 of the 1000-residue helix: y takes 9 characters and
// pushes z into the occupancy column.
TEST(MoleculeColumns, ShiftedCoordinateColumnsAreAnErrorNamingTheLine) {
  const Structure s = build_alanine_helix(2);
  const std::string path = ::testing::TempDir() + "shifted.pdb";
  write_pdb(path, s, positions(s));
  std::vector<std::string> v = lines_of(path);
  ASSERT_GE(v.size(), 10u);
  const int line = 7;   // 1-based, an ATOM/HETATM record
  std::string& l = v[line - 1];
  ASSERT_TRUE(l.rfind("ATOM", 0) == 0 || l.rfind("HETATM", 0) == 0) << l;
  char xyz[40];
  std::snprintf(xyz, sizeof xyz, "%8.3f%8.3f%8.3f", 993.997, -1000.405, 150.505);
  l = l.substr(0, 30) + xyz + l.substr(54);
  write_lines(path, v);
  const std::string err = load_error(path);
  EXPECT_NE(err.find(path + ":" + std::to_string(line) + ": coordinate columns"), std::string::npos) << err;
}

TEST(MoleculeColumns, CoincidentAtomsAreRefusedNamingBoth) {
  const Structure s = build_alanine_helix(2);
  std::vector<Vec3> x = positions(s);
  const int a = 3, b = 9;   // atoms 4 and 10 of the file (lines 4 and 10)
  x[b] = x[a];
  const std::string path = ::testing::TempDir() + "coincident.pdb";
  write_pdb(path, s, x);
  const std::string err = load_error(path);
  EXPECT_NE(err.find("atoms " + s.atoms[a].name), std::string::npos) << err;
  EXPECT_NE(err.find("(line 4) and " + s.atoms[b].name), std::string::npos) << err;
  EXPECT_NE(err.find("(line 10) are 0.0000 Å apart"), std::string::npos) << err;
}

}  // namespace
}  // namespace haptree::mol
