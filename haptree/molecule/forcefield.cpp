#include "haptree/molecule/forcefield.hpp"

#include <algorithm>
#include <cmath>
#ifdef __AVX__
#include <immintrin.h>
#endif

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

// Switched non-bonded pairs, atom × 4-atom cluster ("1×4"; GROMACS' nbnxm cluster pairs with one
// i atom, since this kernel is double precision): an entry evaluates atom i against the 4 slots of
// one cluster with vector loads from the slot arrays (no per-pair gather or compaction) and vector
// stores of the 4 j forces (no scatter). Lanes outside the entry's mask (pairs not listed, padding,
// i itself) get r² = far, beyond r_off, where the switch is exactly 0 (x clamped to 1: S = 1 − 10 +
// 15 − 6 = 0 and dS = 0 in exact arithmetic, even with FMA), so they add exact zeros; so do listed
// pairs at or beyond r_off, as in the reference. 1/r is double precision from rsqrt + Newton steps
// y ← y(1.5 − 0.5 r² y²), whose relative error e maps to ≤ 1.5e² (+ rounding): AVX-512VL rsqrt14
// (|e₀| < 2⁻¹⁴) and two steps (5.6e-9, then 4.7e-17), else SSE's rsqrt (|e₀| ≤ 1.5·2⁻¹²) and three
// (2.1e-7, 6.3e-14, 6e-27): the result is within the few ulp of rounding of 1/sqrt(r²), so nothing
// is single precision. F_i and the energies are summed in 4 lanes (round-off-level reordering
// against the reference). Without AVX the same lanes run scalar with sqrt and a division.
#ifdef __AVX__
namespace {
// 4-lane (AVX) and, with AVX-512, 8-lane double vectors behind one set of names, so that one
// kernel body (pair_lanes) serves both widths. The 8-lane kernel takes two entries of a row at once
// (lanes 0-3: one cluster, 4-7: the next), which doubles the work per instruction on CPUs with
// 512-bit units (AMD Zen 5, Intel server cores) and costs one insert/extract per load/store.
inline __m256d vadd(__m256d a, __m256d b) { return _mm256_add_pd(a, b); }
inline __m256d vsub(__m256d a, __m256d b) { return _mm256_sub_pd(a, b); }
inline __m256d vmul(__m256d a, __m256d b) { return _mm256_mul_pd(a, b); }
inline __m256d vmin(__m256d a, __m256d b) { return _mm256_min_pd(a, b); }
inline __m256d vmax(__m256d a, __m256d b) { return _mm256_max_pd(a, b); }
inline __m256d fmadd(__m256d a, __m256d b, __m256d c) {   // a·b + c
#ifdef __FMA__
  return _mm256_fmadd_pd(a, b, c);
#else
  return _mm256_add_pd(_mm256_mul_pd(a, b), c);
#endif
}
inline __m256d fnmadd(__m256d a, __m256d b, __m256d c) {   // c − a·b
#ifdef __FMA__
  return _mm256_fnmadd_pd(a, b, c);
#else
  return _mm256_sub_pd(c, _mm256_mul_pd(a, b));
#endif
}
inline double hsum(__m256d v) {
  alignas(32) double a[4];
  _mm256_store_pd(a, v);
  return (a[0] + a[1]) + (a[2] + a[3]);
}
inline __m256d inv_sqrt(__m256d r2) {
#ifdef __AVX512VL__
  // rsqrt14 (|e₀| < 2⁻¹⁴), then one refinement of order 4: with ε = 1 − r²y₀² (|ε| < 1.3e-4),
  // 1/√r² = y₀(1 − ε)^(−1/2) = y₀(1 + ε/2 + 3ε²/8 + 5ε³/16 + 35ε⁴/128 …): the ε⁴ term left out is
  // < 1e-16 relative.
  const __m256d y = _mm256_rsqrt14_pd(r2);
  const __m256d eps = fnmadd(_mm256_mul_pd(r2, y), y, _mm256_set1_pd(1.0));
  const __m256d p = fmadd(fmadd(_mm256_set1_pd(0.3125), eps, _mm256_set1_pd(0.375)), eps, _mm256_set1_pd(0.5));
  return fmadd(_mm256_mul_pd(y, eps), p, y);
#else
  // SSE rsqrt (|e₀| ≤ 1.5·2⁻¹²), three Newton steps y ← y(1.5 − 0.5r²y²): e ↦ ≤ 1.5e² + rounding.
  __m256d y = _mm256_cvtps_pd(_mm_rsqrt_ps(_mm256_cvtpd_ps(r2)));
  const __m256d h = _mm256_mul_pd(_mm256_set1_pd(0.5), r2), c15 = _mm256_set1_pd(1.5);
  for (int k = 0; k < 3; ++k) y = _mm256_mul_pd(y, fnmadd(h, _mm256_mul_pd(y, y), c15));
  return y;
#endif
}
struct LaneMasks {
  alignas(32) std::int64_t m[16][4];
};
constexpr LaneMasks make_lane_masks() {
  LaneMasks t{};
  for (int k = 0; k < 16; ++k)
    for (int l = 0; l < 4; ++l) t.m[k][l] = (k >> l & 1) ? -1 : 0;
  return t;
}
constexpr LaneMasks kLanes = make_lane_masks();
// r² in the lanes of mask m (bit l: lane l), `far` elsewhere.
inline __m256d masked(__m256d far, __m256d r2, int m) {
  return _mm256_blendv_pd(far, r2, _mm256_castsi256_pd(_mm256_load_si256(reinterpret_cast<const __m256i*>(kLanes.m[m]))));
}
template <class D> D vset(double x);
template <> inline __m256d vset<__m256d>(double x) { return _mm256_set1_pd(x); }

#ifdef __AVX512F__
inline __m512d vadd(__m512d a, __m512d b) { return _mm512_add_pd(a, b); }
inline __m512d vsub(__m512d a, __m512d b) { return _mm512_sub_pd(a, b); }
inline __m512d vmul(__m512d a, __m512d b) { return _mm512_mul_pd(a, b); }
inline __m512d vmin(__m512d a, __m512d b) { return _mm512_min_pd(a, b); }
inline __m512d vmax(__m512d a, __m512d b) { return _mm512_max_pd(a, b); }
inline __m512d fmadd(__m512d a, __m512d b, __m512d c) { return _mm512_fmadd_pd(a, b, c); }
inline __m512d fnmadd(__m512d a, __m512d b, __m512d c) { return _mm512_fnmadd_pd(a, b, c); }
inline __m256d hi4(__m512d v) { return _mm512_extractf64x4_pd(v, 1); }   // lanes 4-7
inline double hsum(__m512d v) {
  return hsum(_mm512_castpd512_pd256(v)) + hsum(hi4(v));
}
inline __m512d inv_sqrt(__m512d r2) {   // as the 4-lane AVX-512VL version above
  const __m512d y = _mm512_rsqrt14_pd(r2);
  const __m512d eps = fnmadd(_mm512_mul_pd(r2, y), y, _mm512_set1_pd(1.0));
  const __m512d p = fmadd(fmadd(_mm512_set1_pd(0.3125), eps, _mm512_set1_pd(0.375)), eps, _mm512_set1_pd(0.5));
  return fmadd(_mm512_mul_pd(y, eps), p, y);
}
inline __m512d masked(__m512d far, __m512d r2, int m) {
  return _mm512_mask_blend_pd(static_cast<__mmask8>(m), far, r2);
}
template <> inline __m512d vset<__m512d>(double x) { return _mm512_set1_pd(x); }
// Lanes 0-3 from p0, 4-7 from p1 (both 32-byte aligned slot arrays).
inline __m512d load2(const double* p0, const double* p1) {
  return _mm512_insertf64x4(_mm512_zextpd256_pd512(_mm256_load_pd(p0)), _mm256_load_pd(p1), 1);
}
inline void add_store2(double* p0, double* p1, __m512d v) {   // p0[0..3] += v[0..3], then p1 += v[4..7]
  _mm256_store_pd(p0, _mm256_add_pd(_mm256_load_pd(p0), _mm512_castpd512_pd256(v)));
  _mm256_store_pd(p1, _mm256_add_pd(_mm256_load_pd(p1), hi4(v)));
}
#endif

// Switch constants and the per-pair arithmetic of cluster_rows, for either width. Up to
// cluster_rows' end two GCC 12 warnings are off: a vector type's alignment attribute dropped as a
// template argument (not needed there), and the "undefined" source vector inside its own
// _mm512_extractf64x4_pd (a false positive).
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wignored-attributes"
#pragma GCC diagnostic ignored "-Wuninitialized"
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
template <class D>
struct PairConsts {
  D one, zero, far, iw, x0, c6, c12, c2, c1n, s6n, s15, s10n, d30, d60;
  PairConsts(double r_on, double r_off)
      : one(vset<D>(1.0)), zero(vset<D>(0.0)), far(vset<D>((r_off + 1.0) * (r_off + 1.0))),
        iw(vset<D>(1.0 / (r_off - r_on))), x0(vset<D>(-r_on / (r_off - r_on))), c6(vset<D>(6.0)),
        c12(vset<D>(-12.0)), c2(vset<D>(-2.0)), c1n(vset<D>(-1.0)), s6n(vset<D>(-6.0)), s15(vset<D>(15.0)),
        s10n(vset<D>(-10.0)), d30(vset<D>(30.0 / (r_off - r_on))), d60(vset<D>(2.0 * (30.0 / (r_off - r_on)))) {}
};
// Lanes of atom i against j: vq = k q_i q_j, vs = σ_ij, ve = 4ε_ij, r2 already masked. Returns
// (dE/dr)/r; adds S·E_c and S·E_lj to vec, vel.
template <bool DDD, class D>
inline D pair_lanes(const PairConsts<D>& c, D r2, D vq, D vs, D ve, D& vec, D& vel) {
  const D inv_r = inv_sqrt(r2);
  const D inv_r2 = vmul(inv_r, inv_r);
  const D r = vmul(r2, inv_r);
  const D Ec = DDD ? vmul(vq, inv_r2) : vmul(vq, inv_r);
  const D sr2 = vmul(vmul(vs, vs), inv_r2);
  const D s6 = vmul(vmul(sr2, sr2), sr2);
  const D a6 = vmul(ve, s6);                       // 4ε (σ/r)⁶
  const D El = fmadd(a6, s6, vsub(c.zero, a6));    // 4ε((σ/r)¹² − (σ/r)⁶)
  // (dE/dr)/r = (−2E_c [DDD] or −E_c, + 4ε(−12(σ/r)¹² + 6(σ/r)⁶)) / r²
  const D rdE = fmadd(DDD ? c.c2 : c.c1n, Ec, vmul(a6, fmadd(c.c12, s6, c.c6)));
  const D dE_r = vmul(rdE, inv_r2);
  // Switch in Horner form: S = 1 + x³(−10 + x(15 − 6x)), dS/dr = x²(−30 + x(60 − 30x))/w; at x = 1
  // both are exactly 0 (all steps exact: integers, and 60/w = 2·(30/w)).
  const D xs = vmin(vmax(fmadd(r, c.iw, c.x0), c.zero), c.one);
  const D x2 = vmul(xs, xs), x3 = vmul(x2, xs);
  const D S = fmadd(x3, fmadd(fmadd(c.s6n, xs, c.s15), xs, c.s10n), c.one);
  const D dS = vmul(x2, fmadd(fnmadd(c.d30, xs, c.d60), xs, vsub(c.zero, c.d30)));
  vec = fmadd(S, Ec, vec);
  vel = fmadd(S, El, vel);
  return fmadd(S, dE_r, vmul(vmul(dS, vadd(Ec, El)), inv_r));
}
}  // namespace
#endif

