// replay_coupling: re-runs the coupler's computation on the snapshots and device poses of an LCM log and
// compares with the logged FEEDBACK forces. Each FEEDBACK carries the snapshot version and the device seq
// it was computed from; forces rendered while the watchdog ramp was active (time-dependent gain) or with a
// non-finite input are skipped and counted. The coupler options must match the recorded session.
#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/spdlog.h>

#include <cmath>
#include <cstdio>
#include <map>
#include <memory>
#include <vector>

#include "coupler/coupler.hpp"
#include "haptree/bus/auth.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/safety.hpp"

int main(int argc, char** argv) {
  CLI::App app{"replay_coupling: reproduce logged feedback forces from logged snapshots and poses"};
  std::string log;
  haptree::CouplerOptions o;
  std::vector<double> offset{0, 0, 0};
  double tolerance = 1e-12;
  std::string suffix;
  app.add_option("log", log, "LCM log file (lcm-logger or lcm::LogFile)")->required();
  app.add_option("--user", o.user, "user id")->capture_default_str();
  app.add_option("--device", o.device, "device id")->capture_default_str();
  app.add_option("--stiffness", o.stiffness, "k_s of the session")->capture_default_str();
  app.add_option("--damping", o.damping, "b_s of the session")->capture_default_str();
  app.add_option("--position-scale", o.position_scale, "scene length per device metre")->capture_default_str();
  app.add_option("--force-scale", o.force_scale, "N per scene force unit")->capture_default_str();
  app.add_option("--offset", offset, "scene position of the device origin")->expected(3);
  app.add_option("--max-force-n", o.max_force_n, "force clamp of the session")->capture_default_str();
  app.add_option("--tolerance", tolerance, "max allowed deviation, N")->capture_default_str();
  app.add_option("--channel-suffix", suffix, "channel suffix of the session");
  std::string key_file;
  app.add_option("--session-key-file", key_file, "key of a keyed session: events are verified and their "
                 "authentication trailers stripped (docs/sessions.md)")->envname("HAPTREE_SESSION_KEY_FILE");
  CLI11_PARSE(app, argc, argv);
  std::unique_ptr<haptree::bus::Authenticator> auth;
  if (!key_file.empty()) auth = std::make_unique<haptree::bus::Authenticator>(haptree::bus::load_session_key(key_file));
  int64_t unauthentic = 0;
  o.offset = haptree::Vec3(offset[0], offset[1], offset[2]);
  namespace ch = haptree::bus::channel;
  const std::string c_snap = ch::coeffs(o.user, suffix), c_state = ch::device_state(o.device, suffix),
                    c_fb = ch::feedback(o.device, suffix);
  lcm::LogFile file(log, "r");
  if (!file.good()) {
    spdlog::critical("cannot open log '{}'", log);
    return 2;
  }
  std::map<int64_t, haptree::CouplingSnapshot> snaps;
  std::map<int64_t, haptree::lcmt_device_state> states;
  std::vector<haptree::lcmt_feedback> feedback;
  int64_t undecodable = 0;
  for (const lcm::LogEvent* ev = file.readNextEvent(); ev != nullptr; ev = file.readNextEvent()) {
    size_t len = static_cast<size_t>(ev->datalen);   // keyed log: the payload before the trailer
    if (auth && auth->verify(ev->channel, ev->data, len, &len) != haptree::bus::AuthVerdict::kOk) {
      ++unauthentic;
      continue;
    }
    if (ev->channel == c_snap) {
      haptree::lcmt_coupling_snapshot m;
      if (haptree::bus::decode_checked(ev->data, len, m) != haptree::bus::DecodeResult::kOk) {
        ++undecodable;
        continue;
      }
      haptree::CouplingSnapshot s;
      haptree::bus::from_lcmt(m, s);
      snaps[s.version] = std::move(s);   // a restarted server reuses versions: the newest wins
    } else if (ev->channel == c_state) {
      haptree::lcmt_device_state m;
      if (haptree::bus::decode_checked(ev->data, len, m) == haptree::bus::DecodeResult::kOk)
        states[m.seq] = m;
      else
        ++undecodable;
    } else if (ev->channel == c_fb) {
      haptree::lcmt_feedback m;
      if (haptree::bus::decode_checked(ev->data, len, m) == haptree::bus::DecodeResult::kOk)
        feedback.push_back(m);
      else
        ++undecodable;
    }
  }
  haptree::CouplingWorkspace ws(o.max_nodes, o.max_slots);
  int64_t compared = 0, skipped_watchdog = 0, missing = 0, no_snapshot = 0;
  double max_dev = 0;
  for (const auto& f : feedback) {
    if (f.snapshot_version < 0) {
      ++no_snapshot;
      continue;
    }
    if (f.flags & (haptree::kSafetyWatchdog | haptree::kSafetyNonFinite)) {
      ++skipped_watchdog;
      continue;
    }
    auto s = snaps.find(f.snapshot_version);
    auto p = states.find(f.echo_device_seq);
    if (s == snaps.end() || p == states.end()) {
      ++missing;
      continue;
    }
    haptree::CouplingInputs in;
    in.position_m = haptree::Vec3(p->second.position_m[0], p->second.position_m[1], p->second.position_m[2]);
    in.velocity_mps = haptree::Vec3(p->second.linear_velocity_mps[0], p->second.linear_velocity_mps[1],
                                    p->second.linear_velocity_mps[2]);
    if (!ws.fits(s->second)) ws.reserve_for(s->second);
    haptree::Vec6 f_u, f_feed;
    haptree::Vec3 force_n;
    if (haptree::coupler_feedback(o, s->second, in, ws, f_u, f_feed, force_n) != haptree::CouplingStatus::kOk)
      force_n.setZero();
    force_n = haptree::clamp_norm(haptree::finite_or_zero(force_n), o.max_force_n);
    const haptree::Vec3 logged(f.force_n[0], f.force_n[1], f.force_n[2]);
    max_dev = std::max(max_dev, (force_n - logged).cwiseAbs().maxCoeff());
    ++compared;
  }
  std::printf("replay_coupling: %zu feedback messages, %lld compared, max deviation %.3e N "
              "(skipped: %lld watchdog ramp, %lld without snapshot, %lld missing snapshot/pose; %lld undecodable)\n",
              feedback.size(), static_cast<long long>(compared), max_dev, static_cast<long long>(skipped_watchdog),
              static_cast<long long>(no_snapshot), static_cast<long long>(missing),
              static_cast<long long>(undecodable));
  if (auth)
    std::printf("replay_coupling: session key %s: %lld events rejected (no trailer, other key, bad MAC)\n",
                auth->key().fingerprint.c_str(), static_cast<long long>(unauthentic));
  if (compared == 0) {
    std::printf("nothing to compare: the log needs %s, %s and %s\n", c_snap.c_str(), c_state.c_str(), c_fb.c_str());
    return 1;
  }
  return max_dev <= tolerance ? 0 : 1;
}
