#include "haptree/molecule/forcefield.hpp"

#include <algorithm>
#include <cmath>

#include "haptree/isa.hpp"
#include "haptree/molecule/cluster_kernel.hpp"

namespace haptree::ff {

namespace {

// Switched nonbonded pair (not 1-4). Adds energy to ec/el and the force on i (−dE/dx_i) to f.
inline void pair_kernel(const NonbondedOptions& o, double qq, double sig, double eps, const Vec3& d,
                        double r2, double& ec, double& el, Vec3& f_i) {
  const double r = std::sqrt(r2);
  const double inv_r = 1.0 / r;
  double Ec, dEc;
  if (o.distance_dielectric) {
    Ec = kCoulomb * qq / (40.0 * r2);
    dEc = -2.0 * Ec * inv_r;
  } else {
    Ec = kCoulomb * qq * inv_r;
    dEc = -Ec * inv_r;
  }
  const double sr2 = sig * sig / r2;
  const double s6 = sr2 * sr2 * sr2, s12 = s6 * s6;
  const double El = 4.0 * eps * (s12 - s6);
  const double dEl = 4.0 * eps * (-12.0 * s12 + 6.0 * s6) * inv_r;
  double S = 1, dS = 0;
  if (r > o.r_on) {
    const double w = o.r_off - o.r_on;
    const double x = (r - o.r_on) / w;
    const double x2 = x * x, x3 = x2 * x;
    S = 1 - 10 * x3 + 15 * x3 * x - 6 * x3 * x2;
    dS = (-30 * x2 + 60 * x3 - 30 * x3 * x) / w;
  }
  ec += S * Ec;
  el += S * El;
  const double dE = S * (dEc + dEl) + dS * (Ec + El);
  f_i = -dE * inv_r * d;   // d = x_i − x_j
}

inline void pair14_kernel(const NonbondedOptions& o, const mol::Pair14& p, const Vec3& d, double& ec,
                          double& el, Vec3& f_i) {
  const double r2 = d.squaredNorm();
  const double r = std::sqrt(r2), inv_r = 1.0 / r;
  double Ec, dEc;
  if (o.distance_dielectric) {
    Ec = kCoulomb * p.qq / (40.0 * r2);
    dEc = -2.0 * Ec * inv_r;
  } else {
    Ec = kCoulomb * p.qq * inv_r;
    dEc = -Ec * inv_r;
  }
  const double sr2 = p.sigma * p.sigma / r2;
  const double s6 = sr2 * sr2 * sr2, s12 = s6 * s6;
  const double El = 4.0 * p.epsilon * (s12 - s6);
  const double dEl = 4.0 * p.epsilon * (-12.0 * s12 + 6.0 * s6) * inv_r;
  ec += Ec;
  el += El;
  f_i = -(dEc + dEl) * inv_r * d;
}

// Proper torsion k(1 + cos(nφ − phase)); φ IUPAC. Forces added to F (GROMACS do_dih_fup scheme).
inline double torsion_kernel(const mol::Torsion& t, const std::vector<Vec3>& x,
                             std::vector<Vec3>* F) {
  const Vec3 r_ij = x[t.i] - x[t.j], r_kj = x[t.k] - x[t.j], r_kl = x[t.k] - x[t.l];
  const Vec3 m = r_ij.cross(r_kj), n = r_kj.cross(r_kl);
  const double nrkj2 = r_kj.squaredNorm(), nrkj = std::sqrt(nrkj2);
  const double phi = std::atan2(nrkj * r_ij.dot(n), m.dot(n));
  const double a = t.periodicity * phi - t.phase;
  const double E = t.k_kJmol * (1 + std::cos(a));
  if (F) {
    const double ddphi = -t.k_kJmol * t.periodicity * std::sin(a);   // dE/dφ
    const double m2 = m.squaredNorm(), n2 = n.squaredNorm();
    const Vec3 f_i = -ddphi * nrkj / m2 * m;
    const Vec3 f_l = ddphi * nrkj / n2 * n;
    const double p = r_ij.dot(r_kj) / nrkj2, q = r_kl.dot(r_kj) / nrkj2;
    const Vec3 svec = p * f_i - q * f_l;
    const Vec3 f_j = f_i - svec, f_k = f_l + svec;
    (*F)[t.i] += f_i;
    (*F)[t.j] -= f_j;
    (*F)[t.k] -= f_k;
    (*F)[t.l] += f_l;
  }
  return E;
}

void build_exclusion_csr(const mol::Topology& t, std::vector<int>& adr, std::vector<int>& list) {
  std::vector<std::vector<int>> part(t.natoms);
  for (const auto& [a, b] : t.excluded) { part[a].push_back(b); part[b].push_back(a); }
  for (const auto& p : t.pairs14) { part[p.i].push_back(p.j); part[p.j].push_back(p.i); }
  adr.assign(t.natoms + 1, 0);
  list.clear();
  for (int a = 0; a < t.natoms; ++a) {
    std::sort(part[a].begin(), part[a].end());
    adr[a] = static_cast<int>(list.size());
    list.insert(list.end(), part[a].begin(), part[a].end());
  }
  adr[t.natoms] = static_cast<int>(list.size());
}

}  // namespace

double evaluate_all_pairs(const mol::Topology& t, const NonbondedOptions& o,
                          const std::vector<Vec3>& x, std::vector<Vec3>* F, EnergyTerms* terms) {
  const int n = t.natoms;
  EnergyTerms e;
  if (F) F->assign(n, Vec3::Zero());
  std::vector<int> adr, list;
  build_exclusion_csr(t, adr, list);
  std::vector<int> mark(n, -1);
  std::vector<double> sqeps(n);
  for (int a = 0; a < n; ++a) sqeps[a] = std::sqrt(t.epsilon[a]);
  const double roff2 = o.r_off * o.r_off;
  for (int i = 0; i < n; ++i) {
    for (int k = adr[i]; k < adr[i + 1]; ++k) mark[list[k]] = i;
    for (int j = i + 1; j < n; ++j) {
      if (mark[j] == i) continue;
      const Vec3 d = x[i] - x[j];
      const double r2 = d.squaredNorm();
      if (r2 >= roff2) continue;
      Vec3 f;
      pair_kernel(o, t.charge[i] * t.charge[j], 0.5 * (t.sigma[i] + t.sigma[j]), sqeps[i] * sqeps[j],
                  d, r2, e.coulomb, e.lj, f);
      if (F) { (*F)[i] += f; (*F)[j] -= f; }
    }
  }
  for (const auto& p : t.pairs14) {
    Vec3 f;
    pair14_kernel(o, p, x[p.i] - x[p.j], e.coulomb14, e.lj14, f);
    if (F) { (*F)[p.i] += f; (*F)[p.j] -= f; }
  }
  for (const auto& tr : t.torsions) e.torsion += torsion_kernel(tr, x, F);
  if (terms) *terms = e;
  return e.total();
}

Evaluator::Evaluator(const mol::Topology& t, std::vector<int> atom_body, std::vector<Vec3> atom_local,
                     const std::vector<Vec3>& x0, const NonbondedOptions& o)
    : o_(o), n_(t.natoms), body_(std::move(atom_body)), local_(std::move(atom_local)) {
  if (static_cast<int>(body_.size()) != n_ || static_cast<int>(x0.size()) != n_)
    throw std::invalid_argument("ff::Evaluator: atom_body / positions size differs from the topology");
  if (local_.empty()) local_.assign(n_, Vec3::Zero());
  q_ = t.charge;
  sig_ = t.sigma;
  sqeps_.resize(n_);
  for (int a = 0; a < n_; ++a) sqeps_[a] = std::sqrt(t.epsilon[a]);
  hsig_.resize(n_);
  e2_.resize(n_);
  for (int a = 0; a < n_; ++a) {
    hsig_[a] = 0.5 * sig_[a];    // 0.5σ_i + 0.5σ_j == 0.5(σ_i + σ_j) exactly
    e2_[a] = 2.0 * sqeps_[a];    // (2√ε_i)(2√ε_j) == 4√ε_i√ε_j exactly
  }
  build_exclusion_csr(t, ex_adr_, ex_list_);
  // Terms inside one rigid body are constant: evaluate them once here and skip them afterwards.
  EnergyTerms c;
  for (const auto& p : t.pairs14) {
    if (body_[p.i] != body_[p.j]) { p14_.push_back(p); continue; }
    Vec3 f;
    pair14_kernel(o_, p, x0[p.i] - x0[p.j], c.coulomb14, c.lj14, f);
  }
  for (const auto& tr : t.torsions) {
    if (body_[tr.i] == body_[tr.j] && body_[tr.j] == body_[tr.k] && body_[tr.k] == body_[tr.l]) {
      c.torsion += torsion_kernel(tr, x0, nullptr);
      continue;
    }
    tors_.push_back(tr);
  }
  {
    // Intra-body switched pairs: group atoms by body.
    std::vector<std::vector<int>> members;
    int maxb = 0;
    for (int b : body_) maxb = std::max(maxb, b);
    members.resize(maxb + 1);
    for (int a = 0; a < n_; ++a) members[body_[a]].push_back(a);
    const double roff2 = o_.r_off * o_.r_off;
    for (const auto& mem : members)
      for (size_t x = 0; x < mem.size(); ++x)
        for (size_t y = x + 1; y < mem.size(); ++y) {
          const int i = mem[x], j = mem[y];
          if (std::binary_search(ex_list_.begin() + ex_adr_[i], ex_list_.begin() + ex_adr_[i + 1], j))
            continue;
          const Vec3 d = x0[i] - x0[j];
          const double r2 = d.squaredNorm();
          if (r2 >= roff2) continue;
          Vec3 f;
          pair_kernel(o_, q_[i] * q_[j], 0.5 * (sig_[i] + sig_[j]), sqeps_[i] * sqeps_[j], d, r2,
                      c.coulomb, c.lj, f);
        }
  }
  e_const_ = c.coulomb + c.coulomb14 + c.lj + c.lj14 + c.torsion;
  x_ = x0;
  F_.assign(n_, Vec3::Zero());
  x_ref_.assign(n_, Vec3::Zero());
  cell_next_.assign(n_, -1);
  row_.assign(n_ + 1, 0);
  cell_head_.assign(std::max(64, 2 * n_), -1);
  gkey_ = body_;
  p14_act_ = p14_;
  tors_act_ = tors_;
  // Compact clusters of 4 (the fewer lanes an entry's mask leaves empty, the less arithmetic is
  // wasted): walking the atoms in topology order, each atom not yet placed seeds a cluster and
  // takes, one at a time, the unplaced atom among the next kWindow (same or adjacent residues)
  // closest to the members so far (least sum of squared distances at x0).
  {
    constexpr int kWindow = 32;
    std::vector<char> placed(n_, 0);
    slot_atom_.clear();
    slot_atom_.reserve(n_ + 3 * (n_ / 4 + 1));
    for (int a = 0; a < n_; ++a) {
      if (placed[a]) continue;
      placed[a] = 1;
      int mem[4] = {a, -1, -1, -1}, nm = 1;
      for (; nm < 4; ++nm) {
        int best = -1;
        double bd = 0;
        for (int b = a + 1; b < std::min(n_, a + kWindow); ++b) {
          if (placed[b]) continue;
          double d = 0;
          for (int k = 0; k < nm; ++k) d += (x0[b] - x0[mem[k]]).squaredNorm();
          if (best < 0 || d < bd) { best = b; bd = d; }
        }
        if (best < 0) break;
        placed[best] = 1;
        mem[nm] = best;
      }
      for (int k = 0; k < 4; ++k) slot_atom_.push_back(mem[k]);   // −1: padding
    }
  }
  nslots_ = static_cast<int>(slot_atom_.size());
  atom_slot_.resize(n_);
  for (int s = 0; s < nslots_; ++s)
    if (slot_atom_[s] >= 0) atom_slot_[slot_atom_[s]] = s;
  for (DVec* v : {&cx_, &cy_, &cz_, &cq_, &cs_, &ce_, &cfx_, &cfy_, &cfz_}) v->assign(nslots_, 0.0);
  for (int s = 0; s < nslots_; ++s) {   // padding: zero parameters (and masked out anyway)
    const int a = slot_atom_[s];
    if (a < 0) continue;
    cq_[s] = q_[a];
    cs_[s] = hsig_[a];
    ce_[s] = e2_[a];
  }
  slot_gkey_.assign(nslots_, -1);
  crow_.assign(nslots_ + 1, 0);
  carow_.assign(nslots_ + 1, 0);
  cirow_.assign(nslots_ + 1, 0);
  cstamp_.assign(nslots_ / 4, -1);
  cpos_.assign(nslots_ / 4, 0);
  x_prune_.assign(n_, Vec3::Zero());
  build_list(x0);
  const size_t cap = 2 * npairs_ + 1024;
  if (pj_.size() < cap) {
    pj_.resize(cap);
    cent_.resize(cap);
    caent_.resize(cap);
    cient_.resize(cap);
  }
  split_list(x0);
  prunes_ = 0;
  F_loc_.assign(n_, Vec3::Zero());
  cached_atoms_.reserve(n_);
  rebuilds_ = 0;
}

void Evaluator::build_list(const std::vector<Vec3>& x) {
  ++rebuilds_;
  const double rl = o_.r_off + o_.skin;
  Vec3 lo = x[0], hi = x[0];
  for (int a = 1; a < n_; ++a) { lo = lo.cwiseMin(x[a]); hi = hi.cwiseMax(x[a]); }
  bool finite = true;
  for (int a = 0; a < n_; ++a) finite = finite && x[a].allFinite();
  if (!finite) {   // a blown-up state: empty list (the energy comes out non-finite), no growth
    std::fill(row_.begin(), row_.end(), 0);
    npairs_ = 0;
    list_valid_ = false;
    build_clusters();   // empty rows
    return;
  }
  const Vec3 ext = (hi - lo).cwiseMax(Vec3::Constant(1e-9));
  double cs = rl;
  int nc[3];
  const long cap = static_cast<long>(cell_head_.size());
  for (;;) {
    long total = 1;
    for (int k = 0; k < 3; ++k) {
      nc[k] = std::max(1, static_cast<int>(std::floor(ext(k) / cs)));
      total *= nc[k];
    }
    if (total <= cap) break;
    cs *= 1.26;
  }
  Vec3 inv;
  for (int k = 0; k < 3; ++k) inv(k) = nc[k] / ext(k) * (1 - 1e-12);
  std::fill(cell_head_.begin(), cell_head_.begin() + static_cast<long>(nc[0]) * nc[1] * nc[2], -1);
  auto cell_of = [&](const Vec3& p, int c[3]) {
    for (int k = 0; k < 3; ++k)
      c[k] = std::min(nc[k] - 1, std::max(0, static_cast<int>((p(k) - lo(k)) * inv(k))));
  };
  for (int a = n_ - 1; a >= 0; --a) {
    int c[3];
    cell_of(x[a], c);
    const int id = (c[2] * nc[1] + c[1]) * nc[0] + c[0];
    cell_next_[a] = cell_head_[id];
    cell_head_[id] = a;
  }
  const double rl2 = rl * rl;
  size_t np = 0;
  for (int i = 0; i < n_; ++i) {
    row_[i] = static_cast<int>(np);
    int c[3];
    cell_of(x[i], c);
    const int* eb = ex_list_.data() + ex_adr_[i];
    const int* ee = ex_list_.data() + ex_adr_[i + 1];
    for (int dz = -1; dz <= 1; ++dz) {
      const int z = c[2] + dz;
      if (z < 0 || z >= nc[2]) continue;
      for (int dy = -1; dy <= 1; ++dy) {
        const int y = c[1] + dy;
        if (y < 0 || y >= nc[1]) continue;
        for (int dx = -1; dx <= 1; ++dx) {
          // Half shell: each pair once, from the cell with the smaller offset (own cell: j > i).
          const int off = (dz * 3 + dy) * 3 + dx;
          if (off < 0) continue;
          const int xx = c[0] + dx;
          if (xx < 0 || xx >= nc[0]) continue;
          for (int j = cell_head_[(z * nc[1] + y) * nc[0] + xx]; j >= 0; j = cell_next_[j]) {
            if ((off == 0 && j <= i) || body_[j] == body_[i]) continue;
            if ((x[i] - x[j]).squaredNorm() >= rl2) continue;
            if (std::binary_search(eb, ee, j)) continue;
            if (np == pj_.size()) {   // only beyond 2x the setup size
              pj_.resize(2 * np + 1024);
              cent_.resize(pj_.size());   // entries <= pairs
              caent_.resize(pj_.size());
              cient_.resize(pj_.size());
            }
            pj_[np] = j;
            ++np;
          }
        }
      }
    }
  }
  row_[n_] = static_cast<int>(np);
  npairs_ = np;
  for (int a = 0; a < n_; ++a) x_ref_[a] = x[a];
  list_valid_ = true;
  build_clusters();
}

// Row of slot s (atom i): the partners of i merged by cluster, one entry (c << 4 | lane mask) per
// cluster holding at least one; every listed pair is in exactly one entry's mask.
void Evaluator::build_clusters() {
  if (cent_.size() < pj_.size()) {   // the constructor's first build (later: sized with pj_)
    cent_.resize(pj_.size());
    caent_.resize(pj_.size());
    cient_.resize(pj_.size());
  }
  std::fill(cstamp_.begin(), cstamp_.end(), -1);
  size_t ne = 0;
  for (int s = 0; s < nslots_; ++s) {
    crow_[s] = static_cast<int>(ne);
    const int i = slot_atom_[s];
    if (i < 0 || !list_valid_) continue;
    for (int p = row_[i]; p < row_[i + 1]; ++p) {
      const int sj = atom_slot_[pj_[p]], c = sj >> 2;
      if (cstamp_[c] != s) {
        cstamp_[c] = s;
        cpos_[c] = static_cast<int>(ne);
        cent_[ne++] = c << 4;
      }
      cent_[cpos_[c]] |= 1 << (sj & 3);
    }
  }
  crow_[nslots_] = static_cast<int>(ne);
  nents_ = ne;
  prune_valid_ = false;   // new entries: split again
}


void Evaluator::nonbonded(const int* crow, const int* cent, const std::vector<Vec3>& x,
                          std::vector<Vec3>& F, double& ec, double& el) {
  for (int s = 0; s < nslots_; ++s) {
    const int a = slot_atom_[s];
    if (a < 0) continue;
    cx_[s] = x[a](0);
    cy_[s] = x[a](1);
    cz_[s] = x[a](2);
  }
  std::fill(cfx_.begin(), cfx_.end(), 0.0);
  std::fill(cfy_.begin(), cfy_.end(), 0.0);
  std::fill(cfz_.begin(), cfz_.end(), 0.0);
  kernel::ClusterRows a;
  a.x = cx_.data();
  a.y = cy_.data();
  a.z = cz_.data();
  a.q = cq_.data();
  a.sigma = cs_.data();
  a.e2 = ce_.data();
  a.fx = cfx_.data();
  a.fy = cfy_.data();
  a.fz = cfz_.data();
  a.crow = crow;
  a.cent = cent;
  a.nslots = nslots_;
  a.r_on = o_.r_on;
  a.r_off = o_.r_off;
  a.ddd = o_.distance_dielectric;
  a.kq = a.ddd ? kCoulomb / 40.0 : kCoulomb;
  switch (isa::active()) {   // one relaxed atomic load per call
#if HAPTREE_ISA_X86
    case isa::Level::avx512: kernel::cluster_rows_avx512(a, ec, el); break;
    case isa::Level::avx2: kernel::cluster_rows_avx2(a, ec, el); break;
#endif
    default: kernel::cluster_rows_generic(a, ec, el); break;
  }
  last_lanes_ += 4 * static_cast<size_t>(crow[nslots_]);
  for (int s = 0; s < nslots_; ++s) {
    const int a = slot_atom_[s];
    if (a >= 0) F[a] = Vec3(cfx_[s], cfy_[s], cfz_[s]);
  }
}

double Evaluator::evaluate(const std::vector<Vec3>& x, std::vector<Vec3>& F, EnergyTerms* terms,
                           const Data* data) {
  // Pairs inside a group keep their distances through a rebuild: the cache stays valid.
  if (!list_covers(x)) build_list(x);
  if (!prune_covers(x)) split_list(x);
  if (static_cast<int>(F.size()) != n_) F.resize(n_);
  EnergyTerms e;
  double ec = 0, el = 0;
  nonbonded(carow_.data(), caent_.data(), x, F, ec, el);
  const size_t np = grouped_ ? napairs_ : npairs_;
  last_evaluated_ += np;
  total_evaluated_ += static_cast<std::int64_t>(np);
  e.coulomb = ec;
  e.lj = el;
  for (const auto& p : p14_act_) {
    Vec3 f;
    pair14_kernel(o_, p, x[p.i] - x[p.j], e.coulomb14, e.lj14, f);
    F[p.i] += f;
    F[p.j] -= f;
  }
  for (const auto& tr : tors_act_) e.torsion += torsion_kernel(tr, x, &F);
  if (grouped_ && data)   // group-internal forces: constant in the group root's frame
    for (int a : cached_atoms_) F[a] += data->R[group_[body_[a]]] * F_loc_[a];
  e.rigid_constant = e_const_ + e_group_;
  terms_ = e;
  if (terms) *terms = e;
  return e.total();
}

double Evaluator::compute_atoms(const std::vector<Vec3>& x, std::vector<Vec3>& F, EnergyTerms* terms) {
  if (&x != &x_) x_ = x;   // same size: no allocation
  ungroup();
  tracked_ = false;
  last_evaluated_ = last_lanes_ = 0;
  return evaluate(x_, F, terms, nullptr);
}

void Evaluator::ungroup() {
  if (!grouped_) return;
  grouped_ = false;
  gkey_ = body_;
  p14_act_ = p14_;   // within capacity: no allocation
  tors_act_ = tors_;
  e_group_ = 0;
  cached_atoms_.clear();
  prune_valid_ = false;   // re-split by bodies at the next evaluation
  napairs_ = nipairs_ = 0;
  ngroups_ = 0;
}

// Split of the list by group: pairs between groups (evaluated every step, pruned at x) and inside
// one group; an entry whose cluster spans both keeps its lanes apart by mask.
void Evaluator::split_list(const std::vector<Vec3>& x) {
  ++prunes_;
  for (int s = 0; s < nslots_; ++s) {
    const int a = slot_atom_[s];
    slot_gkey_[s] = a < 0 ? -1 : gkey_[a];
    if (a < 0) continue;
    cx_[s] = x[a](0);
    cy_[s] = x[a](1);
    cz_[s] = x[a](2);
  }
  const double rp = o_.r_off + kPrune, rp2 = rp * rp;
  size_t na = 0, ni = 0, pa = 0, pi = 0;
  const int* sg = slot_gkey_.data();
  const double *X = cx_.data(), *Y = cy_.data(), *Z = cz_.data();
  for (int s = 0; s < nslots_; ++s) {
    carow_[s] = static_cast<int>(na);
    cirow_[s] = static_cast<int>(ni);
    const int gi = sg[s];
    for (int k = crow_[s]; k < crow_[s + 1]; ++k) {
      const int w = cent_[k], c = w >> 4, j = c << 2;
      const int same = (sg[j] == gi) | (sg[j + 1] == gi) << 1 | (sg[j + 2] == gi) << 2 | (sg[j + 3] == gi) << 3;
      const int ma = w & 15 & ~same, mi = w & 15 & same;
      if (ma) {
        pa += __builtin_popcount(ma);
        int near = 0;   // lanes within r_off + kPrune now
        for (int l = 0; l < 4; ++l) {
          const double dx = X[s] - X[j + l], dy = Y[s] - Y[j + l], dz = Z[s] - Z[j + l];
          near |= (dx * dx + dy * dy + dz * dz < rp2) << l;
        }
        if (ma & near) caent_[na++] = c << 4 | (ma & near);
      }
      if (mi) { cient_[ni++] = c << 4 | mi; pi += __builtin_popcount(mi); }
    }
  }
  carow_[nslots_] = static_cast<int>(na);
  cirow_[nslots_] = static_cast<int>(ni);
  naents_ = na;
  nients_ = ni;
  napairs_ = pa;
  nipairs_ = pi;
  for (int a = 0; a < n_; ++a) x_prune_[a] = x[a];
  prune_valid_ = true;
}

bool Evaluator::prune_covers(const std::vector<Vec3>& x) const {
  if (!prune_valid_) return false;
  const double lim2 = 0.25 * kPrune * kPrune;
  for (int a = 0; a < n_; ++a)
    if ((x[a] - x_prune_[a]).squaredNorm() > lim2) return false;
  return true;
}

namespace {
inline double max_abs_diff(const Mat3& a, const Mat3& b) { return (a - b).cwiseAbs().maxCoeff(); }
inline double max_abs_diff(const Vec3& a, const Vec3& b) { return (a - b).cwiseAbs().maxCoeff(); }
}  // namespace

// Per joint k: the pose of body k relative to its parent, against the last step (still_) and, for
// joints inside a group, against the pose when the group was formed. True: re-form the groups
// (a group's inside moved, or a joint between groups has been still for two steps).
bool Evaluator::track_motion(const Model& m, const Data& d) {
  const int nb = m.nbodies;
  if (static_cast<int>(group_.size()) != nb) {   // first call with this model: sized once
    group_.resize(nb);
    for (int k = 0; k < nb; ++k) group_[k] = k;
    rel_R_.assign(nb, Mat3::Identity());
    ref_R_.assign(nb, Mat3::Identity());
    rel_t_.assign(nb, Vec3::Zero());
    ref_t_.assign(nb, Vec3::Zero());
    still_.assign(nb, 0);
    gmark_.assign(nb, 0);
    tracked_ = false;
  }
  const bool first = !tracked_;
  bool regroup = false;
  for (int k = 1; k < nb; ++k) {
    const int p = m.parent[k];
    const Mat3 R = d.R[p].transpose() * d.R[k];
    const Vec3 t = d.R[p].transpose() * (d.r[k] - d.r[p]);
    if (first) {
      still_[k] = 0;
    } else {
      const bool moved = max_abs_diff(R, rel_R_[k]) > kStillTol || max_abs_diff(t, rel_t_[k]) > kStillTol;
      still_[k] = moved ? 0 : still_[k] + 1;
    }
    rel_R_[k] = R;
    rel_t_[k] = t;
    if (grouped_ && group_[k] == group_[p]) {
      if (max_abs_diff(R, ref_R_[k]) > kRigidTol || max_abs_diff(t, ref_t_[k]) > kRigidTol) regroup = true;
    } else if (still_[k] >= 2) {
      regroup = true;
    }
  }
  tracked_ = true;
  return regroup;
}

// Groups = components of the body tree over joints that did not move in the last step; everything
// inside one group is evaluated here, once, at the current positions (x_, poses in d).
void Evaluator::regroup(const Model& m, const Data& d) {
  ++regroups_;
  const int nb = m.nbodies;
  group_[0] = 0;
  bool any = false;
  for (int k = 1; k < nb; ++k) {
    const bool joined = still_[k] >= 1;
    any = any || joined;
    group_[k] = joined ? group_[m.parent[k]] : k;
    ref_R_[k] = rel_R_[k];
    ref_t_[k] = rel_t_[k];
  }
  if (!any) {   // everything moved: no group
    for (int k = 0; k < nb; ++k) group_[k] = k;
    ungroup();
    return;
  }
  ngroups_ = 0;
  std::fill(gmark_.begin(), gmark_.end(), 0);
  for (int k = 1; k < nb; ++k)
    if (group_[k] != k && !gmark_[group_[k]]) { gmark_[group_[k]] = 1; ++ngroups_; }
  for (int a = 0; a < n_; ++a) gkey_[a] = group_[body_[a]];
  grouped_ = true;
  if (!list_covers(x_)) build_list(x_);
  split_list(x_);
  // Group-internal terms at the current positions: energy constant, forces kept in the group frame.
  double ec = 0, el = 0, e = 0;   // F_: scratch for the internal forces (overwritten here)
  nonbonded(cirow_.data(), cient_.data(), x_, F_, ec, el);
  last_evaluated_ += nipairs_;
  total_evaluated_ += static_cast<std::int64_t>(nipairs_);
  e = ec + el;
  p14_act_.clear();
  for (const auto& p : p14_) {
    if (gkey_[p.i] != gkey_[p.j]) { p14_act_.push_back(p); continue; }
    double c = 0, l = 0;
    Vec3 f;
    pair14_kernel(o_, p, x_[p.i] - x_[p.j], c, l, f);
    F_[p.i] += f;
    F_[p.j] -= f;
    e += c + l;
  }
  tors_act_.clear();
  for (const auto& t : tors_) {
    const int g = gkey_[t.i];
    if (gkey_[t.j] == g && gkey_[t.k] == g && gkey_[t.l] == g) e += torsion_kernel(t, x_, &F_);
    else tors_act_.push_back(t);
  }
  e_group_ = e;
  cached_atoms_.clear();
  for (int a = 0; a < n_; ++a) {
    if (F_[a].isZero(0)) continue;
    F_loc_[a] = d.R[group_[body_[a]]].transpose() * F_[a];
    cached_atoms_.push_back(a);
  }
}

bool Evaluator::list_covers(const std::vector<Vec3>& x) const {
  if (!list_valid_) return false;
  const double lim2 = 0.25 * o_.skin * o_.skin;
  for (int a = 0; a < n_; ++a)
    if ((x[a] - x_ref_[a]).squaredNorm() > lim2) return false;
  return true;
}

double Evaluator::compute(const Model& model, const Data& data, std::vector<Vec6>& f_ext) {
  for (int a = 0; a < n_; ++a) x_[a] = data.r[body_[a]] + data.R[body_[a]] * local_[a];
  last_evaluated_ = last_lanes_ = 0;
  double E;
  bool finite = true;
  for (int a = 0; a < n_ && finite; ++a) finite = x_[a].allFinite();
  if (o_.follow_motion && finite) {
    if (track_motion(model, data)) regroup(model, data);
    E = evaluate(x_, F_, nullptr, &data);
  } else {
    ungroup();
    tracked_ = false;
    E = evaluate(x_, F_, nullptr, nullptr);
  }
  if (static_cast<int>(f_ext.size()) != model.nbodies) f_ext.resize(model.nbodies);
  for (auto& f : f_ext) f.setZero();
  for (int a = 0; a < n_; ++a) {
    const int b = body_[a];
    const Vec3 arm = x_[a] - data.r[b];
    f_ext[b].head<3>() += arm.cross(F_[a]);
    f_ext[b].tail<3>() += F_[a];
  }
  return E;
}

}  // namespace haptree::ff
