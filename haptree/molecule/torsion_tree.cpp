#include "haptree/molecule/torsion_tree.hpp"

#include <algorithm>
#include <functional>
#include <map>
#include <queue>

namespace haptree::mol {

void TorsionModel::atom_positions(const std::vector<Mat3>& R, const std::vector<Vec3>& r,
                                  std::vector<Vec3>& x) const {
  const size_t n = atom_local.size();
  if (x.size() != n) x.resize(n);
  for (size_t i = 0; i < n; ++i) {
    const int b = atom_model_body[i];
    x[i] = r[b] + R[b] * atom_local[i];
  }
}

namespace {

std::string joint_label(const Structure& s, const Topology& t, int a1, int a2) {
  const auto& A = s.atoms;
  const std::string &n1 = A[a1].name, &n2 = A[a2].name;
  auto is = [&](const char* x, const char* y) {
    return (n1 == x && n2 == y) || (n1 == y && n2 == x);
  };
  if (!t.typed_by_templates || t.residue_template[t.atom_residue[a1]].empty()) return "tor";
  if (is("N", "CA")) return "phi";
  if (is("CA", "C")) return "psi";
  if (is("C", "N")) return "omega";
  static const std::string greek = "ABGDEZH";
  if (n1.size() > 1) {
    const size_t g = greek.find(n1[1]);
    if (g != std::string::npos) return "chi" + std::to_string(g + 1);
  }
  return "tor";
}

}  // namespace

TorsionModel build_torsion_model(const Structure& s, const Topology& t, const TorsionOptions& opt) {
  const int n = t.natoms;
  const auto& adj = t.adjacency;
  TorsionModel m;

  // 1. Bridges of the bond graph (a bond is in a ring iff it is not a bridge), DFS per segment.
  std::vector<int> disc(n, -1), low(n, 0), parent(n, -1), heavy_sub(n, 0), size_sub(n, 0);
  std::vector<int> seg_heavy(t.nsegments, 0), seg_size(t.nsegments, 0);
  for (int a = 0; a < n; ++a) {
    seg_heavy[t.segment[a]] += t.heavy[a] ? 1 : 0;
    seg_size[t.segment[a]] += 1;
  }
  int timer = 0;
  std::vector<std::pair<int, int>> bridges;   // (dfs parent u, child v)
  // Iterative DFS (deep chains).
  for (int root = 0; root < n; ++root) {
    if (disc[root] >= 0) continue;
    std::vector<std::pair<int, size_t>> st{{root, 0}};
    disc[root] = low[root] = timer++;
    while (!st.empty()) {
      auto& [u, it] = st.back();
      if (it < adj[u].size()) {
        const int v = adj[u][it++];
        if (disc[v] < 0) {
          parent[v] = u;
          disc[v] = low[v] = timer++;
          st.emplace_back(v, 0);
        } else if (v != parent[u]) {
          low[u] = std::min(low[u], disc[v]);
        }
      } else {
        const int uu = u;
        heavy_sub[uu] += t.heavy[uu] ? 1 : 0;
        size_sub[uu] += 1;
        st.pop_back();
        if (!st.empty()) {
          const int p = st.back().first;
          low[p] = std::min(low[p], low[uu]);
          heavy_sub[p] += heavy_sub[uu];
          size_sub[p] += size_sub[uu];
          if (low[uu] > disc[p]) bridges.emplace_back(p, uu);
        }
      }
    }
  }

  // 2. Joints among the bridges.
  std::vector<std::pair<int, int>> joint_bonds;
  for (const auto& [u, v] : bridges) {
    const auto& au = s.atoms[u];
    const auto& av = s.atoms[v];
    const bool same_res = t.atom_residue[u] == t.atom_residue[v];
    const bool cn = (au.name == "C" && av.name == "N") || (au.name == "N" && av.name == "C");
    if (!opt.omega && !same_res && cn) continue;   // peptide bond: ω fixed
    if (same_res && au.resname == "ARG" &&
        ((au.name == "NE" && av.name == "CZ") || (au.name == "CZ" && av.name == "NE")))
      continue;   // guanidinium
    const int sg = t.segment[u];
    const int hv = heavy_sub[v] - (t.heavy[v] ? 1 : 0);
    const int hu = seg_heavy[sg] - heavy_sub[v] - (t.heavy[u] ? 1 : 0);
    const int nv_ = size_sub[v] - 1, nu_ = seg_size[sg] - size_sub[v] - 1;
    if (nv_ <= 0 || nu_ <= 0) continue;                       // terminal atom
    if (!(hv > 0 && hu > 0) && !opt.with_h_rotors) continue;   // moves only hydrogens
    joint_bonds.emplace_back(u, v);
  }
  std::map<std::pair<int, int>, int> is_joint;
  for (const auto& [u, v] : joint_bonds) {
    is_joint[{std::min(u, v), std::max(u, v)}] = 1;
  }
  auto cut = [&](int a, int b) { return is_joint.count({std::min(a, b), std::max(a, b)}) > 0; };

  // 3. Rigid groups = components after cutting the joints (labelled by lowest atom).
  std::vector<int> group(n, -1);
  std::vector<std::vector<int>> groups;
  for (int a = 0; a < n; ++a) {
    if (group[a] >= 0) continue;
    const int g = static_cast<int>(groups.size());
    groups.emplace_back();
    std::vector<int> st{a};
    group[a] = g;
    while (!st.empty()) {
      const int x = st.back();
      st.pop_back();
      groups[g].push_back(x);
      for (int y : adj[x])
        if (group[y] < 0 && !cut(x, y)) { group[y] = g; st.push_back(y); }
    }
    std::sort(groups[g].begin(), groups[g].end());
  }
  // Joint bonds touching each group.
  std::vector<std::vector<std::pair<int, int>>> gjoints(groups.size());
  for (const auto& [u, v] : joint_bonds) {
    gjoints[group[u]].emplace_back(u, v);
    gjoints[group[v]].emplace_back(v, u);
  }

  // 4. BFS from the root group of every segment (the group of the segment's first atom).
  std::vector<int> body_of_group(groups.size(), -1);
  m.atom_body.assign(n, -1);
  std::vector<int> seg_done(t.nsegments, 0);
  for (int a = 0; a < n; ++a) {
    const int sg = t.segment[a];
    if (seg_done[sg]) continue;
    seg_done[sg] = 1;
    const int g0 = group[a];
    std::queue<int> q;
    auto new_body = [&](int g, int parent_body, int joint) {
      const int b = m.nbodies++;
      body_of_group[g] = b;
      m.body_parent.push_back(parent_body);
      m.body_joint.push_back(joint);
      m.body_atoms.push_back(groups[g]);
      for (int x : groups[g]) m.atom_body[x] = b;
      q.push(g);
      return b;
    };
    const int rb = new_body(g0, -1, -1);
    m.roots.push_back(rb);
    m.body_origin.push_back(s.atoms[groups[g0].front()].pos);
    while (!q.empty()) {
      const int g = q.front();
      q.pop();
      auto js = gjoints[g];
      std::sort(js.begin(), js.end());
      for (const auto& [a1, a2] : js) {
        const int cg = group[a2];
        if (body_of_group[cg] >= 0) continue;   // the parent side
        TorsionJoint j;
        j.atom1 = a1;
        j.atom2 = a2;
        j.parent_body = body_of_group[g];
        j.residue = t.atom_residue[a1];
        j.label = joint_label(s, t, a1, a2);
        const int ji = static_cast<int>(m.joints.size());
        m.joints.push_back(j);
        const int cb = new_body(cg, body_of_group[g], ji);
        m.joints[ji].child_body = cb;
        m.body_origin.push_back(s.atoms[a2].pos);
      }
    }
  }

  // 5. Mass properties and the haptree Model.
  ModelBuilder mb;
  mb.set_gravity(Vec3::Zero());
  const double a2r = opt.atom_radius_nm * opt.atom_radius_nm;
  m.atom_local.assign(n, Vec3::Zero());
  for (int b = 0; b < m.nbodies; ++b) {
    const Vec3 o = m.body_origin[b];
    double mass = 0;
    Vec3 c = Vec3::Zero();
    for (int x : m.body_atoms[b]) {
      mass += t.mass[x];
      c += t.mass[x] * (s.atoms[x].pos - o);
      m.atom_local[x] = s.atoms[x].pos - o;
    }
    c /= mass;
    Mat3 I = Mat3::Zero();
    for (int x : m.body_atoms[b]) {
      const Vec3 d = s.atoms[x].pos - o - c;
      I += t.mass[x] * (d.squaredNorm() * Mat3::Identity() - d * d.transpose());
      I += 0.4 * t.mass[x] * a2r * Mat3::Identity();
    }
    const std::string name = "b" + std::to_string(b);
    const int pb = m.body_parent[b];
    if (pb < 0) {
      mb.add_body(name, 0, opt.root_joint, o, Mat3::Identity(), Vec3::UnitZ(), mass, c, I,
                  "root" + std::to_string(b));
    } else {
      const TorsionJoint& j = m.joints[m.body_joint[b]];
      const Vec3 axis = (s.atoms[j.atom2].pos - s.atoms[j.atom1].pos).normalized();
      const auto& res = s.residues[j.residue];
      const std::string jn = "j" + std::to_string(m.body_joint[b]) + ":" + res.name +
                             std::to_string(res.resid) + ":" + j.label;
      // Parent body frame has world axes at q = 0: offset = difference of origins.
      mb.add_body(name, 0 + (pb + 1), JointType::kRevolute, o - m.body_origin[pb],
                  Mat3::Identity(), axis, mass, c, I, jn);
    }
  }
  m.model = mb.build(opt.build);
  std::map<std::string, int> by_name;
  for (int k = 0; k < m.model->nbodies; ++k) by_name[m.model->body_name[k]] = k;
  m.model_body.resize(m.nbodies);
  for (int b = 0; b < m.nbodies; ++b) m.model_body[b] = by_name.at("b" + std::to_string(b));
  for (auto& j : m.joints) j.model_body = m.model_body[j.child_body];
  m.atom_model_body.resize(n);
  for (int x = 0; x < n; ++x) m.atom_model_body[x] = m.model_body[m.atom_body[x]];
  return m;
}

}  // namespace haptree::mol
