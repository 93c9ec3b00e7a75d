// sim_server: adaptive DCA simulation, one coupling snapshot per grabbing user after every step.
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <atomic>

#include "haptree/bus/cli.hpp"
#include "haptree/bus/realtime_cli.hpp"
#include "haptree/bus/session_config.hpp"
#include "haptree/molecule/scene.hpp"
#include "sim_server/sim_server.hpp"

int main(int argc, char** argv) {
  CLI::App app{"haptree sim_server: adaptive DCA dynamics + coupling snapshots over LCM"};
  haptree::bus::ProgramCli cli(app, "sim_server", {{"--rate-hz", "--sim-rate-hz"}});
  haptree::SimServerOptions o;
  o.rate_hz = 1000;   // the launcher's: a haptic session steps at a steady rate
  haptree::bus::BusOptions b;
  haptree::bus::add_bus_options(app, b, /*shm_link=*/false, /*mirror=*/false);   // the server has no device link
  std::string molecules;
  for (const auto& m : haptree::mol::molecular_scene_names()) molecules += (molecules.empty() ? "" : ", ") + m;
  app.add_option("--scene", o.scene,
                 "procedural: chain|binary_tree|random_tree|star|protein_like (857 DOF, fixed size); molecule: " +
                     molecules + "; or a PDB/mmCIF path")
      ->capture_default_str();
  app.add_option("--n", o.n, "bodies of a procedural scene (count)")->check(CLI::Range(1, 1 << 20))->capture_default_str();
  app.add_option("--urdf", o.urdf, "URDF file (overrides --scene)");
  app.add_option("--budget-dofs", o.budget_dofs, "adaptive budget, active degrees of freedom (count)")->check(CLI::Range(1, 1 << 24))->capture_default_str();
  app.add_option("--epsilon", o.epsilon, "> 0: threshold mode with this bound on the inactive joints' acceleration metric sum qdd^T A qdd, scene units (A = 1: (rad or scene length)^2/(scene time)^4); 0: budget mode")
      ->check(haptree::bus::finite_in(0, 1e30))->capture_default_str();
  app.add_option("--reselect-every", o.reselect_every, "steps between active-region selections (count)")
      ->check(CLI::Range(1, 1 << 30))->capture_default_str();
  app.add_option("--dt", o.dt, "time step, scene time units: s for procedural and URDF scenes, ps for molecules (default: 0.001 s; 0.0005 ps for molecules)")
      ->check(haptree::bus::positive(1.0))->capture_default_str();
  app.add_option("--steps", o.steps, "steps to run, count (0 = until stopped)")
      ->check(CLI::NonNegativeNumber)->capture_default_str();
  app.add_option("--sim-rate-hz", o.rate_hz, "simulation step rate, Hz (0 = free-running)")
      ->check(haptree::bus::finite_in(0, 1e6))->capture_default_str();
  app.add_option("--display-rate-hz", o.display_rate_hz, "scene state rate, Hz (0: none)")
      ->check(haptree::bus::finite_in(0, 1e4))->capture_default_str();
  app.add_option("--users", o.users, "users, count: user ids 0..N-1 are listened to (HAPTREE_USER_FORCE_<id>)")
      ->check(CLI::Range(1, 64))->capture_default_str();
  std::vector<double> gravity;
  app.add_option("--gravity", gravity,
                 "X,Y,Z gravity of procedural/URDF scenes, m/s^2 (default: none for protein_like, which "
                 "stands for a molecule; 0,0,-9.81 for the robot scenes; molecules never have gravity)")
      ->delimiter(',')->expected(3)->check(haptree::bus::finite_in(-1e4, 1e4));
  app.add_option("--max-joint-rate", o.max_joint_rate,
                 "blow-up guard, rad or scene length per scene time unit: a joint rate above this (or a non-finite state) "
                 "restores the last healthy checkpoint at rest and is counted as a reset")
      ->check(haptree::bus::positive(1e30))->capture_default_str();
  app.add_option("--checkpoint-every", o.checkpoint_every, "steps between checkpoints of a healthy state (count)")
      ->check(CLI::Range(1, 1 << 30))->capture_default_str();
  app.add_option("--user-force-stale-s", o.user_force_stale_s,
                 "watchdog on user forces, s: a user whose USER_FORCE has not arrived for this long has the force "
                 "ramped to zero (over --user-force-ramp-s; counted in the stats' watchdog_events)")
      ->check(haptree::bus::positive(10.0))->capture_default_str();
  app.add_option("--user-force-ramp-s", o.user_force_ramp_s, "time from full user force to zero once stale, s")
      ->check(haptree::bus::finite_in(0, 10.0))->capture_default_str();
  app.add_option("--max-user-force", o.max_user_force,
                 "scene-side limit on an incoming user force (scene force units; the moment gets the same number "
                 "per scene length): larger ones are clamped, non-finite ones zeroed, both counted. Default: "
                 "2 x the coupler's default max_force_n / force_scale (2 x 3 N / 0.5)")
      ->check(haptree::bus::positive(1e12))->capture_default_str();
  // ---- trajectory ----
  app.add_option("--trajectory", o.trajectory,
                 "record atom positions (molecules) or body origins to FILE: .dcd (CHARMM/NAMD binary) or .pdb "
                 "(multi-model), in angstrom");
  app.add_option("--trajectory-every-steps", o.trajectory_every_steps, "steps between trajectory frames (count)")
      ->check(CLI::Range(1, 100000000))->capture_default_str();
  app.add_option("--trajectory-every-time", o.trajectory_every_time,
                 "> 0: scene time between frames instead (ps for molecules, s otherwise)")
      ->check(CLI::NonNegativeNumber)->capture_default_str();
  // ---- end trajectory ----
  haptree::bus::RealtimeOptions rt;   // e.g. --cpu-affinity to keep the server off the coupler's CPU
  haptree::bus::add_realtime_options(app, rt);
  const int rc = cli.parse(argc, argv, [&] {   // a molecule's own time step unless one is given
    haptree::bus::set_default(app, "--dt", o.dt, haptree::bus::scene_defaults(o.scene, o.urdf).dt);
  });
  if (rc >= 0) return rc;
  if (o.scene == "protein_like" && app.count("--n") > 0 && o.urdf.empty())
    spdlog::warn("--n {} is ignored: protein_like has a fixed size (343 backbone bodies, 857 DOF)", o.n);
  if (gravity.size() == 3) o.gravity = haptree::Vec3(gravity[0], gravity[1], gravity[2]);
  o.channel_suffix = b.channel_suffix;
  std::atomic<bool>& g_stop = haptree::bus::install_stop_signals();
  haptree::bus::log_realtime_report(haptree::bus::apply_realtime(rt), "sim_server");   // before any thread
  try {
    haptree::bus::Bus bus(b.lcm_url);
    haptree::bus::HandlerThread handler(bus);
    haptree::SimServer server(bus, o);
    const int rc = server.run(g_stop);
    handler.stop();
    const auto& k = server.counters();
    spdlog::info("sim_server: {} steps, {} snapshots, {} user forces in, {} user-force watchdog trips, longest "
                 "USER_FORCE gap {:.1f} ms, {} clamped, {} non-finite, {} refused",
                 server.steps_done(), server.snapshots_published(), k.user_forces_in.load(), k.watchdog_events.load(),
                 1e3 * k.user_force_gap_max_s.load(), k.clamp_events.load(), k.nonfinite_events.load(),
                 k.foreign_rejected.load());
    return rc;
  } catch (const std::exception& e) {
    spdlog::critical("{}", e.what());
    return 1;
  }
}
