#include "haptree/molecule/topology.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <set>
#include <sstream>

namespace haptree::ff {

int ResidueTemplate::find(const std::string& n) const {
  for (size_t k = 0; k < atoms.size(); ++k)
    if (atoms[k].name == n) return static_cast<int>(k);
  return -1;
}

int ForceFieldParams::type_id(const std::string& name) const {
  auto it = type_index.find(name);
  if (it == type_index.end()) throw std::runtime_error(source + ": unknown atom type " + name);
  return it->second;
}

ForceFieldParams load_force_field(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error(path + ": cannot open force-field table");
  ForceFieldParams p;
  p.source = path;
  std::string line;
  int ln = 0;
  ResidueTemplate* cur = nullptr;
  auto fail = [&](const std::string& what) {
    throw std::runtime_error(path + ":" + std::to_string(ln) + ": " + what + " in '" + line + "'");
  };
  while (std::getline(in, line)) {
    ++ln;
    if (line.empty() || line[0] == '#') continue;
    std::istringstream ss(line);
    std::string key;
    ss >> key;
    if (key == "scale14") {
      if (!(ss >> p.coulomb14scale >> p.lj14scale)) fail("bad scale14 record");
    } else if (key == "type") {
      AtomType t;
      if (!(ss >> t.name >> t.cls >> t.element >> t.mass >> t.sigma >> t.epsilon)) fail("bad type record");
      p.type_index[t.name] = static_cast<int>(p.types.size());
      p.types.push_back(t);
    } else if (key == "residue") {
      std::string n;
      if (!(ss >> n)) fail("bad residue record");
      cur = &p.templates[n];
      cur->name = n;
    } else if (key == "atom" || key == "bond" || key == "external") {
      if (!cur) fail("record outside a residue");
      if (key == "atom") {
        TemplateAtom a;
        std::string tn;
        if (!(ss >> a.name >> tn >> a.charge)) fail("bad atom record");
        auto it = p.type_index.find(tn);
        if (it == p.type_index.end()) fail("unknown type " + tn);
        a.type = it->second;
        cur->atoms.push_back(a);
      } else if (key == "bond") {
        std::string a, b;
        if (!(ss >> a >> b)) fail("bad bond record");
        const int ia = cur->find(a), ib = cur->find(b);
        if (ia < 0 || ib < 0) fail("bond names an unknown atom");
        cur->bonds.emplace_back(ia, ib);
      } else {
        std::string a;
        if (!(ss >> a) || cur->find(a) < 0) fail("bad external record");
        cur->external.push_back(cur->find(a));
      }
    } else if (key == "end") {
      cur = nullptr;
    } else if (key == "proper") {
      ProperDef d;
      for (int k = 0; k < 4; ++k) {
        std::string t;
        if (!(ss >> t)) fail("bad proper record");
        if (t == "*") d.type[k] = -1;
        else {
          auto it = p.type_index.find(t);
          if (it == p.type_index.end()) fail("unknown type " + t);
          d.type[k] = it->second;
        }
      }
      int n = 0;
      if (!(ss >> n) || n < 1 || n > 6) fail("bad number of terms");
      for (int k = 0; k < n; ++k) {
        TorsionTerm t;
        if (!(ss >> t.periodicity >> t.phase >> t.k)) fail("bad torsion term");
        d.terms.push_back(t);
      }
      p.propers.push_back(std::move(d));
    } else {
      fail("unknown record '" + key + "'");
    }
  }
  if (p.types.empty() || p.templates.empty()) throw std::runtime_error(path + ": empty force-field table");
  return p;
}

}  // namespace haptree::ff