template <bool DDD>
void Evaluator::cluster_rows(const int* crow, const int* cent, double& ec_out, double& el_out) {
  const double r_on = o_.r_on;
  const double kq = DDD ? kCoulomb / 40.0 : kCoulomb;
  const double *X = cx_.data(), *Y = cy_.data(), *Z = cz_.data();
  const double *Q = cq_.data(), *SG = cs_.data(), *E2 = ce_.data();
  double *FX = cfx_.data(), *FY = cfy_.data(), *FZ = cfz_.data();
#ifdef __AVX__
  const PairConsts<__m256d> c4(r_on, o_.r_off);
  __m256d vec = c4.zero, vel = c4.zero;
#ifdef __AVX512F__
  const PairConsts<__m512d> c8(r_on, o_.r_off);
  __m512d vec8 = c8.zero, vel8 = c8.zero;
#endif
  for (int s = 0; s < nslots_; ++s) {
    int k = crow[s];
    const int e = crow[s + 1];
    if (k == e) continue;
    __m256d fix = c4.zero, fiy = c4.zero, fiz = c4.zero;
#ifdef __AVX512F__
    {   // two entries (clusters) per step
      const __m512d xi = _mm512_set1_pd(X[s]), yi = _mm512_set1_pd(Y[s]), zi = _mm512_set1_pd(Z[s]);
      const __m512d qi = _mm512_set1_pd(kq * Q[s]), si = _mm512_set1_pd(SG[s]), ei = _mm512_set1_pd(E2[s]);
      __m512d gx = c8.zero, gy = c8.zero, gz = c8.zero;
      for (; k + 1 < e; k += 2) {
        const int w0 = cent[k], w1 = cent[k + 1];
        const int j0 = (w0 >> 4) << 2, j1 = (w1 >> 4) << 2;
        const __m512d vx = _mm512_sub_pd(xi, load2(X + j0, X + j1));
        const __m512d vy = _mm512_sub_pd(yi, load2(Y + j0, Y + j1));
        const __m512d vz = _mm512_sub_pd(zi, load2(Z + j0, Z + j1));
        const __m512d r2 = masked(c8.far, fmadd(vz, vz, fmadd(vy, vy, _mm512_mul_pd(vx, vx))),
                                  (w0 & 15) | (w1 & 15) << 4);
        const __m512d dE = pair_lanes<DDD>(c8, r2, _mm512_mul_pd(qi, load2(Q + j0, Q + j1)),
                                           _mm512_add_pd(si, load2(SG + j0, SG + j1)),
                                           _mm512_mul_pd(ei, load2(E2 + j0, E2 + j1)), vec8, vel8);
        const __m512d fx = _mm512_mul_pd(dE, vx), fy = _mm512_mul_pd(dE, vy), fz = _mm512_mul_pd(dE, vz);
        gx = _mm512_sub_pd(gx, fx);   // f_i = −dE/dr · d/r, d = x_i − x_j
        gy = _mm512_sub_pd(gy, fy);
        gz = _mm512_sub_pd(gz, fz);
        add_store2(FX + j0, FX + j1, fx);   // f_j = −f_i
        add_store2(FY + j0, FY + j1, fy);
        add_store2(FZ + j0, FZ + j1, fz);
      }
      fix = _mm256_add_pd(_mm512_castpd512_pd256(gx), hi4(gx));
      fiy = _mm256_add_pd(_mm512_castpd512_pd256(gy), hi4(gy));
      fiz = _mm256_add_pd(_mm512_castpd512_pd256(gz), hi4(gz));
    }
#endif
    if (k < e) {   // one entry (every entry without AVX-512, the odd last one with it)
      const __m256d xi = _mm256_set1_pd(X[s]), yi = _mm256_set1_pd(Y[s]), zi = _mm256_set1_pd(Z[s]);
      for (; k < e; ++k) {
        const int w = cent[k];
        const int j = (w >> 4) << 2;
        const __m256d vx = _mm256_sub_pd(xi, _mm256_load_pd(X + j));
        const __m256d vy = _mm256_sub_pd(yi, _mm256_load_pd(Y + j));
        const __m256d vz = _mm256_sub_pd(zi, _mm256_load_pd(Z + j));
        const __m256d r2 = masked(c4.far, fmadd(vz, vz, fmadd(vy, vy, _mm256_mul_pd(vx, vx))), w & 15);
        const __m256d dE = pair_lanes<DDD>(c4, r2, _mm256_mul_pd(_mm256_set1_pd(kq * Q[s]), _mm256_load_pd(Q + j)),
                                           _mm256_add_pd(_mm256_set1_pd(SG[s]), _mm256_load_pd(SG + j)),
                                           _mm256_mul_pd(_mm256_set1_pd(E2[s]), _mm256_load_pd(E2 + j)), vec, vel);
        const __m256d fx = _mm256_mul_pd(dE, vx), fy = _mm256_mul_pd(dE, vy), fz = _mm256_mul_pd(dE, vz);
        fix = _mm256_sub_pd(fix, fx);
        fiy = _mm256_sub_pd(fiy, fy);
        fiz = _mm256_sub_pd(fiz, fz);
        _mm256_store_pd(FX + j, _mm256_add_pd(_mm256_load_pd(FX + j), fx));
        _mm256_store_pd(FY + j, _mm256_add_pd(_mm256_load_pd(FY + j), fy));
        _mm256_store_pd(FZ + j, _mm256_add_pd(_mm256_load_pd(FZ + j), fz));
      }
    }
    FX[s] += hsum(fix);
    FY[s] += hsum(fiy);
    FZ[s] += hsum(fiz);
  }
#ifdef __AVX512F__
  ec_out += hsum(vec8);
  el_out += hsum(vel8);
#endif
  ec_out += hsum(vec);
  el_out += hsum(vel);
#else
  const double inv_w = 1.0 / (o_.r_off - o_.r_on);
  const double far = (o_.r_off + 1.0) * (o_.r_off + 1.0);
  double ec = 0, el = 0;
  for (int s = 0; s < nslots_; ++s) {
    const int b = crow[s], e = crow[s + 1];
    if (b == e) continue;
    const double qi = kq * Q[s];
    double fix = 0, fiy = 0, fiz = 0;
    for (int k = b; k < e; ++k) {
      const int w = cent[k];
      const int j0 = (w >> 4) << 2;
      for (int l = 0; l < 4; ++l) {
        const int j = j0 + l;
        const double dx = X[s] - X[j], dy = Y[s] - Y[j], dz = Z[s] - Z[j];
        const double r2 = (w >> l & 1) ? dx * dx + dy * dy + dz * dz : far;
        const double inv_r2 = 1.0 / r2;
        const double r = std::sqrt(r2);
        const double inv_r = r * inv_r2;
        double Ec, dEc_r;
        if (DDD) {
          Ec = qi * Q[j] * inv_r2;
          dEc_r = -2.0 * Ec * inv_r2;
        } else {
          Ec = qi * Q[j] * inv_r;
          dEc_r = -Ec * inv_r2;
        }
        const double sg = SG[s] + SG[j], e4 = E2[s] * E2[j];
        const double sr2 = sg * sg * inv_r2;
        const double s6 = sr2 * sr2 * sr2, s12 = s6 * s6;
        const double El = e4 * (s12 - s6);
        const double dE_r = dEc_r + e4 * (-12.0 * s12 + 6.0 * s6) * inv_r2;
        double xs = (r - r_on) * inv_w;
        xs = xs < 0.0 ? 0.0 : xs;
        xs = xs > 1.0 ? 1.0 : xs;
        const double x2 = xs * xs, x3 = x2 * xs;
        const double S = 1 - 10 * x3 + 15 * x3 * xs - 6 * x3 * x2;
        const double dS = (-30 * x2 + 60 * x3 - 30 * x3 * xs) * inv_w;
        const double dE = S * dE_r + dS * (Ec + El) * inv_r;
        fix -= dE * dx;
        fiy -= dE * dy;
        fiz -= dE * dz;
        FX[j] += dE * dx;
        FY[j] += dE * dy;
        FZ[j] += dE * dz;
        ec += S * Ec;
        el += S * El;
      }
    }
    FX[s] += fix;
    FY[s] += fiy;
    FZ[s] += fiz;
  }
  ec_out += ec;
  el_out += el;
#endif
}

#ifdef __AVX__
#pragma GCC diagnostic pop
#endif

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
  if (o_.distance_dielectric) cluster_rows<true>(crow, cent, ec, el);
  else cluster_rows<false>(crow, cent, ec, el);
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
#ifdef __AVX__
        const __m256d vx = _mm256_sub_pd(_mm256_set1_pd(X[s]), _mm256_load_pd(X + j));
        const __m256d vy = _mm256_sub_pd(_mm256_set1_pd(Y[s]), _mm256_load_pd(Y + j));
        const __m256d vz = _mm256_sub_pd(_mm256_set1_pd(Z[s]), _mm256_load_pd(Z + j));
        const __m256d r2 = fmadd(vz, vz, fmadd(vy, vy, _mm256_mul_pd(vx, vx)));
        near = _mm256_movemask_pd(_mm256_cmp_pd(r2, _mm256_set1_pd(rp2), _CMP_LT_OQ));
#else
        for (int l = 0; l < 4; ++l) {
          const double dx = X[s] - X[j + l], dy = Y[s] - Y[j + l], dz = Z[s] - Z[j + l];
          near |= (dx * dx + dy * dy + dz * dz < rp2) << l;
        }
#endif
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
