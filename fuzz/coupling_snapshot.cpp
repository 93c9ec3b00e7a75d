// Fuzz target: a coefficient snapshot from the wire, as the coupler takes it: decode_checked →
// bus::from_lcmt → validate_coupling_snapshot → coupling_forces (and the per-grab accessors the
// coupler and sim_server use). Input: the lcmt_coupling_snapshot bytes after the fingerprint
// (lcm_input.hpp). Oracles: never crash; a snapshot that validates is computable (no kBadSnapshot /
// kWorkspaceTooSmall after reserve_for), and coupling_forces returns finite forces or kNonFinite with
// zeros — a device must never be handed a NaN.
#include <cmath>
#include <vector>

#include "fuzz/fuzz_target.hpp"
#include "fuzz/lcm_input.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/coupling.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace haptree;
  static lcmt_coupling_snapshot msg{};
  static CouplingSnapshot snap;
  static CouplingWorkspace ws;
  const std::vector<uint8_t>& buf = fuzz::with_fingerprint<lcmt_coupling_snapshot>(data, size);
  if (bus::decode_checked(buf.data(), buf.size(), msg) != bus::DecodeResult::kOk) return 0;
  bus::from_lcmt(msg, snap);
  const CouplingStatus v = validate_coupling_snapshot(snap);
  if (v != CouplingStatus::kOk) {
    Vec6 dummy = Vec6::Zero();
    FUZZ_CHECK(coupling_forces(snap, &dummy, ws, &dummy) == v);
    return 0;
  }
  ws.reserve_for(snap);
  FUZZ_CHECK(ws.fits(snap));
  const size_t G = snap.grabs.size();
  std::vector<Vec6> f_u(G), f_feed(G, Vec6::Constant(7));
  for (size_t g = 0; g < G; ++g) f_u[g] << 0.1, -0.2, 0.3, 1.0 + g, -2.0, 0.5;   // a user pulling
  const CouplingStatus st = coupling_forces(snap, f_u.data(), ws, f_feed.data());
  FUZZ_CHECK(st == CouplingStatus::kOk || st == CouplingStatus::kNonFinite);
  for (size_t g = 0; g < G; ++g) {
    FUZZ_CHECK(f_feed[g].allFinite());
    if (st == CouplingStatus::kNonFinite) FUZZ_CHECK(f_feed[g].isZero(0));
    const int gi = static_cast<int>(g);
    (void)snapshot_grab_offset(snap, gi);
    (void)snapshot_grab_rotation(snap, gi);
    (void)snapshot_grab_angular_velocity(snap, gi);
    (void)grab_force_at_body_origin(snap, gi, f_u[g]);
  }
  return 0;
}
