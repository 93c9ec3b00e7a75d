#include "imd_bridge/imd_server.hpp"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <spdlog/spdlog.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/molecule/body_poses.hpp"
#include "haptree/molecule/scene.hpp"

namespace haptree {

using Clock = std::chrono::steady_clock;

namespace {
// The one place outgoing messages are stamped (schema version, clock): adapt here when the
// message header changes.
template <class T>
void stamp_message(T& msg) {
  static const int64_t instance_id = bus::new_instance_id();   // this IMD server's origin: consumers follow one producer per channel
  bus::stamp(msg, instance_id);
}

double seconds_since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

bool is_procedural(const std::string& s) {
  return s == "chain" || s == "binary_tree" || s == "random_tree" || s == "star" || s == "protein_like";
}
}  // namespace

struct ImdServer::Impl {
  enum class Phase { kNone, kAwaitGo, kStreaming };

  Impl(bus::Bus& b, const ImdServerOptions& o, ImdCounters& k, std::atomic<bool>& c)
      : bus(b), opt(o), counters(k), connected(c) {}

  bus::Bus& bus;
  ImdServerOptions opt;
  ImdCounters& counters;
  std::atomic<bool>& connected;
  mol::MolecularScene scene;
  int natoms = 0;
  double force_to_scene = 1;   // receiver force unit -> kJ/(mol nm)

  bus::LatestValue<lcmt_scene_state> box;
  int listen_fd = -1;

  // The receiver.
  int fd = -1;
  Phase phase = Phase::kNone;
  Clock::time_point accepted_at, send_progress_at;
  std::vector<uint8_t> in, out;
  size_t out_off = 0;
  imd::ClientMessage msg;
  bool paused = false;
  int rate = 1;
  int64_t last_frame_version = std::numeric_limits<int64_t>::min();

  // Latest scene state, as atoms.
  bool have_state = false, have_prev = false;
  int64_t version = 0, prev_version = 0;
  double sim_time = 0, prev_time = 0, dt = 0;
  std::vector<Vec3> body_r;
  std::vector<Quat> body_q;
  std::vector<Vec3> x, x_prev;
  std::vector<float> fx, fv, ff;
  std::vector<Vec3> atom_f;
  bool mismatch_logged = false;

  // The pull.
  bool pulling = false;
  int releases_pending = 0;
  int anchor = -1;                     // atom whose point is the grab point (material point)
  std::vector<int32_t> pull_atoms;
  std::vector<Vec3> pull_forces;       // kJ/(mol nm)
  lcmt_user_force uf{};
  int64_t seq = 0;
  std::string force_channel;
  Clock::time_point next_force = Clock::now();

  bool pending() const { return out_off < out.size(); }

