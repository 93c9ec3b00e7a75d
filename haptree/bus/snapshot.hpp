// Conversion between a coupling snapshot value and lcmt_coupling_snapshot: a field-by-field copy.
// Templated on the snapshot type so the bus does not depend on haptree/coupling.hpp: any S with
//   model_fingerprint (uint64 or int64), version (int64), sim_time (double),
//   grabs (vector of {body, point[3], velocity[3]}), ints (vector<int32_t>), values (vector<double>)
// works — haptree::CouplingSnapshot does, and so does bus::SnapshotView below (tests, tools).
// Reuses the destination's storage: no allocation once it has reached its largest size.
#pragma once

#include <array>
#include <cstdint>
#include <cstring>
#include <vector>

#include "haptree/lcmt_coupling_snapshot.hpp"

namespace haptree::bus {

struct SnapshotGrabView {
  int body = -1;
  std::array<double, 3> point{};
  std::array<double, 3> velocity{};
};
struct SnapshotView {
  uint64_t model_fingerprint = 0;
  int64_t version = -1;
  double sim_time = 0;
  std::vector<SnapshotGrabView> grabs;
  std::vector<int32_t> ints;
  std::vector<double> values;
};

// The 64-bit model hash travels as int64_t (LCM has no unsigned types): bit-cast both ways.
inline int64_t fingerprint_to_wire(uint64_t f) noexcept {
  int64_t w;
  std::memcpy(&w, &f, 8);
  return w;
}
inline uint64_t fingerprint_from_wire(int64_t w) noexcept {
  uint64_t f;
  std::memcpy(&f, &w, 8);
  return f;
}

// Copies s into m (schema_version set; utime and user_id are the caller's).
template <class S>
void to_lcmt(const S& s, lcmt_coupling_snapshot& m) {
  m.schema_version = lcmt_coupling_snapshot::SCHEMA_VERSION;
  m.model_fingerprint = fingerprint_to_wire(static_cast<uint64_t>(s.model_fingerprint));
  m.version = s.version;
  m.sim_time = s.sim_time;
  const int n = static_cast<int>(s.grabs.size());
  m.n_grabs = n;
  m.grab_body.resize(n);
  m.grab_point.resize(n);
  m.grab_point_velocity.resize(n);
  for (int g = 0; g < n; ++g) {
    m.grab_body[g] = static_cast<int32_t>(s.grabs[g].body);
    m.grab_point[g].resize(3);
    m.grab_point_velocity[g].resize(3);
    for (int i = 0; i < 3; ++i) {
      m.grab_point[g][i] = s.grabs[g].point[i];
      m.grab_point_velocity[g][i] = s.grabs[g].velocity[i];
    }
  }
  m.n_ints = static_cast<int32_t>(s.ints.size());
  m.ints.assign(s.ints.begin(), s.ints.end());
  m.n_values = static_cast<int32_t>(s.values.size());
  m.values.assign(s.values.begin(), s.values.end());
}

// Copies m into s. Assumes m came from decode (array sizes match the counts).
template <class S>
void from_lcmt(const lcmt_coupling_snapshot& m, S& s) {
  using Fp = decltype(s.model_fingerprint);
  s.model_fingerprint = static_cast<Fp>(fingerprint_from_wire(m.model_fingerprint));
  s.version = m.version;
  s.sim_time = m.sim_time;
  s.grabs.resize(static_cast<size_t>(m.n_grabs));
  for (int g = 0; g < m.n_grabs; ++g) {
    s.grabs[g].body = m.grab_body[g];
    for (int i = 0; i < 3; ++i) {
      s.grabs[g].point[i] = m.grab_point[g][i];
      s.grabs[g].velocity[i] = m.grab_point_velocity[g][i];
    }
  }
  s.ints.assign(m.ints.begin(), m.ints.end());
  s.values.assign(m.values.begin(), m.values.end());
}

}  // namespace haptree::bus