namespace haptree::mol {

namespace {

using ff::ForceFieldParams;
using ff::ResidueTemplate;

std::vector<std::string> aliases(const std::string& res, const std::string& n) {
  if (res == "ACE" || res == "NME") {
    if (n == "H1" || n == "1H") return {"HH31"};
    if (n == "H2" || n == "2H") return {"HH32"};
    if (n == "H3" || n == "3H") return {"HH33"};
    if (n == "C" && res == "NME") return {"CH3"};
    if (n == "CA" && res == "NME") return {"CH3"};
  }
  if (n == "H") return {"H1"};
  if (n == "HN") return {"H", "H1"};
  if (n == "1H" || n == "HN1" || n == "HT1") return {"H1", "H"};
  if (n == "2H" || n == "HN2" || n == "HT2") return {"H2"};
  if (n == "3H" || n == "HN3" || n == "HT3") return {"H3"};
  if (n == "O1" || n == "OT1" || n == "OC1" || n == "OCT1") return {"O"};
  if (n == "O2" || n == "OT2" || n == "OC2" || n == "OCT2" || n == "OT") return {"OXT"};
  return {};
}

double covalent_radius_nm(const std::string& e) {
  if (e == "H") return 0.031;
  if (e == "C") return 0.076;
  if (e == "N") return 0.071;
  if (e == "O") return 0.066;
  if (e == "S") return 0.105;
  if (e == "P") return 0.107;
  return 0.075;
}

double element_mass(const std::string& e) {
  static const std::map<std::string, double> m = {{"H", 1.008},  {"C", 12.01}, {"N", 14.01},
                                                   {"O", 16.0},   {"S", 32.06}, {"P", 30.97},
                                                   {"D", 2.014}};
  auto it = m.find(e);
  if (it == m.end()) throw std::runtime_error("no mass for element " + e);
  return it->second;
}

bool has_atom(const Structure& s, const ResidueRecord& r, const std::string& n) {
  for (int a = r.first_atom; a < r.first_atom + r.natoms; ++a)
    if (s.atoms[a].name == n) return true;
  return false;
}
int atom_in(const Structure& s, const ResidueRecord& r, const std::string& n) {
  for (int a = r.first_atom; a < r.first_atom + r.natoms; ++a)
    if (s.atoms[a].name == n) return a;
  return -1;
}

}  // namespace

Topology build_topology(const Structure& s, const ForceFieldParams& p, const TopologyOptions& opt) {
  Topology t;
  const int n = static_cast<int>(s.atoms.size());
  t.natoms = n;
  t.mass.assign(n, 0);
  t.charge.assign(n, 0);
  t.sigma.assign(n, 0);
  t.epsilon.assign(n, 0);
  t.atom_class.assign(n, "");
  t.heavy.assign(n, true);
  t.atom_residue.assign(n, -1);
  t.residue_template.assign(s.residues.size(), "");
  std::vector<int> atom_type(n, -1);
  for (size_t r = 0; r < s.residues.size(); ++r)
    for (int a = s.residues[r].first_atom; a < s.residues[r].first_atom + s.residues[r].natoms; ++a)
      t.atom_residue[a] = static_cast<int>(r);
  for (int a = 0; a < n; ++a) t.heavy[a] = !(s.atoms[a].element == "H" || s.atoms[a].element == "D");
  t.hydrogens_present = s.has_hydrogens();
  if (!t.hydrogens_present && opt.require_hydrogens)
    throw StructureError(s.path + ": the structure has no hydrogen atoms; the all-atom force field "
                                  "needs them (add hydrogens first, e.g. with PDBFixer or pdb2pqr, "
                                  "or set TopologyOptions::require_hydrogens = false for a heavy-atom model)");
  std::set<std::pair<int, int>> bonds;
  auto add_bond = [&](int a, int b) { bonds.emplace(std::min(a, b), std::max(a, b)); };
  const auto& R = s.residues;
  std::vector<bool> templated(R.size(), false);

  if (s.protein_mode) {
    t.typed_by_templates = true;
    // Peptide links and chain breaks (geometric).
    std::vector<bool> linked_prev(R.size(), false), linked_next(R.size(), false);
    for (size_t r = 0; r + 1 < R.size(); ++r) {
      if (R[r].chain != R[r + 1].chain) continue;
      if (!is_protein_residue_name(R[r].name) || !is_protein_residue_name(R[r + 1].name)) continue;
      const int c = atom_in(s, R[r], "C"), nn = atom_in(s, R[r + 1], "N");
      if (c < 0 || nn < 0) continue;
      const double d = (s.atoms[c].pos - s.atoms[nn].pos).norm();
      if (d <= opt.peptide_bond_max_nm) {
        add_bond(c, nn);
        linked_next[r] = linked_prev[r + 1] = true;
      } else {
        t.chain_breaks.push_back(static_cast<int>(r + 1));
        t.messages.push_back("chain break between " + R[r].label() + " and " + R[r + 1].label() +
                             ": C-N distance " + std::to_string(d * 10) + " A > " +
                             std::to_string(opt.peptide_bond_max_nm * 10) + " A");
      }
    }
    // Disulfides.
    std::vector<int> sg;
    for (size_t r = 0; r < R.size(); ++r)
      if (R[r].name == "CYS" || R[r].name == "CYX") {
        const int a = atom_in(s, R[r], "SG");
        if (a >= 0) sg.push_back(a);
      }
    std::set<int> bridged_res;
    for (size_t x = 0; x < sg.size(); ++x)
      for (size_t y = x + 1; y < sg.size(); ++y)
        if ((s.atoms[sg[x]].pos - s.atoms[sg[y]].pos).norm() <= opt.disulfide_max_nm) {
          add_bond(sg[x], sg[y]);
          bridged_res.insert(t.atom_residue[sg[x]]);
          bridged_res.insert(t.atom_residue[sg[y]]);
        }
    bool first_in_chain = true;
    for (size_t r = 0; r < R.size(); ++r) {
      const ResidueRecord& res = R[r];
      if (r > 0 && R[r - 1].chain != res.chain) first_in_chain = true;
      if (!is_protein_residue_name(res.name)) { first_in_chain = false; continue; }
      std::string name = res.name;
      if (name == "HIS") {
        const bool d1 = has_atom(s, res, "HD1"), e2 = has_atom(s, res, "HE2");
        name = d1 && e2 ? "HIP" : d1 ? "HID" : "HIE";
      } else if (name == "ASP" && has_atom(s, res, "HD2")) {
        name = "ASH";
      } else if (name == "GLU" && has_atom(s, res, "HE2")) {
        name = "GLH";
      } else if (name == "LYS" && t.hydrogens_present && !has_atom(s, res, "HZ3")) {
        name = "LYN";
      } else if (name == "CYS" || name == "CYX") {
        name = bridged_res.count(static_cast<int>(r)) ? "CYX"
               : (t.hydrogens_present && !has_atom(s, res, "HG")) ? "CYM" : "CYS";
      }
      const bool cap = name == "ACE" || name == "NME" || name == "NHE";
      if (!cap) {
        const bool nterm = !linked_prev[r] &&
                           (has_atom(s, res, "H2") || has_atom(s, res, "H3") ||
                            (!t.hydrogens_present && first_in_chain));
        const bool cterm = !linked_next[r] && (has_atom(s, res, "OXT") || has_atom(s, res, "OT2"));
        if (nterm && p.templates.count("N" + name)) name = "N" + name;
        else if (cterm && p.templates.count("C" + name)) name = "C" + name;
      }
      first_in_chain = false;
      auto it = p.templates.find(name);
      if (it == p.templates.end())
        throw StructureError(s.path + ": residue " + res.label() + ": no force-field template " + name);
      const ResidueTemplate& tp = it->second;
      t.residue_template[r] = name;
      templated[r] = true;
      std::vector<int> tatom(res.natoms, -1);
      std::vector<int> used(tp.atoms.size(), -1);
      std::vector<std::string> unknown;
      for (int k = 0; k < res.natoms; ++k) {
        const AtomRecord& a = s.atoms[res.first_atom + k];
        int ti = tp.find(a.name);
        if (ti >= 0 && used[ti] >= 0) ti = -1;
        if (ti < 0)
          for (const auto& al : aliases(res.name, a.name)) {
            const int c = tp.find(al);
            if (c >= 0 && used[c] < 0 && atom_in(s, res, al) < 0) { ti = c; break; }
          }
        if (ti < 0) {
          unknown.push_back(a.name + (a.line ? " (line " + std::to_string(a.line) + ")" : ""));
          continue;
        }
        tatom[k] = ti;
        used[ti] = res.first_atom + k;
      }
      std::vector<std::string> missing_heavy, missing_h;
      for (size_t ti = 0; ti < tp.atoms.size(); ++ti)
        if (used[ti] < 0) {
          const bool h = p.types[tp.atoms[ti].type].element == "H";
          (h ? missing_h : missing_heavy).push_back(tp.atoms[ti].name);
        }
      auto join = [](const std::vector<std::string>& v) {
        std::string o;
        for (const auto& x : v) o += (o.empty() ? "" : ", ") + x;
        return o;
      };
      const std::string where = s.path +
                                (res.natoms && s.atoms[res.first_atom].line
                                     ? ":" + std::to_string(s.atoms[res.first_atom].line)
                                     : std::string()) +
                                ": residue " + res.label() + " (template " + name + ")";
      if (!unknown.empty())
        throw StructureError(where + ": atoms not in the template: " + join(unknown));
      if (!missing_heavy.empty())
        throw StructureError(where + ": missing heavy atoms: " + join(missing_heavy));
      if (!missing_h.empty() && t.hydrogens_present)
        throw StructureError(where + ": missing hydrogens: " + join(missing_h) +
                             " (add hydrogens consistently, or remove all of them)");
      for (int k = 0; k < res.natoms; ++k) {
        const int a = res.first_atom + k;
        const ff::TemplateAtom& ta = tp.atoms[tatom[k]];
        const ff::AtomType& ty = p.types[ta.type];
        atom_type[a] = ta.type;
        t.charge[a] = ta.charge;
        t.mass[a] = ty.mass;
        t.sigma[a] = ty.sigma;
        t.epsilon[a] = ty.epsilon;
        t.atom_class[a] = ty.cls;
      }
      for (const auto& [x, y] : tp.bonds)
        if (used[x] >= 0 && used[y] >= 0) add_bond(used[x], used[y]);
    }
    if (!t.hydrogens_present)
      t.messages.push_back("no hydrogens in " + s.path +
                           ": heavy atoms typed with the all-atom ff14SB templates (charges do not "
                           "sum to integers; this is not ff14SB, only a heavy-atom model)");
  }

  // Generic atoms (no template): bonds from CONECT, else covalent radii; LJ by element.
  std::vector<int> generic;
  for (int a = 0; a < n; ++a)
    if (t.atom_residue[a] < 0 || !templated[t.atom_residue[a]]) generic.push_back(a);
  if (!generic.empty()) {
    std::set<int> gs(generic.begin(), generic.end());
    if (!s.conect.empty()) {
      for (const auto& [a, b] : s.conect)
        if (gs.count(a) || gs.count(b)) add_bond(a, b);
    } else {
      for (size_t x = 0; x < generic.size(); ++x)
        for (size_t y = x + 1; y < generic.size(); ++y) {
          const int a = generic[x], b = generic[y];
          const double d = (s.atoms[a].pos - s.atoms[b].pos).norm();
          if (d <= covalent_radius_nm(s.atoms[a].element) + covalent_radius_nm(s.atoms[b].element) + 0.045)
            add_bond(a, b);
        }
      t.messages.push_back("no CONECT records: bonds of " + std::to_string(generic.size()) +
                           " non-template atoms from covalent radii");
    }
  }
  t.bonds.assign(bonds.begin(), bonds.end());
  t.adjacency.assign(n, {});
  for (const auto& [a, b] : t.bonds) {
    t.adjacency[a].push_back(b);
    t.adjacency[b].push_back(a);
  }
  for (auto& v : t.adjacency) std::sort(v.begin(), v.end());
  for (int a : generic) {
    const std::string& e = s.atoms[a].element;
    std::string ty;
    if (e == "C") ty = "protein-CA";
    else if (e == "N") ty = "protein-N";
    else if (e == "O") ty = "protein-O";
    else if (e == "S") ty = "protein-S";
    else if (e == "H") {
      bool on_c = false;
      for (int b : t.adjacency[a]) on_c = on_c || s.atoms[b].element == "C";
      ty = on_c ? "protein-HA" : "protein-H";
    } else {
      throw StructureError(s.path + ": atom " + s.atom_label(a) + ": element " + e +
                           " has no generic parameters");
    }
    const ff::AtomType& tt = p.types[p.type_id(ty)];
    t.mass[a] = element_mass(e);
    t.sigma[a] = tt.sigma;
    t.epsilon[a] = tt.epsilon;
    t.charge[a] = 0;
    t.atom_class[a] = "generic:" + tt.cls;
  }
  if (!generic.empty())
    t.messages.push_back(std::to_string(generic.size()) +
                         " atoms without residue template: generic LJ by element (ff14SB CA/N/O/S, "
                         "HA on C, H on N), zero charges, no torsion terms");

  // Segments (bonded components).
  t.segment.assign(n, -1);
  for (int a = 0; a < n; ++a) {
    if (t.segment[a] >= 0) continue;
    std::vector<int> st{a};
    t.segment[a] = t.nsegments;
    while (!st.empty()) {
      const int x = st.back();
      st.pop_back();
      for (int y : t.adjacency[x])
        if (t.segment[y] < 0) { t.segment[y] = t.nsegments; st.push_back(y); }
    }
    ++t.nsegments;
  }

  // Exclusions (1-2, 1-3) and 1-4 pairs (OpenMM's createExceptionsFromBonds semantics).
  std::set<std::pair<int, int>> ex, p14;
  for (int a = 0; a < n; ++a) {
    for (int b : t.adjacency[a]) {
      if (b > a) ex.emplace(a, b);
      for (int c : t.adjacency[b])
        if (c != a) ex.emplace(std::min(a, c), std::max(a, c));
    }
  }
  for (int a = 0; a < n; ++a)
    for (int b : t.adjacency[a])
      for (int c : t.adjacency[b]) {
        if (c == a) continue;
        for (int d : t.adjacency[c]) {
          if (d == b || d == a) continue;
          const std::pair<int, int> pr(std::min(a, d), std::max(a, d));
          if (!ex.count(pr)) p14.insert(pr);
        }
      }
  t.excluded.assign(ex.begin(), ex.end());
  for (const auto& [a, b] : p14) {
    Pair14 q;
    q.i = a;
    q.j = b;
    q.qq = t.charge[a] * t.charge[b] * p.coulomb14scale;
    q.sigma = 0.5 * (t.sigma[a] + t.sigma[b]);
    q.epsilon = p.lj14scale * std::sqrt(t.epsilon[a] * t.epsilon[b]);
    t.pairs14.push_back(q);
  }

  // Proper torsions (templated atoms only): OpenMM's rule — the first matching definition without
  // wildcards, otherwise the first matching wildcard definition; terms with k = 0 are skipped.
  if (t.typed_by_templates) {
    auto match = [&](const ff::ProperDef& d, int a, int b, int c, int e) {
      auto m = [](int want, int have) { return want < 0 || want == have; };
      return (m(d.type[0], a) && m(d.type[1], b) && m(d.type[2], c) && m(d.type[3], e)) ||
             (m(d.type[0], e) && m(d.type[1], c) && m(d.type[2], b) && m(d.type[3], a));
    };
    for (const auto& [j, k] : t.bonds) {
      for (int i : t.adjacency[j]) {
        if (i == k) continue;
        for (int l : t.adjacency[k]) {
          if (l == j || l == i) continue;
          if (atom_type[i] < 0 || atom_type[j] < 0 || atom_type[k] < 0 || atom_type[l] < 0) continue;
          const ff::ProperDef* best = nullptr;
          for (const auto& d : p.propers) {
            if (!match(d, atom_type[i], atom_type[j], atom_type[k], atom_type[l])) continue;
            const bool wild = d.type[0] < 0 || d.type[1] < 0 || d.type[2] < 0 || d.type[3] < 0;
            if (!best || !wild) best = &d;
            if (!wild) break;
          }
          if (!best) continue;
          for (const auto& term : best->terms)
            if (term.k != 0) t.torsions.push_back({i, j, k, l, term.periodicity, term.phase, term.k});
        }
      }
    }
  }
  return t;
}

}  // namespace haptree::mol
