// ImdServer: serves a haptree session over IMD (v2 for VMD, or v3) on TCP. It subscribes to the
// session's scene state (body poses), places the atoms with the torsion model it loads once, sends
// coordinates (float32 Å) to the connected receiver every `rate` simulation steps (IMD_TRATE), and
// turns the receiver's IMD_MDCOMM atom forces into one user's pull: HAPTREE_USER_FORCE_<user_id> on
// the body holding the most-pulled atom, so it goes through sim_server's clamp and safety layer like
// any user force. One receiver at a time; a receiver that vanishes, stalls or sends garbage is dropped
// with one log line, and the session never waits for it (poll with timeouts, bounded buffers).
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "haptree/bus/bus.hpp"
#include "haptree/imd/protocol.hpp"
#include "haptree/lcmt_scene_state.hpp"
#include "haptree/lcmt_user_force.hpp"

namespace haptree {

struct ImdServerOptions {
  int port = 8888;                 // 0: any free port (see ImdServer::port())
  std::string bind = "127.0.0.1";  // listen address; 0.0.0.0 for every interface
  int version = 2;                 // IMD version announced in the handshake: 2 (VMD) or 3
  std::string scene;               // molecule name or PDB path: the session's scene
  int user_id = 1;                 // the IMD pull is published as this user (sim_server --users > id)
  std::string channel_suffix;
  int default_rate = 1;            // steps between frames until IMD_TRATE (and after IMD_TRATE < 1)
  double max_force = 5000;         // kJ/(mol nm): clamp on the total IMD pull before it is published
  double force_rate_hz = 200;      // USER_FORCE rate while a pull is held
  double go_timeout_s = 2;         // handshake -> IMD_GO (the spec asks 1 s of engines; we allow more)
  double send_timeout_s = 5;       // a receiver that reads nothing for this long is dropped
  bool velocities = true;          // v3: send velocities (finite difference of the last two frames)
  // v3: send per-atom force-field forces, kJ/(mol Å), at the frame's positions (the scene's
  // evaluator: every term between rigid bodies; terms inside one body do no work and are left out).
  bool forces = true;
};

struct ImdCounters {
  std::atomic<int64_t> clients{0};          // accepted connections that got a handshake
  std::atomic<int64_t> dropped{0};          // dropped for garbage, timeout, I/O error
  std::atomic<int64_t> refused_busy{0};     // connections closed because a receiver was served
  std::atomic<int64_t> frames_sent{0};
  std::atomic<int64_t> frames_skipped{0};   // due but the receiver had not read the last one yet
  std::atomic<int64_t> mdcomm{0};           // MD-communication packets accepted
  std::atomic<int64_t> forces_published{0};
  std::atomic<int64_t> scene_mismatch{0};   // scene states whose body count is not the model's
};

class ImdServer {
 public:
  // Loads the scene's torsion model, binds and listens (throws std::runtime_error naming the address
  // and the reason when it cannot), subscribes to HAPTREE_SCENE_STATE on `bus`.
  ImdServer(bus::Bus& bus, const ImdServerOptions& options);
  ~ImdServer();
  // Serves until `stop` is true. Returns 0.
  int run(const std::atomic<bool>& stop);
  int port() const { return port_; }         // the bound port (useful with port 0)
  int natoms() const;
  const ImdCounters& counters() const { return counters_; }
  bool client_connected() const { return connected_.load(); }

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  ImdCounters counters_;
  std::atomic<bool> connected_{false};
  int port_ = 0;
};

}  // namespace haptree
