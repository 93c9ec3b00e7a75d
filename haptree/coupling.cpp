#include "haptree/coupling.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>

#include "haptree/isa.hpp"

#if HAPTREE_COUPLING_AVX2 && !defined(HAPTREE_ISA_COPY)
// The x86-64-v3 copy of coupling_forces (coupling_avx2.cpp), for CPUs with AVX2 + FMA.
extern "C" haptree::CouplingStatus haptree_coupling_forces_avx2(const haptree::CouplingSnapshot& s,
                                                                 const haptree::Vec6* f_u,
                                                                 haptree::CouplingWorkspace& ws,
                                                                 haptree::Vec6* f_feed) noexcept;
#endif

namespace haptree {

namespace {

// Header and node-record field indices (layout in coupling.hpp).
enum : int { kHLayout = 0, kHGrabs, kHNodes, kHLeaves, kHSlots, kHMaxH, kHExt, kHValues };
enum : int { kId = 0, kUp, kP, kQ, kSlotJ, kSlotK, kH, kHP, kVal, kSlot, kKind, kBody };
enum : int { kGBody = 0, kGLeaf, kGVal };
constexpr int kLeafFixed = 45;       // Iinv 36 | f_ext 6 | r 3
constexpr int kInternalFixed = 27;   // W 21 (upper triangle) | β 6
constexpr int kBeta = 21;
constexpr std::int32_t kLeafKind = static_cast<std::int32_t>(NodeKind::kLeaf);

using CM6 = Eigen::Map<const Mat6>;
using M6 = Eigen::Map<Mat6>;
using CV6 = Eigen::Map<const Vec6>;
using V6 = Eigen::Map<Vec6>;
using CV3 = Eigen::Map<const Vec3>;
using V3 = Eigen::Map<Vec3>;

// Raw view of a (validated) snapshot.
struct View {
  const std::int32_t* grec;
  const std::int32_t* nrec;
  const double* val;
  int G, N;
  const std::int32_t* node(int i) const { return nrec + kNodeInts * i; }
  const std::int32_t* grab(int g) const { return grec + kGrabInts * g; }
};

View make_view(const std::vector<std::int32_t>& ints, const double* values) {
  View v;
  v.G = ints[kHGrabs];
  v.N = ints[kHNodes];
  v.grec = ints.data() + kHeaderInts;
  v.nrec = v.grec + kGrabInts * v.G;
  v.val = values;
  return v;
}

// W is symmetric: stored as its upper triangle, column by column (21 doubles).
void pack_sym(const Mat6& W, double* p) {
  for (int c = 0, i = 0; c < 6; ++c)
    for (int r = 0; r <= c; ++r) p[i++] = W(r, c);
}
Mat6 unpack_sym(const double* p) {
  Mat6 W;
  for (int c = 0, i = 0; c < 6; ++c)
    for (int r = 0; r <= c; ++r, ++i) W(r, c) = W(c, r) = p[i];
  return W;
}

// Linear bottom-up pass for the user-force bias b_u over U (§11.4, §12): leaves from fu_leaf (at r_k),
// internal nodes with Δβ = W (b_u^P_j − b_u^Q_k), b_u = 0 off U. Writes bu (per slot) and dbeta.
// Returns the number of assembly-tree nodes whose coefficients were read (U plus the siblings).
// Wfull (optional, 36 per node): W unpacked, kept for the top-down pass.
std::int64_t bottom_up(const View& v, const double* fu_leaf, double* bu, double* dbeta,
                       double* Wfull) noexcept {
  std::int64_t read = 0;
  for (int i = v.N - 1; i >= 0; --i) {
    const std::int32_t* r = v.node(i);
    const int h = r[kH];
    double* b = bu + 6 * r[kSlot];
    const double* val = v.val + r[kVal];
    ++read;
    if (r[kKind] == kLeafKind) {
      const Vec6 a = CM6(val) * CV6(fu_leaf + 6 * i);
      const double* off = val + kLeafFixed;
      for (int x = 0; x < h; ++x) V6(b + 6 * x) = shift_motion(a, CV3(off + 3 * x));
      continue;
    }
    const int P = r[kP], Q = r[kQ], j = r[kSlotJ], k = r[kSlotK], hP = r[kHP];
    const int hQ = h - hP + 2;
    const double* bP = P >= 0 ? bu + 6 * v.node(P)[kSlot] : nullptr;
    const double* bQ = Q >= 0 ? bu + 6 * v.node(Q)[kSlot] : nullptr;
    read += (P < 0) + (Q < 0);   // the sibling's principal column is read from this record
    Vec6 diff = Vec6::Zero();
    if (bP) diff += CV6(bP + 6 * j);
    if (bQ) diff -= CV6(bQ + 6 * k);
    const Mat6 W = unpack_sym(val);
    if (Wfull) M6{Wfull + 36 * i} = W;
    const Vec6 db = W * diff;
    V6(dbeta + 6 * i) = db;
    const double* col = val + kInternalFixed;
    int c = 0;
    for (int ii = 0; ii < hP; ++ii) {
      if (ii == j) continue;
      Vec6 x = -(CM6(col + 36 * c) * db);
      if (bP) x += CV6(bP + 6 * ii);
      V6(b + 6 * c) = x;
      ++c;
    }
    for (int l = 0; l < hQ; ++l) {
      if (l == k) continue;
      Vec6 x = CM6(col + 36 * c) * db;
      if (bQ) x += CV6(bQ + 6 * l);
      V6(b + 6 * c) = x;
      ++c;
    }
  }
  return read;
}

bool finite6(const Vec6& x) { return x.allFinite(); }


[[noreturn]] void bad_input(const std::string& what) {
  throw std::invalid_argument(std::string(__FILE__) + ": make_coupling_snapshot: " + what);
}

}  // namespace

const char* coupling_status_name(CouplingStatus s) {
  switch (s) {
    case CouplingStatus::kOk: return "ok";
    case CouplingStatus::kEmpty: return "empty";
    case CouplingStatus::kBadSnapshot: return "bad_snapshot";
    case CouplingStatus::kWorkspaceTooSmall: return "workspace_too_small";
    case CouplingStatus::kNonFinite: return "non_finite";
  }
  return "unknown";
}

// ---------------------------------------------------------------------------------------------------

Grab make_grab(const Data& data, int body, const Vec3& local_point) {
  if (body < 1 || body >= static_cast<int>(data.r.size()))
    throw std::invalid_argument(std::string(__FILE__) + ": make_grab: bad body id " +
                                std::to_string(body));
  Grab g;
  g.body = body;
  const Vec3 dw = data.R[body] * local_point;
  g.point = data.r[body] + dw;
  g.velocity = shift_motion(data.v[body], dw).tail<3>();
  return g;
}

std::size_t count_subnormals(const double* p, std::size_t n) noexcept {
  // From the bits (exponent 0, mantissa ≠ 0): a comparison would read them as 0 under DAZ.
  std::size_t c = 0;
  for (std::size_t i = 0; i < n; ++i) {
    std::uint64_t b;
    std::memcpy(&b, p + i, sizeof b);
    c += (b & 0x7ff0000000000000ull) == 0 && (b & 0x000fffffffffffffull) != 0;
  }
  return c;
}

std::size_t flush_subnormals(double* v, std::size_t n) noexcept {
  // From the bits, like count_subnormals: under DAZ a comparison would read them as 0 already.
  std::size_t c = 0;
  for (std::size_t i = 0; i < n; ++i) {
    std::uint64_t b;
    std::memcpy(&b, v + i, sizeof b);
    if ((b & 0x7ff0000000000000ull) == 0 && (b & 0x000fffffffffffffull) != 0) {
      v[i] = 0.0;
      ++c;
    }
  }
  return c;
}

void make_coupling_snapshot(const Model& model, const Data& data, const std::vector<Grab>& grabs,
                            const std::vector<Vec6>& f_u_applied, std::int64_t version,
                            double sim_time, CouplingSnapshot& out, bool flush_tiny) {
  const auto& t = model.tree;
  const int G = static_cast<int>(grabs.size());
  if (!f_u_applied.empty() && static_cast<int>(f_u_applied.size()) != G)
    bad_input("f_u_applied has " + std::to_string(f_u_applied.size()) + " entries for " +
              std::to_string(G) + " grabs");
  if (static_cast<int>(data.Phi_adr.size()) != t.nnodes() ||
      static_cast<int>(data.r.size()) != model.nbodies)
    bad_input("Data was not built for this Model");
  for (int g = 0; g < G; ++g) {
    if (grabs[g].body < 1 || grabs[g].body >= model.nbodies)
      bad_input("grab " + std::to_string(g) + ": body " + std::to_string(grabs[g].body) +
                " out of range [1, " + std::to_string(model.nbodies) + ")");
    if (!grabs[g].point.allFinite() || !grabs[g].velocity.allFinite() ||
        (!f_u_applied.empty() && !f_u_applied[g].allFinite()))
      bad_input("grab " + std::to_string(g) + ": non-finite point, velocity or applied force");
  }
  out.model_fingerprint = model.fingerprint;
  out.version = version;
  out.sim_time = sim_time;
  out.grabs = grabs;   // copy-assignment reuses capacity

  // 1. U = union of the grabbed leaves' root paths, ascending tree id, deduplicated in place.
  auto& I = out.ints;
  I.clear();
  const std::size_t base_g = kHeaderInts, base = kHeaderInts + static_cast<std::size_t>(kGrabInts) * G;
  I.resize(base, 0);
  for (const Grab& gr : grabs)
    for (int n = t.leaf_of_body[gr.body]; n >= 0; n = t.up[n]) I.push_back(n);
  std::sort(I.begin() + base, I.end());
  const int N = static_cast<int>(std::unique(I.begin() + base, I.end()) - (I.begin() + base));
  I.resize(base + static_cast<std::size_t>(kNodeInts) * N);
  for (int i = N - 1; i >= 0; --i) {   // spread ids to record stride (records never overlap unread ids)
    const std::int32_t id = I[base + i];
    I[base + static_cast<std::size_t>(kNodeInts) * i + kId] = id;
  }
  std::int32_t* rec = I.data() + base;
  auto local = [&](int node) -> int {   // local index of a tree node, −1 if not in U
    int lo = 0, hi = N - 1;
    while (lo <= hi) {
      const int mid = (lo + hi) / 2;
      const int id = rec[kNodeInts * mid + kId];
      if (id == node) return mid;
      if (id < node) lo = mid + 1; else hi = mid - 1;
    }
    return -1;
  };

  // 2. Node records; value and slot offsets.
  int val = 0, slots = 0, maxh = 0, leaves = 0, ext = 0;
  for (int i = 0; i < N; ++i) {
    std::int32_t* r = rec + kNodeInts * i;
    const int id = r[kId];
    const int h = t.handle_num[id];
    r[kUp] = t.up[id] < 0 ? -1 : local(t.up[id]);
    r[kH] = h;
    r[kVal] = val;
    r[kSlot] = slots;
    r[kKind] = static_cast<std::int32_t>(data.kind[id]);
    ++ext;
    if (t.is_leaf(id)) {
      r[kKind] = kLeafKind;
      r[kP] = r[kQ] = r[kSlotJ] = r[kSlotK] = r[kHP] = -1;
      r[kBody] = t.body[id];
      val += kLeafFixed + 3 * h;
      ++leaves;
    } else {
      if (r[kKind] == kLeafKind) r[kKind] = static_cast<std::int32_t>(NodeKind::kActive);
      r[kP] = local(t.P[id]);
      r[kQ] = local(t.Q[id]);
      r[kSlotJ] = t.slot_j[id];
      r[kSlotK] = t.slot_k[id];
      r[kHP] = t.handle_num[t.P[id]];
      r[kBody] = -1;
      val += kInternalFixed + 36 * h;
      ext += (r[kP] < 0) + (r[kQ] < 0);
    }
    slots += h;
    maxh = std::max(maxh, h);
  }
  for (int g = 0; g < G; ++g) {
    std::int32_t* gr = I.data() + base_g + kGrabInts * g;
    gr[kGBody] = grabs[g].body;
    gr[kGLeaf] = local(t.leaf_of_body[grabs[g].body]);
    gr[kGVal] = val;
    val += kGrabValues;
  }
  I[kHLayout] = kSnapshotLayout;
  I[kHGrabs] = G;
  I[kHNodes] = N;
  I[kHLeaves] = leaves;
  I[kHSlots] = slots;
  I[kHMaxH] = maxh;
  I[kHExt] = ext;
  I[kHValues] = val;

  // 3. Values. When a user force was applied, scratch for the β_ext recovery lives past the end.
  const bool applied = !f_u_applied.empty();
  const std::size_t scratch = applied ? 6 * static_cast<std::size_t>(slots) + 12 * static_cast<std::size_t>(N) : 0;
  auto& V = out.values;
  V.resize(static_cast<std::size_t>(val) + scratch);
  double* vp = V.data();
  for (int i = 0; i < N; ++i) {
    const std::int32_t* r = rec + kNodeInts * i;
    const int id = r[kId], h = r[kH];
    double* v = vp + r[kVal];
    if (r[kBody] >= 0) {
      const int k = r[kBody];
      M6{v} = data.Iinv[k];
      V6(v + 36) = data.f_total[k];
      V3(v + 42) = data.r[k];
      for (int x = 0; x < h; ++x) {
        const int jx = t.handle(id, x);
        V3(v + kLeafFixed + 3 * x) = jx == k ? Vec3::Zero() : Vec3(data.d[jx]);
      }
    } else {
      pack_sym(data.W[id], v);
      V6(v + kBeta) = data.beta[id];
      const int P = t.P[id], Q = t.Q[id], j = r[kSlotJ], kk = r[kSlotK], hP = r[kHP];
      const int hQ = t.handle_num[Q];
      double* col = v + kInternalFixed;
      int c = 0;
      for (int ii = 0; ii < hP; ++ii)
        if (ii != j) M6(col + 36 * c++) = data.Phi(P, hP, ii, j);
      for (int l = 0; l < hQ; ++l)
        if (l != kk) M6(col + 36 * c++) = data.Phi(Q, hQ, l, kk);
    }
  }
  for (int g = 0; g < G; ++g) {
    const int k = grabs[g].body;
    double* v = vp + I[base_g + kGrabInts * g + kGVal];
    V3{v} = grabs[g].point - data.r[k];
    Eigen::Map<Mat3>(v + 3) = data.R[k];
    V3(v + 12) = data.v[k].head<3>();
  }

  // 4. Remove the applied user forces: f_ext of the leaves, then β_ext = β − Δβ_applied.
  if (applied) {
    double* bu = vp + val;
    double* dbeta = bu + 6 * slots;
    double* fu = dbeta + 6 * N;
    for (int g = 0; g < G; ++g) V6(fu + 6 * I[base_g + kGrabInts * g + kGLeaf]).setZero();
    for (int g = 0; g < G; ++g) {
      const std::int32_t* gr = I.data() + base_g + kGrabInts * g;
      const Vec3 off = CV3(vp + gr[kGVal]);
      const Vec6 f_rk = shift_force(f_u_applied[g], -off);
      V6(fu + 6 * gr[kGLeaf]) += f_rk;
      V6(vp + rec[kNodeInts * gr[kGLeaf] + kVal] + 36) -= f_rk;
    }
    const View view = make_view(I, vp);
    bottom_up(view, fu, bu, dbeta, nullptr);
    for (int i = 0; i < N; ++i) {
      const std::int32_t* r = rec + kNodeInts * i;
      if (r[kBody] < 0) V6(vp + r[kVal] + kBeta) -= CV6(dbeta + 6 * i);
    }
    V.resize(static_cast<std::size_t>(val));
  }

  // 5. No subnormals (see coupling.hpp): O(snapshot size), once per snapshot.
  if (flush_tiny) flush_subnormals(V.data(), V.size());
}

// ---------------------------------------------------------------------------------------------------

CouplingStatus validate_coupling_snapshot(const CouplingSnapshot& s) noexcept {
  const auto& I = s.ints;
  if (I.size() < static_cast<std::size_t>(kHeaderInts) || I[kHLayout] != kSnapshotLayout)
    return CouplingStatus::kBadSnapshot;
  const long G = I[kHGrabs], N = I[kHNodes], slots = I[kHSlots], nval = I[kHValues];
  if (G < 0 || N < 0 || slots < 0 || nval < 0 || static_cast<std::size_t>(G) != s.grabs.size() ||
      I.size() != static_cast<std::size_t>(kHeaderInts + kGrabInts * G + kNodeInts * N) ||
      s.values.size() != static_cast<std::size_t>(nval))
    return CouplingStatus::kBadSnapshot;
  if (G == 0) return CouplingStatus::kEmpty;
  if (N == 0) return CouplingStatus::kBadSnapshot;
  const View v = make_view(I, s.values.data());
  long slot = 0;
  for (int i = 0; i < N; ++i) {
    const std::int32_t* r = v.node(i);
    const long h = r[kH], off = r[kVal];
    if (h < 0 || r[kSlot] != slot || off < 0 || r[kUp] < -1 || r[kUp] >= i)
      return CouplingStatus::kBadSnapshot;
    slot += h;
    if (r[kKind] == kLeafKind) {
      if (r[kP] != -1 || r[kQ] != -1 || off + kLeafFixed + 3 * h > nval)
        return CouplingStatus::kBadSnapshot;
      continue;
    }
    const long hP = r[kHP], hQ = h - hP + 2;
    if (hP < 1 || hQ < 1 || r[kSlotJ] < 0 || r[kSlotJ] >= hP || r[kSlotK] < 0 || r[kSlotK] >= hQ ||
        off + kInternalFixed + 36 * h > nval)
      return CouplingStatus::kBadSnapshot;
    for (int side = 0; side < 2; ++side) {
      const int c = side == 0 ? r[kP] : r[kQ];
      if (c == -1) continue;
      if (c <= i || c >= N || v.node(c)[kUp] != i || v.node(c)[kH] != (side == 0 ? hP : hQ))
        return CouplingStatus::kBadSnapshot;
    }
  }
  if (slot != slots) return CouplingStatus::kBadSnapshot;
  for (int g = 0; g < G; ++g) {
    const std::int32_t* gr = v.grab(g);
    if (gr[kGLeaf] < 0 || gr[kGLeaf] >= N || v.node(gr[kGLeaf])[kKind] != kLeafKind ||
        v.node(gr[kGLeaf])[kBody] != gr[kGBody] || gr[kGBody] != s.grabs[g].body ||
        gr[kGVal] < 0 || static_cast<long>(gr[kGVal]) + kGrabValues > nval)
      return CouplingStatus::kBadSnapshot;
  }
  return CouplingStatus::kOk;
}

CouplingWorkspace::CouplingWorkspace(int max_nodes, int max_slots)
    : bu(6 * static_cast<std::size_t>(max_slots)),
      f(6 * static_cast<std::size_t>(max_slots)),
      dbeta(6 * static_cast<std::size_t>(max_nodes)),
      fu_leaf(6 * static_cast<std::size_t>(max_nodes)),
      feed_leaf(6 * static_cast<std::size_t>(max_nodes)),
      W(36 * static_cast<std::size_t>(max_nodes)) {}

bool CouplingWorkspace::fits(const CouplingSnapshot& s) const {
  if (s.ints.size() < static_cast<std::size_t>(kHeaderInts)) return false;
  const long N = s.ints[kHNodes], slots = s.ints[kHSlots];
  return N >= 0 && slots >= 0 && bu.size() >= 6 * static_cast<std::size_t>(slots) &&
         f.size() >= 6 * static_cast<std::size_t>(slots) &&
         dbeta.size() >= 6 * static_cast<std::size_t>(N) &&
         fu_leaf.size() >= 6 * static_cast<std::size_t>(N) &&
         feed_leaf.size() >= 6 * static_cast<std::size_t>(N) &&
         W.size() >= 36 * static_cast<std::size_t>(N);
}

void CouplingWorkspace::reserve_for(const CouplingSnapshot& s) {
  if (s.ints.size() < static_cast<std::size_t>(kHeaderInts)) return;
  const long N = std::max<long>(0, s.ints[kHNodes]), slots = std::max<long>(0, s.ints[kHSlots]);
  if (bu.size() < 6 * static_cast<std::size_t>(slots)) bu.resize(6 * slots);
  if (f.size() < 6 * static_cast<std::size_t>(slots)) f.resize(6 * slots);
  if (dbeta.size() < 6 * static_cast<std::size_t>(N)) dbeta.resize(6 * N);
  if (fu_leaf.size() < 6 * static_cast<std::size_t>(N)) fu_leaf.resize(6 * N);
  if (feed_leaf.size() < 6 * static_cast<std::size_t>(N)) feed_leaf.resize(6 * N);
  if (W.size() < 36 * static_cast<std::size_t>(N)) W.resize(36 * N);
}

CouplingStatus coupling_forces(const CouplingSnapshot& s, const Vec6* f_u, CouplingWorkspace& ws,
                               Vec6* f_feed) noexcept {
#if HAPTREE_COUPLING_AVX2 && !defined(HAPTREE_ISA_COPY)
  if (isa::active() >= isa::Level::avx2) return haptree_coupling_forces_avx2(s, f_u, ws, f_feed);
#endif
  ws.nodes_read = 0;
  const CouplingStatus st = validate_coupling_snapshot(s);
  if (st != CouplingStatus::kOk) return st;
  if (!ws.fits(s)) return CouplingStatus::kWorkspaceTooSmall;
  const View v = make_view(s.ints, s.values.data());
  const int G = v.G, N = v.N;
  auto zero_out = [&] {
    for (int g = 0; g < G; ++g) f_feed[g].setZero();
  };
  for (int g = 0; g < G; ++g)
    if (!finite6(f_u[g])) {
      zero_out();
      return CouplingStatus::kNonFinite;
    }

  // User forces moved to the body origins, summed per leaf.
  double* fu = ws.fu_leaf.data();
  for (int g = 0; g < G; ++g) V6(fu + 6 * v.grab(g)[kGLeaf]).setZero();
  for (int g = 0; g < G; ++g) {
    const std::int32_t* gr = v.grab(g);
    V6(fu + 6 * gr[kGLeaf]) += shift_force(f_u[g], -CV3(v.val + gr[kGVal]));
  }

  // Bottom-up over U: b_u and Δβ.
  double* bu = ws.bu.data();
  double* dbeta = ws.dbeta.data();
  ws.nodes_read = bottom_up(v, fu, bu, dbeta, ws.W.data());

  // Top-down over U (ids ascending): handle forces with β = β_ext + Δβ; only children in U.
  double* f = ws.f.data();
  for (int i = 0; i < N; ++i) {
    const std::int32_t* r = v.node(i);
    const int h = r[kH];
    double* fC = f + 6 * r[kSlot];
    if (r[kUp] < 0)
      for (int x = 0; x < 6 * h; ++x) fC[x] = 0;
    if (r[kKind] == kLeafKind) continue;
    const double* val = v.val + r[kVal];
    const double* col = val + kInternalFixed;
    const int P = r[kP], Q = r[kQ], j = r[kSlotJ], k = r[kSlotK], hP = r[kHP];
    const int hQ = h - hP + 2;
    Vec6 s_diff = Vec6::Zero();   // s_P − s_Q
    for (int c = 0; c < hP - 1; ++c) s_diff.noalias() += CM6(col + 36 * c).transpose() * CV6(fC + 6 * c);
    for (int c = hP - 1; c < h; ++c) s_diff.noalias() -= CM6(col + 36 * c).transpose() * CV6(fC + 6 * c);
    const Vec6 fc = CM6(ws.W.data() + 36 * i) * s_diff + CV6(val + kBeta) + CV6(dbeta + 6 * i);
    if (P >= 0) {
      double* fP = f + 6 * v.node(P)[kSlot];
      int c = 0;
      for (int ii = 0; ii < hP; ++ii) {
        if (ii == j) V6(fP + 6 * ii) = -fc;
        else V6(fP + 6 * ii) = CV6(fC + 6 * c++);
      }
    }
    if (Q >= 0) {
      double* fQ = f + 6 * v.node(Q)[kSlot];
      int c = hP - 1;
      for (int l = 0; l < hQ; ++l) {
        if (l == k) V6(fQ + 6 * l) = fc;
        else V6(fQ + 6 * l) = CV6(fC + 6 * c++);
      }
    }
  }

  // Feedback per grabbed leaf at r_k (seed eq. 12), then at each grab point.
  double* feed = ws.feed_leaf.data();
  for (int g = 0; g < G; ++g) {
    const int L = v.grab(g)[kGLeaf];
    const std::int32_t* r = v.node(L);
    const double* val = v.val + r[kVal];
    const double* fL = f + 6 * r[kSlot];
    Vec6 acc = CV6(val + 36);
    for (int x = 0; x < r[kH]; ++x) acc += shift_force(CV6(fL + 6 * x), -CV3(val + kLeafFixed + 3 * x));
    V6(feed + 6 * L) = acc;
  }
  bool ok = true;
  for (int g = 0; g < G; ++g) {
    const std::int32_t* gr = v.grab(g);
    f_feed[g] = shift_force(CV6(feed + 6 * gr[kGLeaf]), CV3(v.val + gr[kGVal]));
    ok = ok && finite6(f_feed[g]);
  }
  if (!ok) {
    zero_out();
    return CouplingStatus::kNonFinite;
  }
  return CouplingStatus::kOk;
}

// ---------------------------------------------------------------------------------------------------

Vec3 snapshot_grab_offset(const CouplingSnapshot& s, int g) {
  return CV3(s.values.data() + s.ints[kHeaderInts + kGrabInts * g + kGVal]);
}
Mat3 snapshot_grab_rotation(const CouplingSnapshot& s, int g) {
  return Eigen::Map<const Mat3>(s.values.data() + s.ints[kHeaderInts + kGrabInts * g + kGVal] + 3);
}
Vec3 snapshot_grab_angular_velocity(const CouplingSnapshot& s, int g) {
  return CV3(s.values.data() + s.ints[kHeaderInts + kGrabInts * g + kGVal] + 12);
}
Vec6 grab_force_at_body_origin(const CouplingSnapshot& s, int g, const Vec6& f_at_grab_point) {
  return shift_force(f_at_grab_point, -snapshot_grab_offset(s, g));
}
std::size_t snapshot_payload_bytes(const CouplingSnapshot& s) {
  return sizeof(s.model_fingerprint) + sizeof(s.version) + sizeof(s.sim_time) +
         s.grabs.size() * (sizeof(std::int32_t) + 6 * sizeof(double)) +
         s.ints.size() * sizeof(std::int32_t) + s.values.size() * sizeof(double);
}

// ---------------------------------------------------------------------------------------------------

Vec3 WorkspaceMapping::device_to_scene_point(const Vec3& x) const {
  return offset + rotation * (position_scale * x);
}
Vec3 WorkspaceMapping::device_to_scene_velocity(const Vec3& v) const {
  return rotation * (position_scale / time_scale * v);
}
Mat3 WorkspaceMapping::device_to_scene_rotation(const Mat3& R) const { return rotation * R; }
Vec3 WorkspaceMapping::device_to_scene_angular_velocity(const Vec3& w) const {
  return rotation * (w / time_scale);
}
Vec3 WorkspaceMapping::scene_to_device_force(const Vec3& f) const {
  return force_scale * (rotation.transpose() * f);
}
Vec3 WorkspaceMapping::scene_to_device_torque(const Vec3& tau) const {
  return torque_scale * (rotation.transpose() * tau);
}

Vec6 VirtualCoupling3::user_force(const Vec3& x_h, const Vec3& xd_h, const Vec3& x_s,
                                  const Vec3& xd_s) const {
  Vec6 f;
  f.head<3>().setZero();
  f.tail<3>() = k_s * (x_h - x_s) + b_s * (xd_h - xd_s);
  return f;
}

Vec3 rotation_log(const Mat3& R) {
  const Eigen::AngleAxisd aa(Quat(R).normalized());   // angle in [0, π]
  return aa.angle() * aa.axis();
}

Vec6 VirtualCoupling6::user_force(const Vec3& x_h, const Vec3& xd_h, const Mat3& R_h,
                                  const Vec3& w_h, const Vec3& x_s, const Vec3& xd_s,
                                  const Mat3& R_s, const Vec3& w_s) const {
  Vec6 f = linear.user_force(x_h, xd_h, x_s, xd_s);
  const Mat3 R_target = R_s * R_grab;
  f.head<3>() = k_r * rotation_log(R_h * R_target.transpose()) + b_r * (w_h - w_s);
  return f;
}

}  // namespace haptree
