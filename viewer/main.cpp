// viewer: the session in a web browser (page, scene, live frames over a WebSocket; the mouse as a device).
#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include <atomic>
#include <cstdio>

#include "haptree/bus/cli.hpp"
#include "haptree/bus/session_config.hpp"
#include "viewer/viewer.hpp"

int main(int argc, char** argv) {
  CLI::App app{"haptree viewer: serves a web page with the live scene (NGL), the grabs, the feedback forces and a\n"
               "HUD; a tab's mouse drives the `browser` device of a free user (device_bridge --device-kind browser).\n"
               "Works beside any session: embedded, --processes, across hosts, or an lcm-logplayer replay."};
  haptree::bus::ProgramCli cli(app, "viewer",
                               {{"--bind", "--viewer-bind"},
                                {"--port", "--viewer-port"},
                                {"--users", "--viewer-users"},
                                {"--token-file", "--viewer-token-file"},
                                {"--watch-token-file", "--viewer-watch-token-file"},
                                {"--no-token", "--viewer-no-token"},
                                {"--tls-cert", "--viewer-tls-cert"},
                                {"--tls-key", "--viewer-tls-key"}});
  haptree::ViewerOptions o;
  haptree::bus::BusOptions b;
  haptree::bus::add_bus_options(app, b, /*shm_link=*/false, /*mirror=*/false);
  app.add_option("--viewer-bind", o.bind, "address to listen on (127.0.0.1: this machine only)")->capture_default_str();
  app.add_option("--viewer-port", o.port, "HTTP/WebSocket port (0 = any free port, printed)")
      ->check(CLI::Range(0, 65535))->capture_default_str();
  app.add_option("--web-dir", o.web_dir, "folder (path) with index.html, viewer.js, vendor/ngl.js (default: the source tree's viewer/web)");
  app.add_option("--scene", o.scene, "the session's scene, as given to sim_server (procedural name, molecule name or PDB)")
      ->capture_default_str();
  app.add_option("--n", o.n, "bodies of a procedural scene (count)")->capture_default_str();
  app.add_option("--urdf", o.urdf, "URDF file (overrides --scene)");
  app.add_option("--mesh-path", o.mesh_paths, "folder(s) where the URDF's package:// and relative mesh files are found (paths)");
  app.add_option("--viewer-users", o.users, "users a page can be, count: user ids 0..N-1 (each needs a coupler and a browser device)")
      ->check(CLI::Range(1, 8))->capture_default_str();
  app.add_option("--max-fps", o.max_fps, "frames sent to each tab, per second")->check(CLI::Range(1.0, 240.0))
      ->capture_default_str();
  app.add_option("--viewer-token-file", o.token_file,
                 "file whose first line is the token that may pull (default: a random token, printed in the URL)")
      ->check(CLI::ExistingFile);
  app.add_option("--viewer-watch-token-file", o.watch_token_file, "file whose first line is a watch-only token (may not pull)")
      ->check(CLI::ExistingFile);
  app.add_flag("--viewer-no-token", o.no_token, "serve without a token (only with a loopback --viewer-bind: anyone on this machine can pull)");
  app.add_option("--viewer-tls-cert", o.tls_cert, "PEM certificate (chain): serve https:// and wss:// (with --viewer-tls-key)")
      ->check(CLI::ExistingFile);
  app.add_option("--viewer-tls-key", o.tls_key, "PEM private key of --viewer-tls-cert")->check(CLI::ExistingFile);
  if (const int rc = cli.parse(argc, argv); rc >= 0) return rc;
  o.channel_suffix = b.channel_suffix;
  std::atomic<bool>& g_stop = haptree::bus::install_stop_signals();
  try {
    haptree::bus::Bus bus(b.lcm_url);
    haptree::Viewer viewer(bus, o);
    haptree::bus::HandlerThread handler(bus);
    std::printf("viewer: open %s\n", viewer.url().c_str());
    if (!viewer.watch_url().empty()) std::printf("viewer: watch only %s\n", viewer.watch_url().c_str());
    std::fflush(stdout);
    const int rc = viewer.run(g_stop);
    handler.stop();
    const haptree::ViewerRefusals r = viewer.refusals();
    spdlog::info("viewer: {} frames sent ({} bytes), {} dropped for slow tabs, {} pointer messages; refused: {} "
                 "without token, {} wrong token, {} foreign origin, {} watch token pulling", viewer.frames_sent(),
                 viewer.frame_bytes(), viewer.frames_dropped(), viewer.pointer_messages(), r.no_token, r.wrong_token,
                 r.foreign_origin, r.watch_pull);
    return rc;
  } catch (const std::exception& e) {
    spdlog::critical("{}", e.what());
    return 1;
  }
}
