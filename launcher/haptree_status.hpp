#pragma once
// haptree_run's status, once per second in both modes: a text line for people, or one JSON object per
// line (--json) for scripts. A value that does not exist yet (no step done, no rate window closed, no
// body grabbed) is shown as "—" or said in words, and is null in JSON: never a placeholder number.
#include <fmt/format.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

namespace haptree::launcher {

constexpr double kNoValue = std::numeric_limits<double>::quiet_NaN();

struct SimStatus {
  bool started = false;              // the server has reported (processes) or stepped (embedded)
  double step_ms = kNoValue;         // duration of a step (last, or the median of the last window)
  double max_step_ms = kNoValue;     // longest step of the last window
  int active_dofs = -1;
  double steps_per_s = kNoValue;
  int64_t steps = -1;                // steps done; -1: not known
  double real_time_factor = kNoValue;   // simulated time per wall second (s/s; ps/s for molecules)
  double rate_fraction = kNoValue;      // share of the requested step rate kept
};

struct UserStatus {
  int user = 0;
  bool started = false;              // the coupler has reported
  double rate_hz = kNoValue;         // coupling loop rate over the last closed window
  double force_n = kNoValue;         // |f| at the device, N
  int grab_body = -1;                // body held; 0: none; -1: not known
  double snapshot_age_ms = kNoValue; // age of the newest snapshot while grabbing
  int64_t feedbacks = -1;            // FEEDBACK messages the launcher saw; -1: not counted
};

struct ImdStatus {
  bool on = false;
  int port = 0;
  bool receiver = false;
  int64_t frames = 0;
};

struct StatusSample {
  double t_s = 0;
  SimStatus sim;
  std::vector<UserStatus> users;
  ImdStatus imd;
};

namespace status_detail {
inline bool has(double v) { return std::isfinite(v); }
inline std::string num(double v, const char* spec) { return has(v) ? fmt::format(spec, v) : std::string("—"); }
inline std::string json_num(double v) { return has(v) ? fmt::format("{:.6g}", v) : std::string("null"); }
inline std::string json_int(int64_t v) { return v >= 0 ? std::to_string(v) : std::string("null"); }
}  // namespace status_detail

inline std::string status_text(const StatusSample& s) {
  using namespace status_detail;
  std::string line = fmt::format("t {:5.1f} s | ", s.t_s);
  if (!s.sim.started) {
    line += "sim starting";
  } else {
    line += "sim step " + num(s.sim.step_ms, "{:.3f}") + " ms";
    if (has(s.sim.max_step_ms)) line += " (max " + num(s.sim.max_step_ms, "{:.1f}") + ")";
    line += ", " + (s.sim.active_dofs >= 0 ? std::to_string(s.sim.active_dofs) : std::string("—")) + " active DOF";
    if (has(s.sim.steps_per_s)) line += ", " + num(s.sim.steps_per_s, "{:.0f}") + " steps/s";
    if (s.sim.steps >= 0) line += fmt::format(", {} steps", s.sim.steps);
    if (has(s.sim.real_time_factor)) line += ", real-time factor " + num(s.sim.real_time_factor, "{:.3g}");
    if (has(s.sim.rate_fraction) && s.sim.rate_fraction > 0 && s.sim.rate_fraction < 0.9)
      line += fmt::format(" (BEHIND: {:.0f} % of the requested rate)", 100 * s.sim.rate_fraction);
  }
  for (const auto& u : s.users) {
    line += fmt::format(" | user {}: ", u.user);
    if (!u.started) {
      line += "coupler starting";
    } else {
      line += (has(u.rate_hz) && u.rate_hz > 0 ? fmt::format("{:.0f} Hz", u.rate_hz) : std::string("— Hz"));
      line += ", |f| " + num(u.force_n, "{:.3f}") + " N, ";
      line += u.grab_body == 0 ? std::string("no grab")
              : u.grab_body < 0 ? std::string("grab —")
              : !has(u.snapshot_age_ms) || u.snapshot_age_ms < 0
                  ? std::string("no snapshot yet")
                  : fmt::format("body {}, snapshot age {:.1f} ms", u.grab_body, u.snapshot_age_ms);
    }
    if (u.feedbacks >= 0) line += fmt::format(", {} feedbacks", u.feedbacks);
  }
  if (s.imd.on)
    line += fmt::format(" | imd :{} {}, {} frames", s.imd.port, s.imd.receiver ? "receiver" : "no receiver",
                        s.imd.frames);
  return line;
}

// One JSON object (one line): {"t_s":..,"sim":{..},"users":[{..}],"imd":{..}}; null where there is no value.
inline std::string status_json(const StatusSample& s) {
  using namespace status_detail;
  std::string j = "{\"t_s\":" + json_num(s.t_s) + ",\"sim\":{\"started\":" + (s.sim.started ? "true" : "false") +
                  ",\"step_ms\":" + json_num(s.sim.started ? s.sim.step_ms : kNoValue) +
                  ",\"max_step_ms\":" + json_num(s.sim.max_step_ms) +
                  ",\"active_dofs\":" + json_int(s.sim.active_dofs) +
                  ",\"steps_per_s\":" + json_num(s.sim.steps_per_s) + ",\"steps\":" + json_int(s.sim.steps) +
                  ",\"real_time_factor\":" + json_num(s.sim.real_time_factor) +
                  ",\"rate_fraction\":" + json_num(s.sim.rate_fraction) + "},\"users\":[";
  for (size_t i = 0; i < s.users.size(); ++i) {
    const auto& u = s.users[i];
    const bool grabbing = u.started && u.grab_body > 0;
    j += (i ? "," : "") + fmt::format("{{\"user\":{},\"started\":{}", u.user, u.started ? "true" : "false") +
         ",\"rate_hz\":" + json_num(u.started && u.rate_hz > 0 ? u.rate_hz : kNoValue) +
         ",\"force_n\":" + json_num(u.started ? u.force_n : kNoValue) +
         ",\"grab_body\":" + (grabbing ? std::to_string(u.grab_body) : std::string("null")) +
         ",\"snapshot_age_ms\":" + json_num(grabbing && u.snapshot_age_ms >= 0 ? u.snapshot_age_ms : kNoValue) +
         ",\"feedbacks\":" + json_int(u.feedbacks) + "}";
  }
  j += "]";
  if (s.imd.on)
    j += fmt::format(",\"imd\":{{\"port\":{},\"receiver\":{},\"frames\":{}}}", s.imd.port,
                     s.imd.receiver ? "true" : "false", s.imd.frames);
  return j + "}";
}

}  // namespace haptree::launcher
