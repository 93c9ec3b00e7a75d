// haptree_log_dump: decodes an LCM log with the C++ types lcm-gen made from lcmtypes/*.lcm and prints
// per-channel counts and plain sums (in file order) as JSON, for the Python log reader's test to
// compare against. [--start-s S] [--end-s E]: the window, in seconds after the file's first event.
#include <lcm/lcm-cpp.hpp>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <string>

#include "haptree/lcmt_coupling_snapshot.hpp"
#include "haptree/lcmt_device_state.hpp"
#include "haptree/lcmt_feedback.hpp"
#include "haptree/lcmt_process_stats.hpp"
#include "haptree/lcmt_scene_state.hpp"
#include "haptree/lcmt_user_force.hpp"

namespace {
struct Sums {
  long long n = 0;
  double a[6] = {0, 0, 0, 0, 0, 0};
  long long i0 = 0;   // sum of an integer field (versions, seq, active DOF)
};
template <class T>
bool decode(const lcm::LogEvent* ev, T& m) {
  return m.decode(ev->data, 0, ev->datalen) == ev->datalen;
}
bool starts(const std::string& s, const char* p) { return s.rfind(p, 0) == 0; }
}  // namespace

int main(int argc, char** argv) {
  std::string path;
  double start_s = -1e300, end_s = 1e300;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--start-s") && i + 1 < argc) start_s = std::atof(argv[++i]);
    else if (!std::strcmp(argv[i], "--end-s") && i + 1 < argc) end_s = std::atof(argv[++i]);
    else path = argv[i];
  }
  lcm::LogFile log(path, "r");
  if (path.empty() || !log.good()) {
    std::fprintf(stderr, "usage: haptree_log_dump LOG [--start-s S] [--end-s E] (cannot open '%s')\n", path.c_str());
    return 2;
  }
  std::map<std::string, Sums> fb, ds, sn, uf, st, sc;
  std::map<std::string, long long> count;
  long long events = 0, bad = 0;
  int64_t first = -1;
  for (const lcm::LogEvent* ev = log.readNextEvent(); ev; ev = log.readNextEvent()) {
    if (first < 0) first = ev->timestamp;
    const double t = (ev->timestamp - first) * 1e-6;
    if (t < start_s || t >= end_s) continue;
    ++events;
    ++count[ev->channel];
    const std::string& c = ev->channel;
    if (starts(c, "HAPTREE_FEEDBACK_")) {
      haptree::lcmt_feedback m;
      if (!decode(ev, m)) { ++bad; continue; }
      Sums& s = fb[c];
      ++s.n;
      for (int k = 0; k < 3; ++k) s.a[k] += m.force_n[k];
      s.i0 += m.snapshot_version;
    } else if (starts(c, "HAPTREE_DEVICE_STATE_")) {
      haptree::lcmt_device_state m;
      if (!decode(ev, m)) { ++bad; continue; }
      Sums& s = ds[c];
      ++s.n;
      for (int k = 0; k < 3; ++k) s.a[k] += m.position_m[k];
      s.i0 += m.seq;
    } else if (starts(c, "HAPTREE_COEFFS_")) {
      haptree::lcmt_coupling_snapshot m;
      if (!decode(ev, m)) { ++bad; continue; }
      Sums& s = sn[c];
      ++s.n;
      s.a[0] += m.sim_time;
      s.i0 += m.version;
    } else if (starts(c, "HAPTREE_USER_FORCE_")) {
      haptree::lcmt_user_force m;
      if (!decode(ev, m)) { ++bad; continue; }
      Sums& s = uf[c];
      ++s.n;
      for (int k = 0; k < 6; ++k) s.a[k] += m.force[k];
      s.i0 += m.snapshot_version;
    } else if (starts(c, "HAPTREE_STATS_")) {
      haptree::lcmt_process_stats m;
      if (!decode(ev, m)) { ++bad; continue; }
      Sums& s = st[c];
      ++s.n;
      s.a[0] += m.loop_rate_hz;
      s.i0 += m.messages_out;
    } else if (starts(c, "HAPTREE_SCENE_STATE")) {
      haptree::lcmt_scene_state m;
      if (!decode(ev, m)) { ++bad; continue; }
      Sums& s = sc[c];
      ++s.n;
      s.a[0] += m.neglected_metric;
      s.i0 += m.active_dofs;
    }
  }
  auto section = [](const char* name, const std::map<std::string, Sums>& m, int na, bool last) {
    std::printf("  \"%s\": {", name);
    bool firstc = true;
    for (const auto& [c, s] : m) {
      std::printf("%s\n    \"%s\": {\"n\": %lld, \"isum\": %lld, \"sum\": [", firstc ? "" : ",", c.c_str(), s.n, s.i0);
      for (int k = 0; k < na; ++k) std::printf("%s%.17g", k ? ", " : "", s.a[k]);
      std::printf("]}");
      firstc = false;
    }
    std::printf("}%s\n", last ? "" : ",");
  };
  std::printf("{\n  \"events\": %lld,\n  \"undecodable\": %lld,\n  \"channels\": {", events, bad);
  bool firstc = true;
  for (const auto& [c, n] : count) {
    std::printf("%s\"%s\": %lld", firstc ? "" : ", ", c.c_str(), n);
    firstc = false;
  }
  std::printf("},\n");
  section("feedback", fb, 3, false);
  section("device_state", ds, 3, false);
  section("snapshots", sn, 1, false);
  section("user_force", uf, 6, false);
  section("stats", st, 1, false);
  section("scene_state", sc, 1, true);
  std::printf("}\n");
  return 0;
}