  void listen_on() {
    listen_fd = ::socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (listen_fd < 0) throw std::runtime_error(std::string("IMD: socket(): ") + std::strerror(errno));
    const int one = 1;
    ::setsockopt(listen_fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_port = htons(static_cast<uint16_t>(opt.port));
    if (::inet_pton(AF_INET, opt.bind.c_str(), &a.sin_addr) != 1)
      throw std::runtime_error("IMD: --bind '" + opt.bind + "' is not an IPv4 address (e.g. 127.0.0.1)");
    if (::bind(listen_fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 || ::listen(listen_fd, 4) != 0) {
      const std::string why = std::strerror(errno);
      ::close(listen_fd);
      listen_fd = -1;
      throw std::runtime_error("IMD: cannot listen on " + opt.bind + ":" + std::to_string(opt.port) + ": " + why +
                               (opt.port < 1024 && opt.port > 0 ? " (ports below 1024 need root)" : "") +
                               "; choose another --imd-port");
    }
  }

  void drop(const std::string& why, bool error) {
    if (fd < 0) return;
    if (error) {
      spdlog::warn("IMD: receiver dropped: {}", why);
      counters.dropped.fetch_add(1);
    } else {
      spdlog::info("IMD: receiver disconnected: {}", why);
    }
    ::close(fd);
    fd = -1;
    phase = Phase::kNone;
    in.clear();
    out.clear();
    out_off = 0;
    connected.store(false);
    release();
  }

  void accept_one() {
    const int c = ::accept4(listen_fd, nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (c < 0) return;
    if (fd >= 0) {
      counters.refused_busy.fetch_add(1);
      spdlog::warn("IMD: a second receiver connected while one is served; closed it");
      ::close(c);
      return;
    }
    const int one = 1;
    ::setsockopt(c, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    ::setsockopt(c, SOL_SOCKET, SO_KEEPALIVE, &one, sizeof one);
    // A small kernel send buffer (two frames): a slow receiver gets the newest frame, not seconds of
    // queued old ones, and a stalled one is noticed within --send-timeout-s.
    const int sndbuf = static_cast<int>(std::max<size_t>(65536, 2 * (64 + 36 * static_cast<size_t>(natoms))));
    ::setsockopt(c, SOL_SOCKET, SO_SNDBUF, &sndbuf, sizeof sndbuf);
    fd = c;
    phase = Phase::kAwaitGo;
    accepted_at = send_progress_at = Clock::now();
    paused = false;
    rate = opt.default_rate;
    last_frame_version = std::numeric_limits<int64_t>::min();
    in.clear();
    out.clear();
    out_off = 0;
    imd::append_handshake(out, opt.version);
    if (opt.version >= 3) {
      imd::SessionInfo si;
      si.velocities = opt.velocities;
      si.forces = opt.forces;
      imd::append_session_info(out, si);
    }
    counters.clients.fetch_add(1);
    connected.store(true);
    spdlog::info("IMD: receiver connected (IMD v{}, {} atoms); waiting for IMD_GO", opt.version, natoms);
  }

  void flush() {
    while (fd >= 0 && pending()) {
      const ssize_t n = ::send(fd, out.data() + out_off, out.size() - out_off, MSG_NOSIGNAL | MSG_DONTWAIT);
      if (n > 0) {
        out_off += static_cast<size_t>(n);
        send_progress_at = Clock::now();
      } else if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR)) {
        return;
      } else {
        drop(std::string("send: ") + (n < 0 ? std::strerror(errno) : "connection closed"), true);
        return;
      }
    }
    if (!pending()) {
      out.clear();
      out_off = 0;
    }
  }

  void read_client() {
    const size_t cap = imd::max_client_message_bytes(natoms);
    for (;;) {
      if (in.size() >= cap) break;   // a full message is waiting to be parsed
      uint8_t buf[65536];
      const size_t want = std::min(sizeof buf, cap - in.size());
      const ssize_t n = ::recv(fd, buf, want, MSG_DONTWAIT);
      if (n > 0) {
        in.insert(in.end(), buf, buf + n);
        if (static_cast<size_t>(n) < want) break;
        continue;
      }
      if (n == 0) {
        if (!in.empty()) return drop("closed the connection in the middle of a packet (" +
                                     std::to_string(in.size()) + " bytes)", true);
        return drop("closed the connection", false);
      }
      if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) break;
      return drop(std::string("recv: ") + std::strerror(errno), true);
    }
    size_t at = 0;
    while (fd >= 0) {
      const imd::ParseResult r = imd::parse_client_message(in.data() + at, in.size() - at, natoms, msg);
      if (r.status == imd::ParseStatus::kError) return drop("bad packet: " + r.error, true);
      if (r.status == imd::ParseStatus::kNeedMore) break;
      at += r.consumed;
      handle(msg);
    }
    if (fd >= 0) in.erase(in.begin(), in.begin() + static_cast<std::ptrdiff_t>(at));
  }

  void handle(const imd::ClientMessage& m) {
    using imd::Type;
    switch (m.type) {
      case Type::kGo:
        if (phase == Phase::kAwaitGo) spdlog::info("IMD: IMD_GO received; streaming every {} step(s)", rate);
        phase = Phase::kStreaming;
        break;
      case Type::kDisconnect:
        drop("IMD_DISCONNECT", false);
        break;
      case Type::kKill:
        // Not honoured: the session has other users (haptic devices); the receiver only leaves.
        drop("IMD_KILL (not honoured: the session keeps running for its other users)", false);
        break;
      case Type::kPause:
        paused = opt.version >= 3 ? true : !paused;   // v2: toggle; v3: idempotent
        spdlog::info("IMD: {}", paused ? "paused (no frames; IMD pull released)" : "resumed (v2 toggle)");
        if (paused) release();
        break;
      case Type::kResume:
        if (paused) spdlog::info("IMD: resumed");
        paused = false;
        break;
      case Type::kTrate:
        rate = m.value < 1 ? opt.default_rate : m.value;
        spdlog::info("IMD: transmission rate: a frame every {} step(s)", rate);
        break;
      case Type::kWait:
        break;   // the session never waits for a receiver
      case Type::kMdcomm:
        counters.mdcomm.fetch_add(1);
        if (!paused) set_pull(m);
        break;
      default:
        drop(std::string("unexpected ") + imd::type_name(static_cast<int32_t>(m.type)), true);
        break;
    }
  }

  void set_pull(const imd::ClientMessage& m) {
    const int n = m.value;
    if (n == 0) return release();
    pull_atoms.assign(m.indices.begin(), m.indices.end());
    pull_forces.resize(static_cast<size_t>(n));
    int strongest = m.indices[0];
    double best = -1;
    for (int i = 0; i < n; ++i) {
      pull_forces[i] = force_to_scene * Vec3(m.forces[3 * i], m.forces[3 * i + 1], m.forces[3 * i + 2]);
      if (pull_forces[i].norm() > best) best = pull_forces[i].norm(), strongest = m.indices[i];
    }
    // Same body as before: keep the anchor (sim_server keeps the material point of the grab).
    if (!pulling || anchor < 0 ||
        scene.torsion.atom_model_body[anchor] != scene.torsion.atom_model_body[strongest])
      anchor = strongest;
    pulling = true;
    releases_pending = 0;
    next_force = Clock::now();   // publish now
  }

  void release() {
    if (pulling) releases_pending = 5;   // repeated: LCM over UDP may drop one
    pulling = false;
    anchor = -1;
  }

  void publish_force_if_due() {
    if ((!pulling && releases_pending == 0) || Clock::now() < next_force) return;
    next_force = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                    std::chrono::duration<double>(1.0 / opt.force_rate_hz));
    stamp_message(uf);
    uf.seq = ++seq;
    uf.user_id = opt.user_id;
    uf.snapshot_version = version;
    if (!pulling) {
      --releases_pending;
      uf.active = false;
      uf.grab_body = 0;
      for (double& f : uf.force) f = 0;
    } else {
      if (!have_state) return;   // no atom positions yet
      // One body takes the whole pull: the wrench of all pulled atoms about the anchor atom.
      const Vec3 p = x[anchor];
      Vec3 F = Vec3::Zero(), M = Vec3::Zero();
      double biggest = 0;
      for (size_t i = 0; i < pull_atoms.size(); ++i) {
        F += pull_forces[i];
        M += (x[pull_atoms[i]] - p).cross(pull_forces[i]);
        biggest = std::max(biggest, pull_forces[i].norm());
      }
      const double big = std::max(F.norm(), biggest);
      const double s = big > opt.max_force ? opt.max_force / big : 1.0;
      uf.active = true;
      uf.grab_body = scene.torsion.atom_model_body[anchor];
      for (int i = 0; i < 3; ++i) {
        uf.grab_point[i] = p[i];
        uf.force[i] = s * M[i];
        uf.force[3 + i] = s * F[i];
      }
    }
    if (bus.publish(force_channel, uf) == 0) counters.forces_published.fetch_add(1);
  }

