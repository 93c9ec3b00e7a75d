// Fuzz target: the URDF loader (haptree/io/urdf.*: TinyXML, urdfdom, our conversion to a Model).
// Any input must either give a Model that passed Model's own checks or throw UrdfError / ModelError.
#include <string>

#include "fuzz/fuzz_target.hpp"
#include "haptree/io/urdf.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string xml(reinterpret_cast<const char*>(data), size);
  for (const bool floating : {false, true}) {
    haptree::io::UrdfOptions opt;
    opt.floating_base = floating;
    opt.lump_fixed = floating;
    try {
      const auto model = haptree::io::parse_urdf(xml, "fuzz.urdf", opt);
      FUZZ_CHECK(model != nullptr && model->nbodies >= 1);
      FUZZ_CHECK(model->nv >= 0 && model->nq >= model->nv);
    } catch (const haptree::ModelError&) {
      // UrdfError derives from ModelError: a clear refusal
    }
  }
  return 0;
}
