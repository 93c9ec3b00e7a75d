// haptree_demo: simulates a procedural scene with full DCA and prints per-step timing.
#include <CLI/CLI.hpp>

#include <chrono>
#include <cstdio>

#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"

int main(int argc, char** argv) {
  CLI::App app{"haptree_demo: simulate a scene with DCA forward dynamics and print step timing"};
  std::string scene = "protein_like";
  int n = 1024, steps = 2000, report = 200;
  double dt = 1e-3;
  app.add_option("--scene", scene, "chain, binary_tree, random_tree, star, protein_like")
      ->capture_default_str();
  app.add_option("--n", n, "bodies (ignored by protein_like)")->capture_default_str()->check(CLI::Range(1, 1 << 20));
  app.add_option("--steps", steps, "steps to simulate")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--dt", dt, "time step [s]")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--report-every", report, "print a line every N steps")->capture_default_str();
  CLI11_PARSE(app, argc, argv);
  try {
    haptree::SceneOptions o;
    o.n = n;
    auto model = haptree::make_scene(scene, o);
    haptree::State st(*model);
    haptree::Data d(*model);
    std::printf("scene %s: %d bodies, %d DOF, assembly depth %d\n", scene.c_str(),
                model->nbodies - 1, model->nv, model->tree.max_depth);
    double total = 0;
    for (int i = 1; i <= steps; ++i) {
      const auto t0 = std::chrono::steady_clock::now();
      haptree::forward_dynamics(*model, d, st);
      haptree::integrate(*model, st.q, st.qd, d.qdd, dt);
      const double us =
          std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count();
      total += us;
      if (i % report == 0 || i == steps) {
        haptree::body_dynamics_terms(*model, d, st);
        std::printf("step %6d  t=%.3f s  %.1f us/step (mean %.1f)  E=%.6g J\n", i, st.t, us,
                    total / i, haptree::kinetic_energy(*model, d) + haptree::potential_energy(*model, d));
      }
      st.t += dt;
    }
    std::printf("done: %d steps, mean %.1f us per step (%.3f us per DOF)\n", steps, total / steps,
                total / steps / model->nv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
}
