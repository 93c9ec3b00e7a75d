// isa_probe: the kernel level the dispatcher picked on this CPU and the force field of two molecular
// scenes at a fixed pose (energy terms, every body's wrench), as JSON with %.17g numbers; the
// qemu test (qemu_isa_test.py) runs it on this machine and as an older CPU and compares.
#include <cmath>
#include <cstdio>

#include "haptree/dca.hpp"
#include "haptree/isa.hpp"
#include "haptree/molecule/scene.hpp"

using namespace haptree;

int main() {
  std::printf("{\"isa\": \"%s\", \"best\": \"%s\", \"scenes\": {", isa::name(isa::active()), isa::name(isa::best()));
  const char* sep = "";
  for (const char* name : {"ala20", "bacteriorhodopsin"}) {
    mol::MolecularScene sc = mol::load_molecular_scene(name);
    const Model& m = *sc.model;
    Data d(m);
    Eigen::VectorXd q = neutral_configuration(m);
    const double amp = sc.natoms() > 1000 ? 0.002 : 0.05;   // off the input pose, no clashes
    for (int k = 0; k < q.size(); ++k) q(k) += amp * std::sin(3.0 * k);
    forward_kinematics(m, d, q);
    std::vector<Vec6> f_ext;
    const double E = sc.compute(d, f_ext);
    const ff::EnergyTerms& t = sc.force_field->last_terms();
    std::printf("%s\"%s\": {\"E\": %.17g, \"terms\": [%.17g, %.17g, %.17g, %.17g, %.17g], \"wrench\": [", sep, name, E,
                t.coulomb, t.coulomb14, t.lj, t.lj14, t.torsion);
    for (int k = 0; k < m.nbodies; ++k)
      for (int i = 0; i < 6; ++i) std::printf("%s%.17g", k == 0 && i == 0 ? "" : ", ", f_ext[k](i));
    std::printf("]}");
    sep = ", ";
  }
  std::printf("}}\n");
  return 0;
}
