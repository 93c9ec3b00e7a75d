#pragma once
// Viewer: the session seen in a web browser, the fourth thin process.
// Subscribes to the session's channels (scene state, user forces, device states, feedback, stats),
// loads the scene once to know where every atom (or body) sits on its body, and serves on one port
// (127.0.0.1 unless told otherwise; http, or https with a certificate), to holders of a token only, the
// page (viewer/web), the scene as PDB (/scene.pdb) and one WebSocket (/ws). A frame is one binary
// message (<= max_fps, only when something shown changed, else once a second): the overlays and the HUD
// as JSON, then the display points as Float32 when the scene moved. The page acknowledges each frame it
// receives ({"t":"ack","n":frames}); once a client has acknowledged one, it gets no new frame while
// max_frames_in_flight of its frames are unacknowledged, so a tab that reads slowly gets the newest
// state, a few frames late at most, instead of a queue of old ones (the socket's and the browser's
// buffers hold many seconds of frames). A client whose socket still holds more than max_buffered_bytes
// gets no new frame either. Frames skipped for either reason are counted (frames_dropped; the next
// frame a tab gets carries everything that changed): a slow tab never slows the bus handler or the
// other tabs.
// The page is also a device: each tab with the pull token takes a free user id; its pointer comes back
// as JSON and goes out as lcmt_pointer (device metres, the coupler's mapping inverted) to that user's
// `browser` device. The bus handler only copies messages into slots (one small mutex); frames are built
// on the server thread.
#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "haptree/bus/bus.hpp"
#include "haptree/spatial.hpp"
#include "viewer/input.hpp"

namespace haptree {

struct ViewerOptions {
  std::string bind = "127.0.0.1";
  int port = 8080;                 // 0: any free port (see Viewer::port())
  std::string web_dir;             // "" = $HAPTREE_VIEWER_WEB_DIR, else the source tree's viewer/web
  // The scene, as given to sim_server (the viewer loads it to place atoms; it simulates nothing).
  std::string scene = "protein_like";
  int n = 64;
  std::string urdf;
  std::vector<std::string> mesh_paths;   // where a URDF's package:// and relative mesh files are looked up
  int users = 2;                   // user ids 0..users-1 a tab may take (one coupler + browser device each)
  double max_fps = 30;
  size_t max_buffered_bytes = 1 << 20;
  int max_frames_in_flight = 4;    // unacknowledged frames per acknowledging client (>= 1)
  std::string channel_suffix;
  // Access: the page, its files and its WebSocket need a token (`?token=` once, then a cookie). Two roles:
  // the pull token may take a user and pull, the watch token only watches.
  std::string token;               // the pull token; "" = read token_file, else a random one
  std::string token_file;          // file whose first line is the pull token
  std::string watch_token_file;    // file whose first line is the watch-only token ("" = no watch role)
  bool no_token = false;           // serve without a token: refused unless bind is a loopback address
  std::string tls_cert, tls_key;   // PEM files: HTTPS and wss:// instead of http and ws (both or neither)
};

// Requests refused, by reason (each reason logged once per client address).
struct ViewerRefusals {
  int64_t no_token = 0, wrong_token = 0, foreign_origin = 0, watch_pull = 0;
  int64_t total() const { return no_token + wrong_token + foreign_origin + watch_pull; }
};

// 24 random bytes (libsodium) as 48 hex digits.
std::string random_viewer_token();
// The first line of a token file, trimmed; throws std::runtime_error (missing, empty, < 16 characters).
std::string read_viewer_token_file(const std::string& path);

class Viewer {
 public:
  // Loads the scene, subscribes, binds the port. Throws std::runtime_error with the reason (port in
  // use, web files missing, unknown scene).
  Viewer(bus::Bus& bus, const ViewerOptions& options);
  ~Viewer();
  // Serves until stop is true. Returns 0.
  int run(const std::atomic<bool>& stop);
  int port() const;
  std::string url() const;          // with ?token= of the pull token (none with no_token)
  std::string watch_url() const;    // with the watch token; "" without one
  ViewerRefusals refusals() const;
  int64_t frames_sent() const;
  int64_t frames_dropped() const;
  int64_t frame_bytes() const;      // WebSocket payload bytes of all frames sent
  int clients() const;
  int64_t pointer_messages() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace haptree
