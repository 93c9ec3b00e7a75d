// imd_bridge: serves a running haptree session over IMD (VMD: `imd connect HOST PORT`). Runs beside
// sim_server (same bus); the IMD pull is published as one more user, so start sim_server with
// --users one above the IMD user id.
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <atomic>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/cli.hpp"
#include "haptree/bus/session_config.hpp"
#include "imd_bridge/imd_server.hpp"

int main(int argc, char** argv) {
  CLI::App app{"haptree imd_bridge: the session's atoms over IMD v2 (VMD) or v3, IMD forces back as a user's pull.\n"
               "Coordinates: float32 angstrom (scene nm x 10). Forces from the receiver: kcal/(mol A) in v2\n"
               "(VMD's unit), kJ/(mol A) in v3; published in the scene's kJ/(mol nm) on HAPTREE_USER_FORCE_<id>.\n"
               "sim_server must listen to that user: sim_server --users N with N > --imd-user."};
  haptree::bus::ProgramCli cli(app, "imd_bridge",
                               {{"--port", "--imd-port"}, {"--bind", "--imd-bind"}, {"--user-id", "--imd-user"},
                                {"--rate", "--imd-every-steps"}, {"--max-force", "--max-user-force"},
                                {"--force-rate-hz", "--user-force-rate-hz"}, {"--go-timeout-s", "--imd-go-timeout-s"},
                                {"--send-timeout-s", "--imd-send-timeout-s"}});
  haptree::ImdServerOptions o;
  haptree::bus::BusOptions b;
  haptree::bus::add_bus_options(app, b, /*shm_link=*/false, /*mirror=*/false);
  app.add_option("--scene", o.scene, "the session's molecule (name such as ala20 or bacteriorhodopsin, or PDB path)")
      ->required();
  app.add_option("--imd-port", o.port, "IMD TCP port (0: any free port, printed at start)")
      ->check(CLI::Range(0, 65535))->capture_default_str();
  app.add_option("--imd-bind", o.bind, "IMD listen address (IPv4; 0.0.0.0 = every interface)")->capture_default_str();
  app.add_option("--imd-version", o.version, "IMD version announced: 2 (VMD) or 3 (IMDv3: time, velocities and forces too)")
      ->check(CLI::IsMember({2, 3}))->capture_default_str();
  app.add_option("--imd-user", o.user_id, "user id of the IMD pull (HAPTREE_USER_FORCE_<id>)")
      ->check(CLI::Range(0, 1000))->capture_default_str();
  app.add_option("--imd-every-steps", o.default_rate, "sim steps between IMD frames, count (the receiver's IMD_TRATE overrides)")
      ->check(CLI::Range(1, 1000000))->capture_default_str();
  app.add_option("--max-user-force", o.max_force, "clamp on the IMD pull before it is published, scene force units (kJ/(mol nm)); sim_server clamps with its own --max-user-force")
      ->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--user-force-rate-hz", o.force_rate_hz, "USER_FORCE publication rate while a pull is held, Hz")
      ->check(CLI::Range(1.0, 10000.0))->capture_default_str();
  app.add_option("--imd-go-timeout-s", o.go_timeout_s, "handshake -> IMD_GO limit, s; a silent receiver is dropped")
      ->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--imd-send-timeout-s", o.send_timeout_s, "a receiver that reads nothing for this long is dropped, s")
      ->check(CLI::PositiveNumber)->capture_default_str();
  bool no_forces = false, no_velocities = false;
  app.add_flag("--no-forces", no_forces, "v3: do not send the per-atom force-field forces (saves the evaluation)");
  app.add_flag("--no-velocities", no_velocities, "v3: do not send velocities");
  if (const int rc = cli.parse(argc, argv); rc >= 0) return rc;
  o.forces = !no_forces;
  o.velocities = !no_velocities;
  o.channel_suffix = b.channel_suffix;
  std::atomic<bool>& stop = haptree::bus::install_stop_signals();
  try {
    haptree::bus::Bus bus(b.lcm_url);
    haptree::ImdServer server(bus, o);
    haptree::bus::HandlerThread handler(bus);
    const int rc = server.run(stop);
    handler.stop();
    const auto& k = server.counters();
    spdlog::info("imd_bridge: {} receiver(s), {} dropped, {} frames sent ({} skipped), {} MDCOMM packets",
                 k.clients.load(), k.dropped.load(), k.frames_sent.load(), k.frames_skipped.load(), k.mdcomm.load());
    return rc;
  } catch (const std::exception& e) {
    spdlog::critical("{}", e.what());
    return 1;
  }
}
