// isa_probe: the kernel level the dispatcher picked on this CPU, the level the DCA runs at, the
// force field of two molecular scenes at a fixed pose (energy terms, every body's wrench) and the
// DCA's q̈ of a protein-like tree, as JSON with %.17g numbers; the qemu test (qemu_isa_test.py) runs
// it on this machine and as older CPUs and compares.
#include <cmath>
#include <cstdio>

#include "haptree/dca.hpp"
#include "haptree/isa.hpp"
#include "haptree/molecule/scene.hpp"
#include "haptree/scenes.hpp"

using namespace haptree;

int main() {
  std::printf("{\"isa\": \"%s\", \"best\": \"%s\", \"dca\": \"%s\", \"scenes\": {", isa::name(isa::active()),
              isa::name(isa::best()), isa::name(dca_level()));
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
  std::printf("}, \"dca_qdd\": [");
  {
    SceneOptions o;
    o.seed = 3;
    const auto model = make_scene("protein_like", o);
    Data d(*model);
    State st(*model);
    st.q = neutral_configuration(*model);
    if (model->nq == model->nv)   // revolute / prismatic joints only: any q is a configuration
      for (int k = 0; k < model->nq; ++k) st.q(k) += 0.3 * std::sin(1.7 * k);
    for (int k = 0; k < model->nv; ++k) st.qd(k) = 0.5 * std::cos(2.3 * k);
    const Eigen::VectorXd& qdd = forward_dynamics(*model, d, st);
    for (int k = 0; k < qdd.size(); ++k) std::printf("%s%.17g", k ? ", " : "", qdd(k));
  }
  std::printf("]}\n");
  return 0;
}
