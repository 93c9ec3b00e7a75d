// imd_bridge: serves a running haptree session over IMD (VMD: `imd connect HOST PORT`). Runs beside
// sim_server (same bus); the IMD pull is published as one more user, so start sim_server with
// --users one above the IMD user id.
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <atomic>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/cli.hpp"
#include "imd_bridge/imd_server.hpp"

int main(int argc, char** argv) {
  CLI::App app{"haptree imd_bridge: the session's atoms over IMD v2 (VMD) or v3, IMD forces back as a user's pull.\n"
               "Coordinates: float32 angstrom (scene nm x 10). Forces from the receiver: kcal/(mol A) in v2\n"
               "(VMD's unit), kJ/(mol A) in v3; published in the scene's kJ/(mol nm) on HAPTREE_USER_FORCE_<id>.\n"
               "sim_server must listen to that user: sim_server --users N with N > --user-id."};
  haptree::ImdServerOptions o;
  haptree::bus::BusOptions b;
  haptree::bus::add_bus_options(app, b);
  app.add_option("--scene", o.scene, "the session's molecule (name such as ala20 or bacteriorhodopsin, or PDB path)")
      ->required();
  app.add_option("--port", o.port, "TCP port (0: any free port, printed at start)")
      ->check(CLI::Range(0, 65535))->capture_default_str();
  app.add_option("--bind", o.bind, "listen address (IPv4; 0.0.0.0 = every interface)")->capture_default_str();
  app.add_option("--imd-version", o.version, "IMD version announced: 2 (VMD) or 3 (IMDv3: time, velocities and forces too)")
      ->check(CLI::IsMember({2, 3}))->capture_default_str();
  app.add_option("--user-id", o.user_id, "user id of the IMD pull (HAPTREE_USER_FORCE_<id>)")
      ->check(CLI::Range(0, 1000))->capture_default_str();
  app.add_option("--rate", o.default_rate, "default steps between frames (the receiver's IMD_TRATE overrides)")
      ->check(CLI::Range(1, 1000000))->capture_default_str();
  app.add_option("--max-force", o.max_force, "clamp on the IMD pull, kJ/(mol nm), before sim_server's own")
      ->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--force-rate-hz", o.force_rate_hz, "USER_FORCE rate while a pull is held")
      ->check(CLI::Range(1.0, 10000.0))->capture_default_str();
  app.add_option("--go-timeout-s", o.go_timeout_s, "handshake -> IMD_GO limit; a silent receiver is dropped")
      ->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--send-timeout-s", o.send_timeout_s, "a receiver that reads nothing for this long is dropped")
      ->check(CLI::PositiveNumber)->capture_default_str();
  bool no_forces = false, no_velocities = false;
  app.add_flag("--no-forces", no_forces, "v3: do not send the per-atom force-field forces (saves the evaluation)");
  app.add_flag("--no-velocities", no_velocities, "v3: do not send velocities");
  CLI11_PARSE(app, argc, argv);
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