  void on_scene_state(const lcmt_scene_state& s) {
    const int nb = scene.model->nbodies;
    if (s.nbodies != nb || static_cast<int>(s.body_position.size()) != nb ||
        static_cast<int>(s.body_orientation.size()) != nb) {
      counters.scene_mismatch.fetch_add(1);
      if (!mismatch_logged)
        spdlog::error("IMD: scene state with {} bodies, but the scene '{}' has {}: wrong --scene?", s.nbodies,
                      opt.scene, nb);
      mismatch_logged = true;
      return;
    }
    body_r.resize(nb);
    body_q.resize(nb);
    for (int k = 0; k < nb; ++k) {
      const auto& p = s.body_position[k];
      const auto& q = s.body_orientation[k];
      body_r[k] = Vec3(p[0], p[1], p[2]);
      body_q[k] = Quat(q[0], q[1], q[2], q[3]);
    }
    if (have_state) {
      x_prev.swap(x);
      prev_time = sim_time;
      prev_version = version;
      have_prev = true;
    }
    mol::atom_positions_from_body_poses(scene.torsion, body_r, body_q, x);
    version = s.version;
    sim_time = s.sim_time;
    if (have_prev && version > prev_version && sim_time > prev_time)
      dt = (sim_time - prev_time) / static_cast<double>(version - prev_version);
    have_state = true;
    if (fd < 0 || phase != Phase::kStreaming || paused) return;
    if (last_frame_version != std::numeric_limits<int64_t>::min() && version - last_frame_version < rate &&
        version >= last_frame_version)
      return;
    if (pending()) {   // the receiver has not read the last frame: skip, never queue
      counters.frames_skipped.fetch_add(1);
      return;
    }
    send_frame();
  }

