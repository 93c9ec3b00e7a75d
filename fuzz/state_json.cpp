// Fuzz target: the STATE.json parser (haptree/io/state_json.*) on a model with every joint type
// (revolute, prismatic, spherical, fixed, free root). Any input must either give a finite State of the
// model's sizes with unit quaternions, or throw StateJsonError (or a JSON parse error, as the CLI maps it).
#include <cmath>

#include <nlohmann/json.hpp>

#include "fuzz/fuzz_target.hpp"
#include "haptree/io/state_json.hpp"
#include "haptree/scenes.hpp"

namespace {
const haptree::Model& model() {
  static const auto m = [] {
    haptree::SceneOptions o;
    o.n = 8;
    o.seed = 3;
    o.mixed_joints = true;
    o.free_root = true;
    return haptree::make_chain(o);
  }();
  return *m;
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const haptree::Model& m = model();
  const nlohmann::json doc = nlohmann::json::parse(data, data + size, nullptr, /*allow_exceptions=*/false);
  if (doc.is_discarded()) return 0;
  try {
    const haptree::State st = haptree::io::state_from_json(m, doc, "fuzz.json");
    FUZZ_CHECK(st.q.size() == m.nq && st.qd.size() == m.nv && st.tau.size() == m.nv);
    FUZZ_CHECK(st.q.allFinite() && st.qd.allFinite() && st.tau.allFinite());
    for (int k = 1; k < m.nbodies; ++k) {
      FUZZ_CHECK(st.f_ext[k].allFinite());
      const int off = m.joint_type[k] == haptree::JointType::kSpherical ? 0
                      : m.joint_type[k] == haptree::JointType::kFree    ? 3
                                                                        : -1;
      if (off >= 0) FUZZ_CHECK(std::abs(st.q.segment(m.q_adr[k] + off, 4).norm() - 1) < 1e-9);
    }
  } catch (const haptree::io::StateJsonError&) {
  }
  return 0;
}
