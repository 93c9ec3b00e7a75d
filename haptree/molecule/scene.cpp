#include "haptree/molecule/scene.hpp"

#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>

#ifndef HAPTREE_SOURCE_DATA_DIR
#define HAPTREE_SOURCE_DATA_DIR ""
#endif

namespace haptree::mol {

namespace fs = std::filesystem;

std::string data_dir() {
  if (const char* env = std::getenv("HAPTREE_DATA_DIR"); env && *env) {
    if (!fs::is_directory(env))
      throw std::runtime_error(std::string("HAPTREE_DATA_DIR=") + env + " is not a directory");
    return env;
  }
  char buf[4096];
  const ssize_t len = ::readlink("/proc/self/exe", buf, sizeof(buf) - 1);
  if (len > 0) {
    buf[len] = '\0';
    const fs::path exe_dir = fs::path(buf).parent_path();
    for (const char* rel : {"../data", "../../data", "../share/haptree/data", "data"}) {
      const fs::path p = exe_dir / rel;
      if (fs::is_directory(p / "molecules")) return fs::weakly_canonical(p).string();
    }
  }
  const std::string src = HAPTREE_SOURCE_DATA_DIR;
  if (!src.empty() && fs::is_directory(fs::path(src) / "molecules")) return src;
  throw std::runtime_error(
      "haptree data directory not found: set HAPTREE_DATA_DIR to the folder holding molecules/");
}

std::vector<std::string> molecular_scene_names() {
  return {"bacteriorhodopsin", "bacteriorhodopsin-raw", "ala20", "polyaniline"};
}

std::string resolve_molecule_path(const std::string& n) {
  std::string file;
  if (n == "bacteriorhodopsin" || n == "bR" || n == "1c3w_protein_h") file = "1c3w_protein_h.pdb";
  else if (n == "bacteriorhodopsin-raw" || n == "1c3w") file = "1c3w.pdb";
  else if (n == "ala20" || n == "polyalanine") file = "ala20_helix_h.pdb";
  else if (n == "polyaniline" || n == "pani") file = "pani_leuco_20N_helix.pdb";
  if (!file.empty()) return (fs::path(data_dir()) / "molecules" / file).string();
  if (!fs::exists(n))
    throw std::runtime_error("molecule '" + n + "': not a scene name (bacteriorhodopsin, "
                             "bacteriorhodopsin-raw, ala20, polyaniline) nor an existing file");
  return n;
}

MolecularScene load_molecular_scene(const std::string& name_or_path, const SceneOptions& o) {
  MolecularScene sc;
  sc.path = resolve_molecule_path(name_or_path);
  sc.name = fs::exists(name_or_path) ? fs::path(name_or_path).stem().string() : name_or_path;
  sc.structure = read_structure(sc.path, o.read);
  const std::string ffp = o.force_field_path.empty()
                              ? (fs::path(data_dir()) / "molecules" / "ff14sb.dat").string()
                              : o.force_field_path;
  const ff::ForceFieldParams params = ff::load_force_field(ffp);
  sc.topology = build_topology(sc.structure, params, o.topology);
  sc.torsion = build_torsion_model(sc.structure, sc.topology, o.torsion);
  sc.model = sc.torsion.model;
  sc.messages = sc.structure.messages;
  sc.messages.insert(sc.messages.end(), sc.topology.messages.begin(), sc.topology.messages.end());
  sc.messages.push_back(std::to_string(sc.topology.natoms) + " atoms, " +
                        std::to_string(sc.torsion.joints.size()) + " torsional joints, " +
                        std::to_string(sc.torsion.nbodies) + " rigid bodies, " +
                        std::to_string(sc.torsion.roots.size()) + " segment root(s) attached by " +
                        joint_type_name(o.torsion.root_joint) + " joints; model DOF " +
                        std::to_string(sc.model->nv));
  if (o.with_force_field) {
    std::vector<Vec3> x0(sc.topology.natoms);
    for (int a = 0; a < sc.topology.natoms; ++a) x0[a] = sc.structure.atoms[a].pos;
    sc.force_field = std::make_unique<ff::Evaluator>(sc.topology, sc.torsion.atom_model_body,
                                                     sc.torsion.atom_local, x0, o.nonbonded);
  }
  return sc;
}

namespace {

void write_atoms(std::FILE* f, const Structure& s, const std::vector<Vec3>& x) {
  for (size_t a = 0; a < s.atoms.size(); ++a) {
    const AtomRecord& r = s.atoms[a];
    std::string nm = r.name;
    // PDB atom-name alignment: names shorter than 4 chars start in column 14 unless the element
    // symbol has two letters.
    char name[5];
    if (nm.size() < 4 && r.element.size() == 1) std::snprintf(name, sizeof name, " %-3s", nm.c_str());
    else std::snprintf(name, sizeof name, "%-4s", nm.substr(0, 4).c_str());
    const Vec3 p = x[a] * 10.0;
    std::fprintf(f, "%-6s%5d %4s %3s %1s%4d%c   %8.3f%8.3f%8.3f%6.2f%6.2f          %2s\n",
                 r.hetero ? "HETATM" : "ATOM", static_cast<int>((a + 1) % 100000), name,
                 r.resname.substr(0, 3).c_str(), r.chain.substr(0, 1).c_str(), r.resid % 10000,
                 r.icode ? r.icode : ' ', p.x(), p.y(), p.z(), 1.0, 0.0, r.element.c_str());
  }
}

// PDB's %8.3f columns hold -999.999 .. 9999.999 Å.
bool fits_pdb(double angstrom) { return angstrom > -999.9995 && angstrom < 9999.9995; }

// Quoted if needed (atom names such as H5' or names with spaces).
std::string cif_value(const std::string& v) {
  if (v.empty()) return ".";
  if (v.find_first_of(" '\"#") == std::string::npos && v[0] != '_' && v[0] != '$') return v;
  return v.find('"') == std::string::npos ? "\"" + v + "\"" : "'" + v + "'";
}

}  // namespace

int first_atom_outside_pdb_columns(const std::vector<Vec3>& x_nm) {
  for (size_t a = 0; a < x_nm.size(); ++a) {
    const Vec3 p = 10.0 * x_nm[a];
    if (!(fits_pdb(p.x()) && fits_pdb(p.y()) && fits_pdb(p.z()))) return static_cast<int>(a);
  }
  return -1;
}

static void require_pdb_columns(const std::string& path, const Structure& s, const std::vector<Vec3>& x) {
  const int a = first_atom_outside_pdb_columns(x);
  if (a < 0) return;
  char xyz[96];
  std::snprintf(xyz, sizeof xyz, "(%.3f, %.3f, %.3f) Å", 10 * x[a].x(), 10 * x[a].y(), 10 * x[a].z());
  throw std::runtime_error(path + ": atom " + std::to_string(a + 1) + " (" + s.atoms[a].name + " " + s.atoms[a].resname +
                           " " + std::to_string(s.atoms[a].resid) + ") at " + xyz +
                           " does not fit PDB's fixed coordinate columns (-999.999 .. 9999.999 Å); write mmCIF (.cif) "
                           "instead");
}

void write_mmcif(const std::string& path, const Structure& s, const std::vector<Vec3>& x) {
  if (x.size() != s.atoms.size()) throw std::invalid_argument(path + ": coordinate count differs from the atoms");
  std::FILE* f = std::fopen(path.c_str(), "w");
  if (!f) throw std::runtime_error(path + ": cannot open for writing");
  std::fprintf(f, "data_haptree\nloop_\n");
  for (const char* k : {"group_PDB", "id", "type_symbol", "label_atom_id", "label_alt_id", "label_comp_id",
                        "label_asym_id", "label_entity_id", "label_seq_id", "pdbx_PDB_ins_code", "Cartn_x", "Cartn_y",
                        "Cartn_z", "occupancy", "B_iso_or_equiv", "auth_seq_id", "auth_asym_id", "pdbx_PDB_model_num"})
    std::fprintf(f, "_atom_site.%s\n", k);
  for (size_t a = 0; a < s.atoms.size(); ++a) {
    const AtomRecord& r = s.atoms[a];
    const Vec3 p = x[a] * 10.0;
    const std::string chain = cif_value(r.chain.empty() ? "A" : r.chain);
    const std::string icode = r.icode && r.icode != ' ' ? std::string(1, r.icode) : "?";
    std::fprintf(f, "%s %zu %s %s . %s %s 1 %d %s %.4f %.4f %.4f %.2f 0.00 %d %s 1\n", r.hetero ? "HETATM" : "ATOM",
                 a + 1, cif_value(r.element).c_str(), cif_value(r.name).c_str(), cif_value(r.resname).c_str(),
                 chain.c_str(), r.resid, icode.c_str(), p.x(), p.y(), p.z(), r.occupancy, r.resid, chain.c_str());
  }
  const bool ok = std::fprintf(f, "#\n") > 0;
  if (std::fclose(f) != 0 || !ok) throw std::runtime_error(path + ": write failed");
}

PdbTrajectoryWriter::PdbTrajectoryWriter(const std::string& path, const Structure& s)
    : s_(s), out_(path), path_(path) {
  if (!out_) throw std::runtime_error(path + ": cannot open for writing");
  out_ << "REMARK   1 HAPTREE TRAJECTORY, " << s.atoms.size() << " ATOMS, SOURCE " << s.path << "\n";
}

void PdbTrajectoryWriter::write_frame(const std::vector<Vec3>& x) {
  if (x.size() != s_.atoms.size()) throw std::invalid_argument(path_ + ": frame size differs");
  require_pdb_columns(path_, s_, x);
  ++frames_;
  char line[32];
  std::snprintf(line, sizeof line, "MODEL     %4d\n", frames_ % 10000);
  out_ << line;
  // Format through a temporary FILE-less buffer: reuse write_atoms via fmemopen-free path.
  std::string buf;
  buf.reserve(x.size() * 81);
  char* mem = nullptr;
  size_t sz = 0;
  std::FILE* f = open_memstream(&mem, &sz);
  write_atoms(f, s_, x);
  std::fclose(f);
  out_.write(mem, static_cast<std::streamsize>(sz));
  std::free(mem);
  out_ << "ENDMDL\n";
  if (!out_) throw std::runtime_error(path_ + ": write failed");
}

void PdbTrajectoryWriter::close() {
  if (out_.is_open()) {
    out_ << "END\n";
    out_.close();
  }
}

PdbTrajectoryWriter::~PdbTrajectoryWriter() {
  try { close(); } catch (...) {}
}

void write_pdb(const std::string& path, const Structure& s, const std::vector<Vec3>& x) {
  require_pdb_columns(path, s, x);
  std::FILE* f = std::fopen(path.c_str(), "w");
  if (!f) throw std::runtime_error(path + ": cannot open for writing");
  write_atoms(f, s, x);
  for (const auto& [a, b] : s.conect) std::fprintf(f, "CONECT%5d%5d\n", a + 1, b + 1);
  std::fprintf(f, "END\n");
  std::fclose(f);
}

}  // namespace haptree::mol