  void send_frame() {
    fx.resize(3 * static_cast<size_t>(natoms));
    for (int a = 0; a < natoms; ++a)
      for (int i = 0; i < 3; ++i) fx[3 * a + i] = static_cast<float>(imd::kNmToAngstrom * x[a][i]);
    if (opt.version >= 3) imd::append_time(out, dt, sim_time, version);
    imd::append_vectors(out, imd::Type::kFcoords, fx.data(), natoms);
    if (opt.version >= 3 && opt.velocities) {
      fv.assign(3 * static_cast<size_t>(natoms), 0.0f);
      const double h = sim_time - prev_time;
      if (have_prev && h > 0)
        for (int a = 0; a < natoms; ++a)
          for (int i = 0; i < 3; ++i)
            fv[3 * a + i] = static_cast<float>(imd::kNmToAngstrom * (x[a][i] - x_prev[a][i]) / h);
      imd::append_vectors(out, imd::Type::kVelocities, fv.data(), natoms);
    }
    if (opt.version >= 3 && opt.forces) {
      scene.force_field->compute_atoms(x, atom_f);
      ff.resize(3 * static_cast<size_t>(natoms));
      for (int a = 0; a < natoms; ++a)   // kJ/(mol nm) -> kJ/(mol Å)
        for (int i = 0; i < 3; ++i) ff[3 * a + i] = static_cast<float>(atom_f[a][i] / imd::kNmToAngstrom);
      imd::append_vectors(out, imd::Type::kForces, ff.data(), natoms);
    }
    send_progress_at = Clock::now();
    last_frame_version = version;
    counters.frames_sent.fetch_add(1);
    flush();
  }

