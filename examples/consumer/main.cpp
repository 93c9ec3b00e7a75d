// Loads a URDF, runs forward_dynamics, checks it against inverse dynamics, and asks the coupling for
// the feedback force on the last body: the library's main path, from a program with its own flags.
// Exit 0 when every check holds; the numbers are printed.
#include <cmath>
#include <cstdio>
#include <vector>

#include "haptree/coupling.hpp"
#include "haptree/dca.hpp"
#include "haptree/inverse_dynamics.hpp"
#include "haptree/io/urdf.hpp"

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: consumer MODEL.urdf\n");
    return 2;
  }
  using namespace haptree;
  const auto model = io::load_urdf(argv[1]);
  const Model& m = *model;
  State st(m);
  for (int i = 0; i < m.nq; ++i) st.q(i) = 0.1 * (i + 1);
  for (int i = 0; i < m.nv; ++i) st.qd(i) = 0.05 * (i % 3) - 0.05;
  Data d(m);
  const Eigen::VectorXd qdd = forward_dynamics(m, d, st);

  // τ − ID(q, q̇, q̈) vanishes up to rounding: the arm's masses and lengths are O(1) (condition of the
  // mass matrix below 1e4), so 1e-8 of the largest gravity torque is far above double rounding and
  // far below any layout or alignment mismatch (which gives O(1) garbage or a crash).
  InverseDynamicsScratch<double> w;
  w.resize(m.nbodies);
  Eigen::VectorXd r(m.nv), g_only(m.nv);
  inverse_dynamics_residual_in(m, st, qdd, w, r);
  State still = st;
  still.qd.setZero();
  inverse_dynamics_residual_in(m, still, Eigen::VectorXd::Zero(m.nv), w, g_only);
  const double scale = std::max(1.0, g_only.cwiseAbs().maxCoeff());
  const double resid = r.cwiseAbs().maxCoeff() / scale;

  // Coupling: feedback at the last body's origin for user forces 0, f and 2f. It is affine in f_u.
  const int body = m.nbodies - 1;
  std::vector<Grab> grabs{make_grab(d, body, Vec3::Zero())};
  CouplingSnapshot snap;
  make_coupling_snapshot(m, d, grabs, {}, 1, st.t, snap);
  CouplingWorkspace ws(snap);
  Vec6 fu[3], feed[3];
  fu[0].setZero();
  fu[1] << 0, 0, 0, 1.0, -0.5, 2.0;
  fu[2] = 2 * fu[1];
  for (int k = 0; k < 3; ++k) {
    const CouplingStatus s = coupling_forces(snap, &fu[k], ws, &feed[k]);
    if (s != CouplingStatus::kOk) {
      std::fprintf(stderr, "coupling_forces: %s\n", coupling_status_name(s));
      return 1;
    }
  }
  const Vec6 lin = (feed[2] - feed[0]) - 2 * (feed[1] - feed[0]);
  const double affine = lin.norm() / std::max(1.0, (feed[1] - feed[0]).norm());
  const int leaf = m.tree.leaf_of_body[body];
  const bool nodes_ok = ws.nodes_read == 2 * m.tree.depth[leaf] + 1;

  std::printf("model %s: %d bodies, %d dof; |qdd| = %.6g; ID residual / scale = %.3g\n", argv[1],
              m.nbodies, m.nv, qdd.norm(), resid);
  std::printf("coupling: |f_feed(0)| = %.6g, |f_feed(f)| = %.6g, affine error %.3g, nodes read %lld\n",
              feed[0].norm(), feed[1].norm(), affine, static_cast<long long>(ws.nodes_read));
  const bool ok = qdd.allFinite() && resid < 1e-8 && affine < 1e-9 && nodes_ok && feed[1].allFinite() &&
                  (feed[1] - feed[0]).norm() > 0;
  std::printf("%s\n", ok ? "OK" : "FAILED");
  return ok ? 0 : 1;
}
