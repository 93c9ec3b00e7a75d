#include "haptree/molecule/builder.hpp"

#include <cmath>
#include <map>

namespace haptree::mol {

namespace {

constexpr double kDeg = M_PI / 180.0;

// NeRF: position of d bonded to c with |cd| = bond, angle b-c-d, dihedral a-b-c-d (degrees).
Vec3 place(const Vec3& a, const Vec3& b, const Vec3& c, double bond, double angle, double torsion) {
  const double ang = angle * kDeg, tor = torsion * kDeg;
  const Vec3 bc = (c - b).normalized();
  const Vec3 n = (b - a).cross(bc).normalized();
  const Vec3 m = n.cross(bc);
  return c + bc * (-bond * std::cos(ang)) + m * (bond * std::sin(ang) * std::cos(tor)) +
         n * (bond * std::sin(ang) * std::sin(tor));
}

}  // namespace

Structure build_alanine_helix(int n, double phi, double psi, double omega) {
  if (n < 1) throw StructureError("build_alanine_helix: need at least one residue, got " + std::to_string(n));
  // Engh & Huber (1991), Å and degrees.
  const double B_NCA = 1.458, B_CAC = 1.525, B_CN = 1.329, B_CO = 1.231, B_CACB = 1.530,
               B_CH3C = 1.520, B_NCH3 = 1.449, B_CH = 1.09, B_NH = 1.01;
  const double A_CNCA = 121.7, A_NCAC = 111.2, A_CACN = 116.2, A_NCO = 122.7, A_TET = 109.5;
  std::map<std::pair<int, std::string>, Vec3> pos;   // (residue, name) -> Å
  // Backbone trace CH3(ACE) C(ACE) | N CA C | ... | N(NME) C(NME).
  std::vector<Vec3> tr;
  tr.push_back(Vec3::Zero());
  tr.push_back(Vec3(B_CH3C, 0, 0));
  const double ang = (180 - A_CACN) * kDeg;
  tr.push_back(tr[1] + Vec3(B_CN * std::cos(ang), B_CN * std::sin(ang), 0));
  pos[{0, "CH3"}] = tr[0];
  pos[{0, "C"}] = tr[1];
  pos[{1, "N"}] = tr[2];
  auto last = [&](int k) { return tr[tr.size() - k]; };
  for (int i = 1; i <= n; ++i) {
    tr.push_back(place(last(3), last(2), last(1), B_NCA, A_CNCA, omega));
    pos[{i, "CA"}] = tr.back();
    tr.push_back(place(last(3), last(2), last(1), B_CAC, A_NCAC, phi));
    pos[{i, "C"}] = tr.back();
    tr.push_back(place(last(3), last(2), last(1), B_CN, A_CACN, psi));
    pos[{i + 1, "N"}] = tr.back();
  }
  tr.push_back(place(last(3), last(2), last(1), B_NCH3, A_CNCA, omega));
  pos[{n + 1, "C"}] = tr.back();
  for (int k = 0; k <= n; ++k) {
    const Vec3 nxt_ca = k < n ? pos[{k + 1, "CA"}] : pos[{n + 1, "C"}];
    pos[{k, "O"}] = place(nxt_ca, pos[{k + 1, "N"}], pos[{k, "C"}], B_CO, A_NCO, 0.0);
  }
  for (int i = 1; i <= n; ++i)
    pos[{i, "CB"}] = place(pos[{i, "C"}], pos[{i, "N"}], pos[{i, "CA"}], B_CACB, 110.5, -122.6);
  // Hydrogens.
  auto amide_h = [&](const Vec3& c_prev, const Vec3& N, const Vec3& c_next) {
    const Vec3 bis = ((c_prev - N).normalized() + (c_next - N).normalized()).normalized();
    return Vec3(N - B_NH * bis);
  };
  auto methyl = [&](int res, const Vec3& a, const Vec3& b, const Vec3& c, const char* n1,
                    const char* n2, const char* n3) {
    pos[{res, n1}] = place(a, b, c, B_CH, A_TET, 180.0);
    pos[{res, n2}] = place(a, b, c, B_CH, A_TET, 60.0);
    pos[{res, n3}] = place(a, b, c, B_CH, A_TET, -60.0);
  };
  methyl(0, pos[{1, "N"}], pos[{0, "C"}], pos[{0, "CH3"}], "H1", "H2", "H3");
  for (int i = 1; i <= n; ++i) {
    const Vec3 N = pos[{i, "N"}], CA = pos[{i, "CA"}], C = pos[{i, "C"}], CB = pos[{i, "CB"}];
    pos[{i, "H"}] = amide_h(pos[{i - 1, "C"}], N, CA);
    const Vec3 s = (N - CA).normalized() + (C - CA).normalized() + (CB - CA).normalized();
    pos[{i, "HA"}] = CA - B_CH * s.normalized();
    methyl(i, N, CA, CB, "HB1", "HB2", "HB3");
  }
  pos[{n + 1, "H"}] = amide_h(pos[{n, "C"}], pos[{n + 1, "N"}], pos[{n + 1, "C"}]);
  methyl(n + 1, pos[{n, "C"}], pos[{n + 1, "N"}], pos[{n + 1, "C"}], "H1", "H2", "H3");

  Structure s;
  s.path = "built:ACE-(ALA)" + std::to_string(n) + "-NME";
  s.protein_mode = true;
  auto add_res = [&](const std::string& rn, int r, std::vector<std::pair<std::string, std::string>> names) {
    ResidueRecord rr;
    rr.name = rn;
    rr.chain = "A";
    rr.resid = r;
    rr.hetero = rn != "ALA";
    rr.first_atom = static_cast<int>(s.atoms.size());
    for (const auto& [nm, el] : names) {
      AtomRecord a;
      a.name = nm;
      a.element = el;
      a.resname = rn;
      a.chain = "A";
      a.resid = r;
      a.hetero = rr.hetero;
      a.serial = static_cast<int>(s.atoms.size()) + 1;
      a.pos = pos.at({r, nm}) * 0.1;
      s.atoms.push_back(a);
    }
    rr.natoms = static_cast<int>(s.atoms.size()) - rr.first_atom;
    s.residues.push_back(rr);
  };
  add_res("ACE", 0, {{"CH3", "C"}, {"H1", "H"}, {"H2", "H"}, {"H3", "H"}, {"C", "C"}, {"O", "O"}});
  for (int i = 1; i <= n; ++i)
    add_res("ALA", i, {{"N", "N"}, {"H", "H"}, {"CA", "C"}, {"HA", "H"}, {"C", "C"}, {"O", "O"},
                       {"CB", "C"}, {"HB1", "H"}, {"HB2", "H"}, {"HB3", "H"}});
  add_res("NME", n + 1, {{"N", "N"}, {"H", "H"}, {"C", "C"}, {"H1", "H"}, {"H2", "H"}, {"H3", "H"}});
  return s;
}

}  // namespace haptree::mol
