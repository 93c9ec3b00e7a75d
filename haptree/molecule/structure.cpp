#include "haptree/molecule/structure.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <unordered_map>

#include <gemmi/pdb.hpp>
#if __has_include(<tao/pegtl.hpp>)
#include <gemmi/cif.hpp>
#include <gemmi/mmcif.hpp>
#define HAPTREE_HAVE_MMCIF 1
#endif

namespace haptree::mol {

namespace {

std::string trim(const std::string& s) {
  size_t a = 0, b = s.size();
  while (a < b && std::isspace(static_cast<unsigned char>(s[a]))) ++a;
  while (b > a && std::isspace(static_cast<unsigned char>(s[b - 1]))) --b;
  return s.substr(a, b - a);
}

std::string upper(std::string s) {
  for (char& c : s) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  return s;
}

bool ends_with_ci(const std::string& s, const std::string& suf) {
  if (s.size() < suf.size()) return false;
  return upper(s.substr(s.size() - suf.size())) == upper(suf);
}

const std::set<std::string>& protein_names() {
  static const std::set<std::string> names = {
      "ALA", "ARG", "ASN", "ASP", "ASH", "CYS", "CYX", "CYM", "GLN", "GLU", "GLH", "GLY",
      "HIS", "HID", "HIE", "HIP", "HYP", "ILE", "LEU", "LYS", "LYN", "MET", "PHE", "PRO",
      "SER", "THR", "TRP", "TYR", "VAL", "ACE", "NME", "NHE"};
  return names;
}

// A fixed-column field (0-based start, width) that must hold one number, nothing else.
bool number_field(const std::string& line, size_t start, size_t width, bool required) {
  if (line.size() <= start) return !required;
  const std::string f = trim(line.substr(start, width));
  if (f.empty()) return !required;
  char* end = nullptr;
  const double v = std::strtod(f.c_str(), &end);
  return end && *end == '\0' && std::isfinite(v);
}

// x, y, z in columns 31-38, 39-46, 47-54 (and occupancy 55-60, B 61-66 when present) must each hold one
// number. A coordinate wider than 8 characters (>= 10000 Å or <= -1000 Å) shifts the columns: gemmi would
// read the pieces as other numbers, so the line is an error.
void check_coordinate_columns(const std::string& path, int ln, const std::string& line) {
  const bool ok = number_field(line, 30, 8, true) && number_field(line, 38, 8, true) &&
                  number_field(line, 46, 8, true) && number_field(line, 54, 6, false) &&
                  number_field(line, 60, 6, false);
  if (ok) return;
  auto col = [&line](size_t a, size_t w) { return line.size() > a ? line.substr(a, w) : std::string(); };
  throw StructureError(path + ":" + std::to_string(ln) + ": coordinate columns do not hold numbers (x '" +
                       col(30, 8) + "', y '" + col(38, 8) + "', z '" + col(46, 8) + "', occupancy '" + col(54, 6) +
                       "'): a coordinate wider than PDB's 8 columns (outside -999.999 .. 9999.999 Å) or a "
                       "misaligned line. Line: '" + line + "'. Write such structures as mmCIF (.cif)");
}

struct LineInfo {
  int line;
  std::string record;
};

// Scans the PDB text once for what gemmi 0.5.7 does not give us: the line of every ATOM/HETATM
// serial and the CONECT records. Also returns the text gemmi reads, every line padded with blanks to
// PDB's 80 columns: gemmi reads some fixed columns past the end of a short line (a LINK record of
// 74-77 columns: its distance field at columns 74-78, found by the fuzz smoke run under ASan), and
// trailing blanks are what a short line means in PDB. A NUL byte is refused (gemmi would stop there).
void scan_pdb_text(const std::string& path, std::unordered_map<int, int>& serial_line,
                   std::vector<std::pair<int, std::vector<int>>>& conect,
                   std::vector<int>& conect_lines, std::string& padded) {
  std::ifstream in(path);
  if (!in) throw StructureError(path + ": cannot open file");
  std::string line;
  int ln = 0;
  bool in_first_model = true, seen_model = false;
  padded.clear();
  while (std::getline(in, line)) {
    ++ln;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    // gemmi keeps a record as a C string: a NUL would cut it short of the padding below.
    if (line.find('\0') != std::string::npos)
      throw StructureError(path + ":" + std::to_string(ln) + ": NUL byte at column " +
                           std::to_string(line.find('\0') + 1) + " (a PDB file is text)");
    // gemmi reads 120 columns of a line and skips the rest with a loop that stops early at a byte >= 0x80
    // (it reads bytes as signed char): the rest would become a record of its own, unpadded (a short LINK
    // was read past its end under ASan) or even an extra atom. The columns past 120 are cut here instead.
    constexpr size_t kGemmiColumns = 120;
    padded.append(line, 0, std::min(line.size(), kGemmiColumns));
    if (line.size() < 80) padded.append(80 - line.size(), ' ');
    padded += '\n';
    const std::string rec = line.substr(0, 6);
    if (rec == "MODEL ") {
      if (seen_model) in_first_model = false;
      seen_model = true;
    }
    if ((rec == "ATOM  " || rec == "HETATM") && in_first_model && line.size() >= 11) {
      check_coordinate_columns(path, ln, line);
      const std::string s = trim(line.substr(6, 5));
      char* end = nullptr;
      const long v = std::strtol(s.c_str(), &end, 10);
      if (!s.empty() && end && *end == '\0') serial_line.emplace(static_cast<int>(v), ln);
    } else if (rec == "CONECT") {
      std::vector<int> nums;
      // Fixed columns 7-11, 12-16, 17-21, 22-26, 27-31 (serials up to 99999).
      for (size_t c = 6; c + 5 <= std::max<size_t>(line.size(), 11) && c < 31; c += 5) {
        if (c >= line.size()) break;
        const std::string f = trim(line.substr(c, std::min<size_t>(5, line.size() - c)));
        if (f.empty()) continue;
        char* end = nullptr;
        const long v = std::strtol(f.c_str(), &end, 10);
        if (!end || *end != '\0')
          throw StructureError(path + ":" + std::to_string(ln) + ": malformed CONECT record '" +
                               line + "' (field '" + f + "' is not an atom serial number)");
        nums.push_back(static_cast<int>(v));
      }
      if (nums.size() < 2)
        throw StructureError(path + ":" + std::to_string(ln) +
                             ": CONECT record names no bonded atom: '" + line + "'");
      conect.emplace_back(nums[0], std::vector<int>(nums.begin() + 1, nums.end()));
      conect_lines.push_back(ln);
    }
  }
}

std::string element_of(const gemmi::Atom& a) {
  std::string e = a.element == gemmi::El::X ? std::string() : upper(a.element.name());
  if (!e.empty()) return e;
  // Fall back to the first letter of the name (PDB convention for C/N/O/H/S).
  for (char c : a.name)
    if (std::isalpha(static_cast<unsigned char>(c))) return std::string(1, static_cast<char>(std::toupper(c)));
  return "X";
}

}  // namespace

std::string ResidueRecord::label() const {
  std::string s = name + " " + chain + " " + std::to_string(resid);
  if (icode != ' ' && icode != '\0') s += icode;
  return s;
}

bool Structure::has_hydrogens() const {
  for (const auto& a : atoms)
    if (a.element == "H" || a.element == "D") return true;
  return false;
}

std::string Structure::atom_label(int i) const {
  const AtomRecord& a = atoms.at(static_cast<size_t>(i));
  std::string s = a.name + " " + a.resname + " " + a.chain + " " + std::to_string(a.resid);
  if (a.line > 0) s += " (line " + std::to_string(a.line) + ")";
  return s;
}

void check_no_coincident_atoms(const Structure& s, double min_distance_nm) {
  // Sort and sweep along x: only pairs closer than min_distance_nm in x are compared.
  const int n = static_cast<int>(s.atoms.size());
  std::vector<int> order(static_cast<size_t>(n));
  for (int i = 0; i < n; ++i) order[static_cast<size_t>(i)] = i;
  std::sort(order.begin(), order.end(), [&s](int a, int b) { return s.atoms[a].pos.x() < s.atoms[b].pos.x(); });
  const double d2 = min_distance_nm * min_distance_nm;
  for (int i = 0; i < n; ++i) {
    const Vec3& p = s.atoms[order[i]].pos;
    for (int j = i + 1; j < n && s.atoms[order[j]].pos.x() - p.x() < min_distance_nm; ++j) {
      const double r2 = (s.atoms[order[j]].pos - p).squaredNorm();
      if (r2 >= d2) continue;
      const int a = std::min(order[i], order[j]), b = std::max(order[i], order[j]);
      char dist[96];
      std::snprintf(dist, sizeof dist, "%.4f Å apart (closer than %.3g Å)", 10.0 * std::sqrt(r2), 10.0 * min_distance_nm);
      throw StructureError(s.path + ": atoms " + s.atom_label(a) + " and " + s.atom_label(b) + " are " + dist +
                           ": coincident atoms make the force field unbounded; remove the duplicate or fix "
                           "its coordinates");
    }
  }
}

bool is_protein_residue_name(const std::string& n) { return protein_names().count(n) > 0; }
bool is_water_residue_name(const std::string& n) {
  return n == "HOH" || n == "WAT" || n == "H2O" || n == "DOD" || n == "SOL" || n == "TIP3";
}

Structure read_structure(const std::string& path, const ReadOptions& opt) {
  Structure out;
  out.path = path;
  const bool cif = ends_with_ci(path, ".cif") || ends_with_ci(path, ".mmcif");
  {
    std::ifstream probe(path);
    if (!probe) throw StructureError(path + ": cannot open file");
  }
  gemmi::Structure st;
  std::unordered_map<int, int> serial_line;
  std::vector<std::pair<int, std::vector<int>>> conect_raw;
  std::vector<int> conect_lines;
  try {
    if (cif) {
#ifdef HAPTREE_HAVE_MMCIF
      st = gemmi::make_structure(gemmi::cif::read_file(path));
#else
      throw StructureError(path + ": mmCIF support was not compiled in (install tao-pegtl-dev)");
#endif
    } else {
      std::string text;
      scan_pdb_text(path, serial_line, conect_raw, conect_lines, text);
      st = gemmi::read_pdb_string(text, path);
    }
  } catch (const StructureError&) {
    throw;
  } catch (const std::exception& e) {
    throw StructureError(path + ": " + e.what());
  }
  if (st.models.empty() || st.models[0].chains.empty())
    throw StructureError(path + ": no atoms found (no ATOM/HETATM records in the first model)");
  gemmi::Model& model = st.models[0];
  if (st.models.size() > 1)
    out.messages.push_back("file has " + std::to_string(st.models.size()) +
                           " models; using the first");

  // Protein mode if any residue is a known polymer residue.
  for (const auto& ch : model.chains)
    for (const auto& r : ch.residues)
      if (is_protein_residue_name(r.name)) out.protein_mode = true;

  std::map<std::string, int> dropped_names;
  std::unordered_map<int, int> serial_to_index;
  for (const auto& ch : model.chains) {
    for (const auto& r : ch.residues) {
      const bool water = is_water_residue_name(r.name);
      const bool keep = water ? opt.keep_water
                              : (!out.protein_mode || is_protein_residue_name(r.name) ||
                                 opt.keep_hetero);
      if (!keep) {
        if (water) ++out.dropped_waters;
        else ++out.dropped_hetero_residues, out.dropped_hetero_atoms += static_cast<int>(r.atoms.size());
        if (!water) ++dropped_names[r.name];
        continue;
      }
      ResidueRecord rr;
      rr.name = r.name;
      rr.chain = ch.name;
      rr.resid = r.seqid.num.has_value() ? r.seqid.num.value : 0;
      rr.icode = r.seqid.icode;
      rr.hetero = r.het_flag == 'H';
      rr.first_atom = static_cast<int>(out.atoms.size());
      // Alternate locations: per atom name keep the highest occupancy (first on ties).
      std::vector<int> chosen;   // indices into r.atoms
      std::map<std::string, int> by_name;
      for (size_t k = 0; k < r.atoms.size(); ++k) {
        const gemmi::Atom& a = r.atoms[k];
        auto it = by_name.find(a.name);
        if (it == by_name.end()) {
          by_name[a.name] = static_cast<int>(chosen.size());
          chosen.push_back(static_cast<int>(k));
          continue;
        }
        const gemmi::Atom& prev = r.atoms[chosen[it->second]];
        if (!a.altloc && !prev.altloc) {
          const int ln = serial_line.count(a.serial) ? serial_line[a.serial] : 0;
          throw StructureError(path + (ln ? ":" + std::to_string(ln) : std::string()) +
                               ": duplicate atom " + a.name + " in residue " + rr.label() +
                               " (no alternate-location indicator)");
        }
        ++out.dropped_altloc_atoms;
        if (a.occ > prev.occ) chosen[it->second] = static_cast<int>(k);
      }
      for (int k : chosen) {
        const gemmi::Atom& a = r.atoms[k];
        AtomRecord ar;
        ar.name = a.name;
        ar.element = element_of(a);
        ar.resname = rr.name;
        ar.chain = rr.chain;
        ar.resid = rr.resid;
        ar.icode = rr.icode;
        ar.hetero = rr.hetero;
        ar.serial = a.serial;
        ar.line = serial_line.count(a.serial) ? serial_line[a.serial] : 0;
        ar.occupancy = a.occ;
        ar.pos = Vec3(a.pos.x, a.pos.y, a.pos.z) * 0.1;   // Å -> nm
        if (!ar.pos.allFinite() || ar.pos.cwiseAbs().maxCoeff() > 1e5)
          throw StructureError(path + (ar.line ? ":" + std::to_string(ar.line) : std::string()) +
                               ": atom " + ar.name + " of residue " + rr.label() +
                               " has invalid coordinates");
        if (a.serial) serial_to_index[a.serial] = static_cast<int>(out.atoms.size());
        out.atoms.push_back(std::move(ar));
      }
      rr.natoms = static_cast<int>(out.atoms.size()) - rr.first_atom;
      if (rr.natoms > 0) out.residues.push_back(rr);
    }
  }
  if (out.atoms.empty())
    throw StructureError(path + ": no atoms left after dropping waters and hetero groups");

  // CONECT: bonds between kept atoms (bonds to dropped atoms are ignored).
  std::set<std::pair<int, int>> bonds;
  for (size_t c = 0; c < conect_raw.size(); ++c) {
    const int s0 = conect_raw[c].first;
    if (!serial_line.count(s0))
      throw StructureError(path + ":" + std::to_string(conect_lines[c]) + ": CONECT names atom " +
                           std::to_string(s0) + " which is not in the file");
    for (int s1 : conect_raw[c].second) {
      if (!serial_line.count(s1))
        throw StructureError(path + ":" + std::to_string(conect_lines[c]) +
                             ": CONECT names atom " + std::to_string(s1) +
                             " which is not in the file");
      auto a = serial_to_index.find(s0), b = serial_to_index.find(s1);
      if (a == serial_to_index.end() || b == serial_to_index.end()) continue;
      if (a->second == b->second)
        throw StructureError(path + ":" + std::to_string(conect_lines[c]) +
                             ": CONECT bonds atom " + std::to_string(s0) + " to itself");
      bonds.emplace(std::min(a->second, b->second), std::max(a->second, b->second));
    }
  }
  out.conect.assign(bonds.begin(), bonds.end());
  check_no_coincident_atoms(out);

  if (out.dropped_waters)
    out.messages.push_back("dropped " + std::to_string(out.dropped_waters) + " water residues");
  if (out.dropped_hetero_residues) {
    std::string s = "dropped " + std::to_string(out.dropped_hetero_residues) +
                    " hetero residues (" + std::to_string(out.dropped_hetero_atoms) +
                    " atoms) not in the protein model:";
    for (const auto& [n, c] : dropped_names) s += " " + n + "x" + std::to_string(c);
    out.messages.push_back(s);
  }
  if (out.dropped_altloc_atoms)
    out.messages.push_back("dropped " + std::to_string(out.dropped_altloc_atoms) +
                           " alternate-location atoms (kept the highest occupancy)");
  return out;
}

}  // namespace haptree::mol
