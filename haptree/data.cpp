#include "haptree/data.hpp"

#include <string>

namespace haptree {

State::State(const Model& model)
    : q(neutral_configuration(model)),
      qd(Eigen::VectorXd::Zero(model.nv)),
      tau(Eigen::VectorXd::Zero(model.nv)),
      f_ext(model.nbodies, Vec6::Zero()) {}

Data::Data(const Model& model) {
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
  refine_qdd = Eigen::VectorXd::Zero(model.nv);
  refine_r = Eigen::VectorXd::Zero(model.nv);
  refine_a.assign(nb, Vec6::Zero());
  refine_f.assign(nb, Vec6::Zero());
  refine_p.assign(nb, Vec6::Zero());
  refine_c.assign(nb, Vec6::Zero());
  refine_b_buf.assign(vec, 0.0);
  refine_f_buf.assign(vec, 0.0);
  refine_beta.assign(nn, Vec6::Zero());
  refine_taut.assign(nn, Vec6::Zero());
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
  for (auto* v : {&refine_cp, &refine_cpA, &refine_cqa, &refine_ca, &refine_cb}) v->assign(nc, Vec6::Zero());
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
}

}  // namespace haptree