  void check_timeouts() {
    if (fd < 0) return;
    if (phase == Phase::kAwaitGo && seconds_since(accepted_at) > opt.go_timeout_s)
      return drop(fmt::format("no IMD_GO within {:g} s of the handshake", opt.go_timeout_s), true);
    if (pending() && seconds_since(send_progress_at) > opt.send_timeout_s)
      drop(fmt::format("read nothing for {:g} s", opt.send_timeout_s), true);
  }
};

ImdServer::ImdServer(bus::Bus& bus, const ImdServerOptions& options)
    : impl_(std::make_unique<Impl>(bus, options, counters_, connected_)) {
  Impl& s = *impl_;
  const ImdServerOptions& o = s.opt;
  if (o.version != 2 && o.version != 3) throw std::invalid_argument("IMD: version must be 2 or 3, not " + std::to_string(o.version));
  if (o.port < 0 || o.port > 65535) throw std::invalid_argument("IMD: port must be in [0, 65535]");
  if (o.user_id < 0) throw std::invalid_argument("IMD: user id must be >= 0");
  if (!(o.max_force > 0)) throw std::invalid_argument("IMD: max force must be > 0 kJ/(mol nm)");
  if (!(o.force_rate_hz > 0 && o.force_rate_hz <= 10000)) throw std::invalid_argument("IMD: force rate must be in (0, 10000] Hz");
  if (o.default_rate < 1) throw std::invalid_argument("IMD: default rate must be >= 1 step");
  if (o.scene.empty() || is_procedural(o.scene))
    throw std::invalid_argument("IMD serves molecular scenes (atoms); '" + o.scene +
                                "' is not one (use a molecule name such as ala20, or a PDB path)");
  mol::SceneOptions so;
  so.with_force_field = o.version >= 3 && o.forces;   // else only the torsion model, to place atoms
  s.scene = mol::load_molecular_scene(o.scene, so);
  s.natoms = s.scene.natoms();
  s.force_to_scene = o.version >= 3 ? imd::kKjPerMolAngstromToKjPerMolNm : imd::kKcalPerMolAngstromToKjPerMolNm;
  s.force_channel = bus::channel::user_force(o.user_id, o.channel_suffix);
  s.rate = o.default_rate;
  s.listen_on();
  sockaddr_in a{};
  socklen_t len = sizeof a;
  ::getsockname(s.listen_fd, reinterpret_cast<sockaddr*>(&a), &len);
  port_ = ntohs(a.sin_port);
  bus.subscribe_latest<lcmt_scene_state>(bus::channel::scene_state(o.channel_suffix), s.box);
  spdlog::info("IMD: serving '{}' ({} atoms) on {}:{} as IMD v{}; pulls go to {} (forces in {})", s.scene.name,
               s.natoms, o.bind, port_, o.version, s.force_channel,
               o.version >= 3 ? "kJ/(mol A)" : "kcal/(mol A), VMD's unit");
}

ImdServer::~ImdServer() {
  if (impl_->fd >= 0) ::close(impl_->fd);
  if (impl_->listen_fd >= 0) ::close(impl_->listen_fd);
}

int ImdServer::natoms() const { return impl_->natoms; }

int ImdServer::run(const std::atomic<bool>& stop) {
  Impl& s = *impl_;
  while (!stop.load(std::memory_order_relaxed)) {
    pollfd fds[2] = {{s.listen_fd, POLLIN, 0}, {s.fd, static_cast<short>(POLLIN | (s.pending() ? POLLOUT : 0)), 0}};
    const nfds_t n = s.fd >= 0 ? 2 : 1;
    ::poll(fds, n, 5);
    if (fds[0].revents & POLLIN) s.accept_one();
    else if (n == 2 && s.fd >= 0 && (fds[1].revents & (POLLIN | POLLHUP | POLLERR))) s.read_client();
    if (s.fd >= 0) s.flush();
    s.check_timeouts();
    if (s.box.update()) s.on_scene_state(s.box.front());
    s.publish_force_if_due();
  }
  // Leaving: end the pull, close the receiver.
  s.drop("server stopping", false);
  for (int i = 0; i < 5 && s.releases_pending > 0; ++i) {
    s.next_force = Clock::now();
    s.publish_force_if_due();
  }
  return 0;
}

}  // namespace haptree
