#include "haptree/data.hpp"

#include <string>

namespace haptree {

State::State(const Model& model)
    : q(neutral_configuration(model)),
      qd(Eigen::VectorXd::Zero(model.nv)),
      tau(Eigen::VectorXd::Zero(model.nv)),
      f_ext(model.nbodies, Vec6::Zero()) {}

Data::Data(const Model& model, Refinement refine_mode) : refine(refine_mode) {
  const int nb = model.nbodies;
  const auto& t = model.tree;
  const int nn = t.nnodes();
  R.assign(nb, Mat3::Identity());
  r.assign(nb, Vec3::Zero());
  d.assign(nb, Vec3::Zero());
  v.assign(nb, Vec6::Zero());
  S.assign(nb, Vec6::Zero());
  c.assign(nb, Vec6::Zero());
  I.assign(nb, Mat6::Zero());
  Iinv.assign(nb, Mat6::Zero());
  f_total.assign(nb, Vec6::Zero());
  p_bias.assign(nb, Vec6::Zero());
  kind.resize(nn);
  Phi_adr.resize(nn);
  vec_adr.resize(nn);
  std::int64_t phi = 0;
  int vec = 0;
  for (int node = 0; node < nn; ++node) {
    kind[node] = t.is_leaf(node) ? NodeKind::kLeaf : NodeKind::kActive;
    const int h = t.handle_num[node];
    Phi_adr[node] = phi;
    phi += 36LL * h * h;
    vec_adr[node] = vec;
    vec += 6 * h;
  }
  // A body with many children keeps many handles open on its way up the assembly: Φ storage grows
  // as O(d^3). Refuse clearly instead of failing inside the allocator.
  if (phi > (std::int64_t{1} << 29)) {   // 4 GiB of doubles
    int hub = 0;
    for (int k = 0; k < nb; ++k)
      if (model.children[k].size() > model.children[hub].size()) hub = k;
    throw ModelError("body '" + model.body_name[hub] + "' has " +
                     std::to_string(model.children[hub].size()) + " children: the assembly would "
                     "need " + std::to_string(phi * 8 >> 20) + " MiB of coefficients; split it into "
                     "rigid pieces with --max-children 4 (haptree-fd; BuildOptions::max_children "
                     "in the API), exact, docs/algorithms.md §4.4");
  }
  Phi_buf.assign(phi, 0.0);
  b_buf.assign(vec, 0.0);
  f_buf.assign(vec, 0.0);
  W.assign(nn, Mat6::Zero());
  beta.assign(nn, Vec6::Zero());
  taut.assign(nn, Vec6::Zero());
  qdd = Eigen::VectorXd::Zero(model.nv);
  const int nc = model.ncluster_nodes;
  if (nc > 0) cluster_offset.assign(nb, Vec3::Zero());
  if (nc > 0) cluster_offset_lo.assign(nb, Vec3::Zero());
  cM.assign(nc, Mat6::Zero());
  cMinv.assign(nc, Mat6::Zero());
  cIA.assign(nc, Mat6::Zero());
  cp.assign(nc, Vec6::Zero());
  cpA.assign(nc, Vec6::Zero());
  cqa.assign(nc, Vec6::Zero());
  ca.assign(nc, Vec6::Zero());
  cb.assign(nc, Vec6::Zero());
  cluster_live.assign(nn, 0);
  leaf_adr.assign(nn, -1);
  leaf_side.assign(nn, 0);
  int nleaf = 0;
  for (int node = 0; node < nn; ++node) {
    if (t.is_leaf(node)) continue;
    const int P = t.P[node], Q = t.Q[node];
    if ((t.is_leaf(P) && t.body[P] != 0) || (t.is_leaf(Q) && t.body[Q] != 0)) leaf_adr[node] = nleaf++;
  }
  leaf_F.assign(nleaf, Mat6::Zero());
  leaf_G.assign(nleaf, Mat6::Zero());

  dca_cut = parallel_cut(t, 1, 0);
  if (refine != Refinement::kOff) size_refinement(model, *this);
}

void size_refinement(const Model& model, Data& d) {
  const int nb = model.nbodies, nn = model.tree.nnodes(), nc = model.ncluster_nodes;
  d.refine_qdd = Eigen::VectorXd::Zero(model.nv);
  d.refine_r = Eigen::VectorXd::Zero(model.nv);
  d.refine_a.assign(nb, Vec6::Zero());
  d.refine_f.assign(nb, Vec6::Zero());
  d.refine_p.assign(nb, Vec6::Zero());
  d.refine_c.assign(nb, Vec6::Zero());
  d.refine_b_buf.assign(d.b_buf.size(), 0.0);
  d.refine_f_buf.assign(d.f_buf.size(), 0.0);
  d.refine_beta.assign(nn, Vec6::Zero());
  d.refine_taut.assign(nn, Vec6::Zero());
  for (auto* v : {&d.refine_cp, &d.refine_cpA, &d.refine_cqa, &d.refine_ca, &d.refine_cb}) v->assign(nc, Vec6::Zero());
}

bool refinement_sized(const Model& model, const Data& d) {
  return d.refine_a.size() == static_cast<std::size_t>(model.nbodies);
}

namespace {

template <class T, class A>
std::size_t heap_bytes(const std::vector<T, A>& v) { return v.capacity() * sizeof(T); }
template <class T, int R, int C, int O, int MR, int MC>
std::size_t heap_bytes(const Eigen::Matrix<T, R, C, O, MR, MC>& m) { return m.size() * sizeof(T); }

}  // namespace

std::vector<MemoryItem> memory_usage(const State& s, const std::string& p) {
  return {{p + "q", heap_bytes(s.q)}, {p + "qd", heap_bytes(s.qd)}, {p + "tau", heap_bytes(s.tau)},
          {p + "f_ext", heap_bytes(s.f_ext)}};
}

std::vector<MemoryItem> memory_usage(const Data& d, const std::string& p) {
  std::vector<MemoryItem> out;
  auto add = [&](const char* name, std::size_t bytes) { out.push_back({p + name, bytes}); };
#define HAPTREE_MEM(x) add(#x, heap_bytes(d.x))
  HAPTREE_MEM(R); HAPTREE_MEM(r); HAPTREE_MEM(d); HAPTREE_MEM(v); HAPTREE_MEM(S); HAPTREE_MEM(c);
  HAPTREE_MEM(I); HAPTREE_MEM(Iinv); HAPTREE_MEM(f_total); HAPTREE_MEM(p_bias);
  HAPTREE_MEM(kind); HAPTREE_MEM(Phi_buf); HAPTREE_MEM(Phi_adr); HAPTREE_MEM(b_buf); HAPTREE_MEM(f_buf);
  HAPTREE_MEM(vec_adr); HAPTREE_MEM(W); HAPTREE_MEM(beta); HAPTREE_MEM(taut);
  HAPTREE_MEM(cluster_offset); HAPTREE_MEM(cluster_offset_lo); HAPTREE_MEM(cM); HAPTREE_MEM(cMinv);
  HAPTREE_MEM(cIA); HAPTREE_MEM(cp); HAPTREE_MEM(cpA); HAPTREE_MEM(cqa); HAPTREE_MEM(ca); HAPTREE_MEM(cb);
  HAPTREE_MEM(cluster_live); HAPTREE_MEM(leaf_adr); HAPTREE_MEM(leaf_side); HAPTREE_MEM(leaf_F);
  HAPTREE_MEM(leaf_G); HAPTREE_MEM(qdd); HAPTREE_MEM(refine_qdd); HAPTREE_MEM(refine_r);
  HAPTREE_MEM(refine_a); HAPTREE_MEM(refine_f); HAPTREE_MEM(refine_p); HAPTREE_MEM(refine_c);
  HAPTREE_MEM(refine_b_buf); HAPTREE_MEM(refine_f_buf); HAPTREE_MEM(refine_beta); HAPTREE_MEM(refine_taut);
  HAPTREE_MEM(refine_cp); HAPTREE_MEM(refine_cpA); HAPTREE_MEM(refine_cqa); HAPTREE_MEM(refine_ca);
  HAPTREE_MEM(refine_cb);
  HAPTREE_MEM(refine_x.R); HAPTREE_MEM(refine_x.d); HAPTREE_MEM(refine_x.v); HAPTREE_MEM(refine_x.a);
  HAPTREE_MEM(refine_x.f);
  HAPTREE_MEM(dca_cut.lo); HAPTREE_MEM(dca_cut.hi); HAPTREE_MEM(dca_cut.top);
#undef HAPTREE_MEM
  return out;
}

std::size_t total_bytes(const std::vector<MemoryItem>& items) {
  std::size_t s = 0;
  for (const auto& i : items) s += i.bytes;
  return s;
}

}  // namespace haptree
