// replay_coupling: re-runs the coupler's computation on the snapshots and device poses of an LCM log and
// compares with the logged FEEDBACK forces. Each FEEDBACK carries the snapshot version and the device seq
// it was computed from; forces rendered while the watchdog ramp was active (time-dependent gain) or with a
// non-finite input are skipped and counted. The coupler options are read from the log (the coupler publishes
// them as lcmt_coupler_settings); options given on the command line override them.
// --start-s / --end-s replay a window (seconds after the log's first event): the reader seeks with
// lcm_eventlog_seek_to_timestamp (approximate, by file offset) and then keeps exactly the events in
// [start, end). Feedback near the window start may need a snapshot logged before it: counted as missing.
#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/spdlog.h>

#include <cmath>
#include <cstdint>
#include <string>
#include <cstdio>
#include <deque>
#include <map>
#include <unordered_set>
#include <memory>
#include <vector>

#include "coupler/coupler.hpp"
#include "haptree/bus/auth.hpp"
#include "haptree/bus/channels.hpp"
#include "haptree/bus/snapshot.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/fp_env.hpp"
#include "haptree/safety.hpp"

int main(int argc, char** argv) {
  const haptree::ScopedFlushDenormals ftz;   // the coupler's loop computes with FTZ/DAZ: the same arithmetic
  CLI::App app{"replay_coupling: reproduce logged feedback forces from logged snapshots and poses"};
  std::string log;
  haptree::CouplerOptions o;
  std::vector<double> offset{0, 0, 0};
  double tolerance = 1e-12;
  std::string suffix;
  double start_s = 0, end_s = -1;
  app.add_option("log", log, "LCM log file (lcm-logger or lcm::LogFile)")->required();
  app.add_option("--user", o.user, "user id")->capture_default_str();
  app.add_option("--device", o.device, "device id (default: the one in the logged coupler settings)");
  // The session's coupler settings come from the log (HAPTREE_COUPLER_SETTINGS_<user>); these override.
  std::vector<CLI::Option*> overrides = {
      app.add_option("--stiffness", o.stiffness, "k_s of the session, scene force per scene length"),
      app.add_option("--damping", o.damping, "b_s of the session, scene force per scene velocity"),
      app.add_option("--position-scale", o.position_scale, "scene length units per device metre"),
      app.add_option("--force-scale", o.force_scale, "N per scene force unit"),
      app.add_option("--offset", offset, "X,Y,Z scene position of the device origin, scene length units")
          ->delimiter(',')->expected(3),
      app.add_option("--max-force-n", o.max_force_n, "force clamp of the session, N")};
  app.add_option("--tolerance", tolerance, "max allowed deviation, N")->capture_default_str();
  app.add_option("--channel-suffix", suffix, "channel suffix of the session");
  app.add_option("--start-s", start_s, "replay from this time, seconds after the log's first event")
      ->check(CLI::NonNegativeNumber)->capture_default_str();
  app.add_option("--end-s", end_s, "replay up to (excluding) this time, seconds after the first event; -1 = to the end")
      ->capture_default_str();
  app.footer("The coupler's settings (gains, mapping, clamp) are read from the log's HAPTREE_COUPLER_SETTINGS_<user> "
             "messages (the newest one before each FEEDBACK); an option given here overrides the logged value. "
             "Logs without settings messages need every option of the session.");
  int show = 0;
  app.add_option("--show", show, "print the first N deviating and the first N missing FEEDBACK messages with "
                 "what they name (diagnosis)")->capture_default_str();
  bool recompute_copies = false;
  app.add_flag("--recompute-copies", recompute_copies, "recompute copies of an earlier FEEDBACK too (diagnosis: their "
               "inputs may no longer be kept, counted as missing)");
  std::string key_file;
  app.add_option("--session-key-file", key_file, "key of a keyed session: events are verified and their "
                 "authentication trailers stripped (docs/sessions.md)")->envname("HAPTREE_SESSION_KEY_FILE");
  CLI11_PARSE(app, argc, argv);
  std::unique_ptr<haptree::bus::Authenticator> auth;
  if (!key_file.empty()) auth = std::make_unique<haptree::bus::Authenticator>(haptree::bus::load_session_key(key_file));
  int64_t unauthentic = 0;
  o.offset = haptree::Vec3(offset[0], offset[1], offset[2]);
  if (end_s != -1 && !(end_s > start_s)) {
    std::fprintf(stderr, "replay_coupling: --end-s %g must be greater than --start-s %g (or -1 for the end)\n", end_s,
                 start_s);
    return 2;
  }
  const bool device_given = app.count("--device") > 0;
  namespace ch = haptree::bus::channel;
  const std::string c_settings = ch::coupler_settings(o.user, suffix), c_snap = ch::coeffs(o.user, suffix);
  int64_t in_window = 0, undecodable = 0;
  // Calls fn(channel, data, len) for each authentic event of the window, in log order. false: no log.
  bool empty_log = false;
  int64_t log_t0 = 0;
  auto for_each_event = [&](auto&& fn) {
    lcm::LogFile file(log, "r");
    if (!file.good()) return false;
    const lcm::LogEvent* ev = file.readNextEvent();
    if (ev == nullptr) {
      empty_log = true;
      return true;
    }
    const int64_t t0 = ev->timestamp;
    log_t0 = t0;
    const int64_t t_begin = t0 + static_cast<int64_t>(std::llround(start_s * 1e6));
    const int64_t t_end = end_s < 0 ? INT64_MAX : t0 + static_cast<int64_t>(std::llround(end_s * 1e6));
    if (start_s > 0) {
      file.seekToTimestamp(t_begin);   // lands near t_begin (before or after): the filter below is exact
      ev = file.readNextEvent();
    }
    in_window = unauthentic = 0;
    for (; ev != nullptr; ev = file.readNextEvent()) {
      if (ev->timestamp < t_begin) continue;
      if (ev->timestamp >= t_end) break;
      ++in_window;
      size_t len = static_cast<size_t>(ev->datalen);   // keyed log: the payload before the trailer
      if (auth && auth->verify(ev->channel, ev->data, len, &len) != haptree::bus::AuthVerdict::kOk) {
        ++unauthentic;
        continue;
      }
      fn(ev->channel, ev->data, len, ev->timestamp);
    }
    return true;
  };
  // Pass 1: the coupler's settings (they name the device, and a logger that started late has FEEDBACK
  // before the first of them).
  std::vector<haptree::lcmt_coupler_settings> settings;
  const bool opened = for_each_event([&](const std::string& channel, const void* data, size_t len, int64_t) {
    if (channel != c_settings) return;
    haptree::lcmt_coupler_settings m;
    if (haptree::bus::decode_checked(data, len, m) == haptree::bus::DecodeResult::kOk) settings.push_back(m);
  });
  if (!opened) {
    spdlog::critical("cannot open log '{}'", log);
    return 2;
  }
  if (empty_log) {
    std::printf("replay_coupling: '%s' holds no events\n", log.c_str());
    return 1;
  }
  if (!settings.empty()) {
    const auto& first = settings.front();
    if (!device_given) o.device = first.device_id;
    std::printf("replay_coupling: coupler settings from the log (%zu messages): k_s %.17g, b_s %.17g, position scale "
                "%.17g, force scale %.17g, offset %.17g %.17g %.17g, clamp %.17g N, device %d\n",
                settings.size(), first.stiffness, first.damping, first.position_scale, first.force_scale,
                first.offset[0], first.offset[1], first.offset[2], first.max_force_n, o.device);
  } else {
    std::printf("replay_coupling: no %s messages in the log: using the options given\n", c_settings.c_str());
  }
  const std::string c_state = ch::device_state(o.device, suffix), c_fb = ch::feedback(o.device, suffix);
  // Options for a FEEDBACK: those its coupler instance published (a coupler stamps its settings with the
  // instance id of its FEEDBACK), else those of settings[i], the newest logged before it (a logger that
  // started late: the first settings message also stands for the FEEDBACK before it).
  const haptree::Vec3 offset_opt(offset[0], offset[1], offset[2]);
  auto options_for = [&](int i, const haptree::lcmt_coupler_settings* own) {
    haptree::CouplerOptions r = o;
    r.offset = offset_opt;
    if (settings.empty()) return r;
    haptree::from_settings(own ? *own : settings[std::min(static_cast<size_t>(std::max(0, i)), settings.size() - 1)], r);
    r.user = o.user;
    r.device = o.device;
    if (overrides[0]->count()) r.stiffness = o.stiffness;
    if (overrides[1]->count()) r.damping = o.damping;
    if (overrides[2]->count()) r.position_scale = o.position_scale;
    if (overrides[3]->count()) r.force_scale = o.force_scale;
    if (overrides[4]->count()) r.offset = offset_opt;
    if (overrides[5]->count()) r.max_force_n = o.max_force_n;
    return r;
  };
  // Pass 2, in log order: each FEEDBACK is recomputed from the snapshot and device state it names, logged
  // before it. They are looked up by (instance_id, version) and (instance_id, seq): a restarted server
  // reuses versions and a restarted device seqs, and a replayed message of an earlier instance must not
  // stand for the live one's (both found by tools/faults/chaos_soak). FEEDBACK of schema 3 names both instances;
  // instance 0 stands for any (the newest message with that number). Only the last kKeep of each are kept
  // (a FEEDBACK answers inputs of the last stale_after_s, or it is a skipped watchdog ramp), so memory stays
  // bounded on long logs.
  constexpr size_t kKeep = 4096;
  using Key = std::pair<int64_t, int64_t>;
  std::map<Key, haptree::CouplingSnapshot> snaps;
  std::map<Key, haptree::lcmt_device_state> states;
  std::deque<std::pair<Key, int64_t>> snap_order, state_order;
  std::map<Key, int64_t> snap_serial, state_serial;
  int64_t serial = 0;
  auto remember = [&serial](auto& map, std::deque<std::pair<Key, int64_t>>& order, std::map<Key, int64_t>& serials,
                            const Key& k, const auto& value) {
    map[k] = value;
    serials[k] = ++serial;
    order.emplace_back(k, serial);
    while (order.size() > 2 * kKeep) {   // two keys per message
      const auto [old, sn] = order.front();
      order.pop_front();
      auto it = serials.find(old);
      if (it != serials.end() && it->second == sn) {   // not overwritten since
        serials.erase(it);
        map.erase(old);
      }
    }
  };
  haptree::CouplingWorkspace ws(o.max_nodes, o.max_slots);
  int64_t feedback_count = 0, compared = 0, skipped_watchdog = 0, missing = 0, no_snapshot = 0, copies = 0, deviating = 0;
  constexpr size_t kKeepFeedback = 1 << 18;   // <= ~40 MB of FEEDBACK bodies; a copy older than that is recomputed
  std::unordered_set<std::string> seen_feedback;
  std::deque<std::string> feedback_order;
  int settings_seen = 0;
  std::map<int64_t, haptree::lcmt_coupler_settings> settings_of;   // newest settings of each coupler instance
  double max_dev = 0;
  for_each_event([&](const std::string& channel, const void* data, size_t len, int64_t t_log) {
    if (channel == c_settings) {
      // Only the messages pass 1 kept count: a garbage or cut one on this channel (chaos_soak) used to shift
      // every later FEEDBACK onto a later settings message, and past the last one (out of range).
      haptree::lcmt_coupler_settings m;
      if (haptree::bus::decode_checked(data, len, m) != haptree::bus::DecodeResult::kOk) return;
      ++settings_seen;
      // A stale copy (another instance id, chaos_soak) adds an entry no FEEDBACK names; bounded.
      if (settings_of.size() > 4096) settings_of.clear();
      settings_of[m.instance_id] = m;
    } else if (channel == c_snap) {
      haptree::lcmt_coupling_snapshot m;
      if (haptree::bus::decode_checked(data, len, m) != haptree::bus::DecodeResult::kOk) {
        ++undecodable;
        return;
      }
      haptree::CouplingSnapshot s;
      haptree::bus::from_lcmt(m, s);
      haptree::flush_subnormals(s.values.data(), s.values.size());   // as the coupler does on arrival
      remember(snaps, snap_order, snap_serial, Key{m.instance_id, s.version}, s);
      remember(snaps, snap_order, snap_serial, Key{0, s.version}, s);
    } else if (channel == c_state) {
      haptree::lcmt_device_state m;
      if (haptree::bus::decode_checked(data, len, m) != haptree::bus::DecodeResult::kOk) {
        ++undecodable;
        return;
      }
      remember(states, state_order, state_serial, Key{m.instance_id, m.seq}, m);
      remember(states, state_order, state_serial, Key{0, m.seq}, m);
    } else if (channel == c_fb) {
      haptree::lcmt_feedback f;
      if (haptree::bus::decode_checked(data, len, f) != haptree::bus::DecodeResult::kOk) {
        ++undecodable;
        return;
      }
      ++feedback_count;
      // A copy: the bytes after the header (type hash, schema, utime, instance id: 28 bytes) equal those of an
      // earlier FEEDBACK. A replayed or stale message (chaos_soak) names the same inputs and carries the same
      // force as the original, so it has the original's verdict; it is not recomputed (its inputs may have
      // been logged long before, beyond what is kept).
      constexpr size_t kHeader = 28;
      std::string body(static_cast<const char*>(data) + kHeader, len - kHeader);
      const bool copy = seen_feedback.count(body) > 0;
      if (copy) {
        ++copies;
        if (!recompute_copies) return;
      } else {
        seen_feedback.insert(body);
        feedback_order.push_back(std::move(body));
        if (feedback_order.size() > kKeepFeedback) {
          seen_feedback.erase(feedback_order.front());
          feedback_order.pop_front();
        }
      }
      auto describe = [&](const char* what, const std::string& extra) {
        std::printf("  %s: t %.3f s (stamped %.3f s before it was logged), coupler %016llx seq %lld, snapshot "
                    "%016llx v%lld, device %016llx seq %lld, flags %d, logged [%.6g %.6g %.6g] N%s\n",
                    what, 1e-6 * static_cast<double>(t_log - log_t0), 1e-6 * static_cast<double>(t_log - f.utime),
                    static_cast<unsigned long long>(f.instance_id), static_cast<long long>(f.seq),
                    static_cast<unsigned long long>(f.snapshot_instance_id), static_cast<long long>(f.snapshot_version),
                    static_cast<unsigned long long>(f.echo_device_instance_id), static_cast<long long>(f.echo_device_seq),
                    f.flags, f.force_n[0], f.force_n[1], f.force_n[2], (extra + (copy ? " (a copy)" : "")).c_str());
      };
      if (f.snapshot_version < 0) {
        ++no_snapshot;
        return;
      }
      if (f.flags & (haptree::kSafetyWatchdog | haptree::kSafetyNonFinite)) {
        ++skipped_watchdog;
        return;
      }
      const auto own = settings_of.find(f.instance_id);
      const haptree::CouplerOptions so = options_for(settings_seen - 1, own == settings_of.end() ? nullptr : &own->second);
      auto s = snaps.find({f.snapshot_instance_id, f.snapshot_version});
      auto p = states.find({f.echo_device_instance_id, f.echo_device_seq});
      if (s == snaps.end() || p == states.end()) {
        if (missing++ < show)
          describe("missing", std::string(s == snaps.end() ? " [no snapshot" : " [") +
                                  (s == snaps.end() && p == states.end() ? ", " : "") +
                                  (p == states.end() ? "no device state]" : "]") +
                                  (snaps.count({0, f.snapshot_version}) ? " (that version of another instance: kept)" : "") +
                                  (states.count({0, f.echo_device_seq}) ? " (that seq of another instance: kept)" : ""));
        return;
      }
      haptree::CouplingInputs in;
      in.position_m = haptree::Vec3(p->second.position_m[0], p->second.position_m[1], p->second.position_m[2]);
      in.velocity_mps = haptree::Vec3(p->second.linear_velocity_mps[0], p->second.linear_velocity_mps[1],
                                      p->second.linear_velocity_mps[2]);
      if (!ws.fits(s->second)) ws.reserve_for(s->second);
      haptree::Vec6 f_u, f_feed;
      haptree::Vec3 force_n;
      if (haptree::coupler_feedback(so, s->second, in, ws, f_u, f_feed, force_n) != haptree::CouplingStatus::kOk)
        force_n.setZero();
      force_n = haptree::clamp_norm(haptree::finite_or_zero(force_n), so.max_force_n);
      const haptree::Vec3 logged(f.force_n[0], f.force_n[1], f.force_n[2]);
      const double dev = (force_n - logged).cwiseAbs().maxCoeff();
      if (dev > tolerance && deviating++ < show)
        describe("deviation", fmt::format(", replayed [{:.6g} {:.6g} {:.6g}] N (device state stamped {:.3f} s before, "
                                          "snapshot at sim time {:.6g}; settings: {}, message {} of {} decoded, k_s {:g} b_s {:g} clamp {:g})",
                                          force_n[0], force_n[1], force_n[2],
                                          1e-6 * static_cast<double>(f.utime - p->second.utime), s->second.sim_time,
                                          own == settings_of.end() ? "the newest" : "its coupler's", settings_seen,
                                          settings.size(), so.stiffness, so.damping, so.max_force_n));
      max_dev = std::max(max_dev, dev);
      ++compared;
    }
  });
  if (start_s > 0 || end_s >= 0)
    std::printf("replay_coupling: window [%g, %s) s: %lld events\n", start_s,
                end_s < 0 ? "end" : fmt::format("{:g}", end_s).c_str(), static_cast<long long>(in_window));
  std::printf("replay_coupling: %lld feedback messages, %lld compared, max deviation %.3e N, %lld deviating "
              "(skipped: %lld watchdog ramp, %lld without snapshot, %lld missing snapshot/pose, %lld copies of an "
              "earlier FEEDBACK; %lld undecodable)\n",
              static_cast<long long>(feedback_count), static_cast<long long>(compared), max_dev,
              static_cast<long long>(deviating), static_cast<long long>(skipped_watchdog),
              static_cast<long long>(no_snapshot), static_cast<long long>(missing), static_cast<long long>(copies),
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
