// sim_server: adaptive DCA simulation, one coupling snapshot per grabbing user after every step.
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <atomic>

#include "haptree/bus/cli.hpp"
#include "sim_server/sim_server.hpp"

int main(int argc, char** argv) {
  CLI::App app{"haptree sim_server: adaptive DCA dynamics + coupling snapshots over LCM"};
  haptree::SimServerOptions o;
  haptree::bus::BusOptions b;
  haptree::bus::add_bus_options(app, b);
  app.add_option("--scene", o.scene, "chain|binary_tree|random_tree|star|protein_like, or a molecule name / PDB path")
      ->capture_default_str();
  app.add_option("--n", o.n, "bodies of a procedural scene")->capture_default_str();
  app.add_option("--urdf", o.urdf, "URDF file (overrides --scene)");
  app.add_option("--budget-dofs", o.budget_dofs, "adaptive budget (active DOFs)")->capture_default_str();
  app.add_option("--epsilon", o.epsilon, "> 0: threshold mode with this error bound")->capture_default_str();
  app.add_option("--reselect-every", o.reselect_every, "steps between active-region selections")->capture_default_str();
  app.add_option("--dt", o.dt, "time step, scene units (s; ps for molecules, e.g. 0.0005)")->capture_default_str();
  app.add_option("--steps", o.steps, "steps to run (0 = until stopped)")->capture_default_str();
  app.add_option("--rate-hz", o.rate_hz, "step rate (0 = free-running)")->capture_default_str();
  app.add_option("--display-rate-hz", o.display_rate_hz, "scene state rate")->capture_default_str();
  app.add_option("--users", o.users, "number of users (HAPTREE_USER_FORCE_0..)")->capture_default_str();
  std::vector<double> gravity;
  app.add_option("--gravity", gravity,
                 "X,Y,Z gravity of procedural/URDF scenes, m/s^2 (default: none for protein_like, which "
                 "stands for a molecule; 0,0,-9.81 for the robot scenes; molecules never have gravity)")
      ->delimiter(',')->expected(3);
  app.add_option("--max-joint-rate", o.max_joint_rate,
                 "blow-up guard: a joint rate above this (or a non-finite state) restores the last "
                 "healthy checkpoint at rest and is counted as a reset")->capture_default_str();
  app.add_option("--checkpoint-every", o.checkpoint_every, "steps between checkpoints of a healthy state")
      ->capture_default_str();
  // ---- trajectory (issue 12) ----
  app.add_option("--trajectory", o.trajectory,
                 "record atom positions (molecules) or body origins to FILE: .dcd (CHARMM/NAMD binary) or .pdb "
                 "(multi-model), in angstrom");
  app.add_option("--trajectory-every-steps", o.trajectory_every_steps, "steps between trajectory frames")
      ->check(CLI::Range(1, 100000000))->capture_default_str();
  app.add_option("--trajectory-every-time", o.trajectory_every_time,
                 "> 0: scene time between frames instead (ps for molecules, s otherwise)")
      ->check(CLI::NonNegativeNumber)->capture_default_str();
  // ---- end trajectory ----
  CLI11_PARSE(app, argc, argv);
  if (gravity.size() == 3) o.gravity = haptree::Vec3(gravity[0], gravity[1], gravity[2]);
  o.channel_suffix = b.channel_suffix;
  std::atomic<bool>& g_stop = haptree::bus::install_stop_signals();
  try {
    haptree::bus::Bus bus(b.lcm_url);
    haptree::bus::HandlerThread handler(bus);
    haptree::SimServer server(bus, o);
    const int rc = server.run(g_stop);
    handler.stop();
    spdlog::info("sim_server: {} steps, {} snapshots", server.steps_done(), server.snapshots_published());
    return rc;
  } catch (const std::exception& e) {
    spdlog::critical("{}", e.what());
    return 1;
  }
}
