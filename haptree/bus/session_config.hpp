// The session file and the option conventions every process shares (docs/processes.md, "Session file").
//
// One TOML file describes a whole session. Every program takes `--config FILE` (CLI11's config-file
// support) and reads from it:
//   - the keys before the first section, shared by every program (each takes the ones it has);
//   - its own section, [sim_server], [coupler], [device_bridge], [viewer], [imd_bridge] or [haptree_run];
//   - for the programs of one user (coupler --user N, device_bridge --device N), the section [user.N]
//     (haptree_run takes device-kind and device-option from every [user.N]: user N's device; the command
//     line's --device-kind/--device-option override [user.0]'s).
// A key is an option's long name without the dashes (`sim-rate-hz = 1000`; `_` may stand for `-`).
// The command line overrides the file; [user.N] overrides the program's section, which overrides the
// shared keys. A key that no program knows, a key in a program's section that this program does not
// have, or an unknown section is an error naming the file, the line and the key. `--print-config`
// writes the effective settings as a file that reads back to the same settings.
//
// Options renamed for one vocabulary across the programs keep their old names for one release: the old
// name is rewritten to the new one with a one-line deprecation warning on stderr.
//
// Header-only: the processes link CLI11.
//   haptree::bus::ProgramCli cli(app, "coupler", {{"--rate-hz", "--coupler-rate-hz"}});
//   ... add the options ...
//   if (const int rc = cli.parse(argc, argv); rc >= 0) return rc;
#pragma once

#include <CLI/CLI.hpp>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <set>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

namespace haptree::bus {

// The programs that read a session file, and the option names of each (without the dashes). This is the
// file's vocabulary: a shared key must belong to one of them. A program reads its own section against
// its own options; tests/integration/session_test.cpp compares this list with every program's --help.
inline const std::map<std::string, std::set<std::string>>& session_programs() {
  static const std::map<std::string, std::set<std::string>> programs = {
      {"sim_server",
       {"lcm-url", "channel-suffix", "session-key-file", "scene", "n", "urdf", "budget-dofs", "epsilon",
        "reselect-every", "dt", "steps", "sim-rate-hz", "display-rate-hz", "users", "gravity", "max-joint-rate",
        "checkpoint-every", "user-force-stale-s", "user-force-ramp-s", "max-user-force", "trajectory",
        "trajectory-every-steps", "trajectory-every-time", "sched-fifo", "mlockall", "cpu-affinity",
        "timer-slack-ns"}},
      {"coupler",
       {"lcm-url", "channel-suffix", "session-key-file", "shm", "user", "device", "coupler-rate-hz", "sleep",
        "stiffness", "damping", "position-scale", "force-scale", "offset", "grab-body", "grab-radius", "max-force-n",
        "stale-after-s", "user-force-rate-hz", "max-device-position-m", "model-fingerprint", "device-model",
        "clamp-gains", "device-damping-n-s-per-m", "sim-dt-s", "device-limits-wait-s", "sched-fifo", "mlockall",
        "cpu-affinity", "timer-slack-ns", "busy-poll"}},
      {"device_bridge",
       {"lcm-url", "channel-suffix", "session-key-file", "shm", "mirror-rate-hz", "device", "device-kind",
        "device-option", "probe", "device-rate-hz", "max-force-n", "max-force-rate-n-per-s", "feedback-timeout-s",
        "sched-fifo", "mlockall", "cpu-affinity", "timer-slack-ns", "busy-poll"}},
      {"viewer",
       {"lcm-url", "channel-suffix", "session-key-file", "viewer-bind", "viewer-port", "web-dir", "scene", "n",
        "urdf", "mesh-path", "viewer-users", "max-fps", "viewer-token-file", "viewer-watch-token-file", "viewer-no-token",
        "viewer-tls-cert", "viewer-tls-key"}},
      {"imd_bridge",
       {"lcm-url", "channel-suffix", "session-key-file", "scene", "imd-port", "imd-bind", "imd-version",
        "imd-user", "imd-every-steps", "max-user-force", "user-force-rate-hz", "imd-go-timeout-s",
        "imd-send-timeout-s", "no-forces", "no-velocities"}},
      {"haptree_run",
       {"lcm-url", "session-key-file", "scene", "n", "urdf", "budget-dofs", "dt", "gravity", "sim-rate-hz",
        "duration-s", "viewer-port", "viewer-bind", "viewer-token-file", "viewer-watch-token-file", "viewer-no-token",
        "viewer-tls-cert", "viewer-tls-key", "mesh-path", "viewer-users", "users", "coupler-rate-hz", "position-scale",
        "force-scale", "stiffness", "damping", "max-force-n", "stale-after-s", "pull-distance-m", "device-kind",
        "device-option", "processes", "bin-dir", "transport", "mirror-rate-hz", "log-dir", "imd-port", "imd-bind",
        "imd-version", "device-model", "clamp-gains", "device-damping-n-s-per-m", "json"}},
  };
  return programs;
}

// Keys a [user.N] section may hold: what differs between the users of one session.
inline const std::set<std::string>& session_user_keys() {
  static const std::set<std::string> keys = {
      "device-kind", "device-option", "device-model", "device-rate-hz", "stiffness", "damping", "position-scale",
      "force-scale", "offset", "grab-body", "grab-radius", "max-force-n", "max-force-rate-n-per-s", "feedback-timeout-s",
      "max-device-position-m",
      "device-damping-n-s-per-m", "clamp-gains", "shm", "sleep", "busy-poll", "cpu-affinity", "sched-fifo"};
  return keys;
}

// Working defaults of a scene kind, used where the command line and the session file leave a value
// unset. Molecules (nm, ps, kJ/mol) need a finer step than the procedural and URDF scenes (SI), a device
// metre mapped to 1 nm instead of 10 m, and a stiffer spring in their own units.
struct SceneDefaults {
  bool molecule = false;
  double dt = 1e-3;             // scene time units: s, or ps for molecules
  double position_scale = 10;   // scene length units per device metre
  double stiffness = 20;        // scene force per scene length
};
inline SceneDefaults scene_defaults(const std::string& scene, const std::string& urdf) {
  const bool procedural = scene == "chain" || scene == "binary_tree" || scene == "random_tree" || scene == "star" ||
                          scene == "protein_like";
  if (!urdf.empty() || procedural) return {};
  return {true, 0.0005, 1.0, 200.0};
}

// A user's device as a session file's [user.N] gives it to the launcher, which runs every user's
// device_bridge itself.
struct UserDevice {
  std::string kind;
  std::vector<std::string> options;   // key=value
};

namespace detail {

inline std::string trim(std::string s) {
  const auto b = s.find_first_not_of(" \t\r");
  if (b == std::string::npos) return "";
  const auto e = s.find_last_not_of(" \t\r");
  return s.substr(b, e - b + 1);
}

inline std::string dashes(std::string key) {
  for (char& c : key)
    if (c == '_') c = '-';
  return key;
}

// The line (1-based) of every key of a TOML file, by its full dotted name (section.key), as CLI11's
// reader names its items; quotes around a key are dropped as CLI11 does.
inline std::map<std::string, int> key_lines(const std::string& text) {
  std::map<std::string, int> lines;
  std::istringstream in(text);
  std::string line, section;
  int no = 0;
  bool in_array = false;
  while (std::getline(in, line)) {
    ++no;
    line = trim(line);
    if (in_array) {
      if (!line.empty() && line.back() == ']') in_array = false;
      continue;
    }
    if (line.empty() || line[0] == '#' || line[0] == ';') continue;
    if (line.front() == '[' && line.back() == ']') {
      section = trim(line.substr(1, line.size() - 2));
      if (section.size() > 1 && section.front() == '[' && section.back() == ']')
        section = trim(section.substr(1, section.size() - 2));
      lines.emplace("[" + section + "]", no);
      continue;
    }
    const auto eq = line.find('=');
    std::string key = trim(line.substr(0, eq));
    if (key.size() > 1 && (key.front() == '"' || key.front() == '\'') && key.back() == key.front())
      key = key.substr(1, key.size() - 2);
    lines.emplace(section.empty() || section == "default" ? key : section + "." + key, no);
    if (eq != std::string::npos) {
      std::string value = trim(line.substr(eq + 1));
      if (const auto hash = value.find('#'); hash != std::string::npos) value = trim(value.substr(0, hash));
      if (!value.empty() && value.front() == '[' && value.back() != ']') in_array = true;
    }
  }
  return lines;
}

inline std::string join(const std::vector<std::string>& v, const char* sep) {
  std::string s;
  for (const auto& x : v) s += (s.empty() ? "" : sep) + x;
  return s;
}

}  // namespace detail

// CLI11's TOML reader, narrowed to one program: it keeps the shared keys this program has, its own
// section and its user's section (in that order of precedence), and refuses what no program knows, with
// the file's name and line.
class SessionConfig : public CLI::ConfigTOML {
 public:
  // user_option: the option whose value picks the [user.N] section ("user", "device"), "" for none.
  // user_devices: where the launcher's [user.N] devices (N >= 1) go; may be null for other programs.
  SessionConfig(const CLI::App* app, std::string program, std::string user_option,
                std::map<int, UserDevice>* user_devices = nullptr)
      : app_(app), program_(std::move(program)), user_option_(std::move(user_option)), user_devices_(user_devices) {}

  std::vector<CLI::ConfigItem> from_config(std::istream& input) const override {
    const std::string text((std::istreambuf_iterator<char>(input)), std::istreambuf_iterator<char>());
    const std::map<std::string, int> lines = detail::key_lines(text);
    std::istringstream again(text);
    std::vector<CLI::ConfigItem> items = CLI::ConfigTOML::from_config(again);
    const auto& programs = session_programs();
    const std::string file = file_name();
    auto where = [&](const CLI::ConfigItem& item) {
      const auto it = lines.find(item.fullname());
      return file + (it == lines.end() ? std::string() : ":" + std::to_string(it->second));
    };
    const int user = user_id(items);
    std::vector<CLI::ConfigItem> user_items, own_items, shared_items;
    for (CLI::ConfigItem item : items) {
      if (item.name == "++" || item.name == "--") continue;   // CLI11's section markers
      const std::string key = detail::dashes(item.name);
      const std::string& p0 = item.parents.empty() ? std::string() : item.parents[0];
      if (item.parents.empty()) {
        bool known = has(key);
        for (const auto& [name, keys] : programs) known = known || keys.count(key) > 0;
        if (!known)
          throw CLI::ConfigError(where(item) + ": unknown key '" + item.name +
                                 "': no program of a session has the option --" + key);
        if (!has(key)) continue;   // another program's
        item.name = key;
        shared_items.push_back(std::move(item));
      } else if (p0 == "user" && item.parents.size() == 2) {
        if (!session_user_keys().count(key))
          throw CLI::ConfigError(where(item) + ": key '" + item.name + "' does not belong in [user." +
                                 item.parents[1] + "]; a user section holds " +
                                 detail::join({session_user_keys().begin(), session_user_keys().end()}, ", "));
        char* end = nullptr;
        const long id = std::strtol(item.parents[1].c_str(), &end, 10);
        if (end == item.parents[1].c_str() || *end != '\0' || id < 0)
          throw CLI::ConfigError(where(item) + ": [user." + item.parents[1] + "]: a user section is [user.N], N >= 0");
        if (program_ == "haptree_run") {
          if (key != "device-kind" && key != "device-option") continue;
          if (id != 0) {   // the command line names user 0's device only: the others' come from here
            if (user_devices_) {
              UserDevice& d = (*user_devices_)[static_cast<int>(id)];
              if (key == "device-kind")
                d.kind = item.inputs.empty() ? std::string() : item.inputs.front();
              else
                d.options.insert(d.options.end(), item.inputs.begin(), item.inputs.end());
            }
            continue;
          }
        }
        if (user < 0 || id != user || !has(key)) continue;   // another user's, or another program's
        item.parents.clear();
        item.name = key;
        user_items.push_back(std::move(item));
      } else if (item.parents.size() == 1 && (programs.count(p0) || p0 == program_)) {
        if (p0 == program_ ? !has(key) : !programs.at(p0).count(key))
          throw CLI::ConfigError(where(item) + ": unknown key '" + item.name + "' in [" + p0 + "]: " + p0 +
                                 " has no option --" + key);
        if (p0 != program_) continue;
        item.parents.clear();
        item.name = key;
        own_items.push_back(std::move(item));
      } else {
        std::string names;
        for (const auto& [name, keys] : programs) names += (names.empty() ? "" : ", ") + ("[" + name + "]");
        const auto it = lines.find("[" + detail::join(item.parents, ".") + "]");
        throw CLI::ConfigError(file + (it == lines.end() ? std::string() : ":" + std::to_string(it->second)) +
                               ": unknown section [" + detail::join(item.parents, ".") + "] (sections: " + names +
                               ", [user.N])");
      }
    }
    // CLI11 takes the first value it meets for an option: the most specific first.
    std::vector<CLI::ConfigItem> out;
    for (auto* v : {&user_items, &own_items, &shared_items}) out.insert(out.end(), v->begin(), v->end());
    return out;
  }

 private:
  std::string file_name() const {
    const CLI::Option* c = app_->get_config_ptr();
    return c && c->count() > 0 ? c->as<std::string>() : std::string("session file");
  }
  // This program's user: the command line's --user/--device, else the file's own section, else 0.
  int user_id(const std::vector<CLI::ConfigItem>& items) const {
    if (program_ == "haptree_run") return 0;   // the launcher runs user 0's own device (the others are scripted)
    if (user_option_.empty()) return -1;
    const CLI::Option* o = app_->get_option_no_throw("--" + user_option_);
    if (o && o->count() > 0) return o->as<int>();
    for (const auto& it : items)
      if (it.parents.size() == 1 && it.parents[0] == program_ && detail::dashes(it.name) == user_option_ &&
          !it.inputs.empty())
        return std::atoi(it.inputs[0].c_str());
    return 0;
  }
  // This program has the option --key (its own options decide, so that a program's new option is in
  // its section without further ado; session_programs() is for the keys of the other programs).
  bool has(const std::string& key) const {
    const CLI::Option* o = app_->get_option_no_throw("--" + key);
    return o != nullptr && o->get_configurable();
  }
  const CLI::App* app_;
  std::string program_, user_option_;
  std::map<int, UserDevice>* user_devices_;
};

// Writes the effective settings of `app` as a session file section [program]: every option with its
// value (given, from a file or the environment, or the default); an option without a value is written
// as a comment. Reads back (`--config`) to the same settings.
inline std::string effective_config(const CLI::App& app, const std::string& program) {
  auto quote = [](const std::string& s) {
    char* end = nullptr;
    std::strtod(s.c_str(), &end);
    if (!s.empty() && *end == '\0' && s.find_first_of("xXpP") == std::string::npos &&
        s.find_first_not_of("0123456789+-.eE") == std::string::npos)
      return s;   // a plain number
    if (s == "true" || s == "false") return s;
    std::string q = "\"";
    for (char c : s) q += (c == '"' || c == '\\') ? std::string("\\") + c : std::string(1, c);
    return q + "\"";
  };
  std::string out = "# " + program + ": effective settings (" + program + " --config FILE reads them back)\n[" +
                    program + "]\n";
  for (const CLI::Option* opt : app.get_options({})) {
    if (!opt->get_configurable() || opt->get_lnames().empty() || opt == app.get_config_ptr() ||
        opt == app.get_help_ptr() || opt == app.get_help_all_ptr())
      continue;
    const std::string key = opt->get_lnames()[0];
    if (opt->get_expected_min() == 0) {   // a flag: `key = true` when its last value is what the bare flag gives
      bool given = false;
      if (!opt->results().empty()) {
        try {
          given = CLI::detail::to_flag_value(opt->results().back()) ==
                  CLI::detail::to_flag_value(opt->get_flag_value(key, ""));
        } catch (const std::exception&) {
        }
      }
      out += key + " = " + (given ? "true" : "false") + "\n";
      continue;
    }
    std::vector<std::string> values = opt->results();
    if (values.empty()) {
      std::string d = opt->get_default_str();
      if (!d.empty() && d.front() == '[' && d.back() == ']') d = d.substr(1, d.size() - 2);
      if (!d.empty()) values = CLI::detail::split(d, ',');
    }
    if (values.empty()) {
      out += "# " + key + " =   (not set)\n";
      continue;
    }
    if (values.size() == 1 && opt->get_items_expected_max() <= 1) {
      out += key + " = " + quote(values[0]) + "\n";
      continue;
    }
    std::string arr;
    for (const auto& v : values) arr += (arr.empty() ? "" : ", ") + quote(detail::trim(v));
    out += key + " = [" + arr + "]\n";
  }
  return out;
}

// A default that depends on other options (a molecule's time step): sets the value unless the command
// line or the file gave one, and makes it the default --print-config writes. True if it was set.
template <typename T>
bool set_default(CLI::App& app, const std::string& name, T& target, const T& value) {
  CLI::Option* o = app.get_option(name);
  if (o->count() > 0) return false;
  target = value;
  std::string text;
  for (int digits = 6; digits <= 17; ++digits) {   // the shortest text that reads back to the value
    std::ostringstream s;
    s.precision(digits);
    s << value;
    text = s.str();
    std::istringstream back(text);
    T read{};
    back >> read;
    if (read == value) break;
  }
  o->default_str(text);
  return true;
}

// One program's command line: --config and --print-config, and the deprecated names.
class ProgramCli {
 public:
  // renamed: {old, new} option names (with dashes) still accepted for one release.
  ProgramCli(CLI::App& app, std::string program, std::vector<std::pair<std::string, std::string>> renamed = {},
             std::string user_option = "")
      : app_(app), program_(std::move(program)), renamed_(std::move(renamed)) {
    app_.set_config("--config", "",
                    "session file (TOML; docs/processes.md): the shared keys, [" + program_ +
                        "]" + (user_option.empty() ? std::string() : " and [user.N]") +
                        "; the command line overrides it")
        ->type_name("FILE")
        ->group("Session file");
    app_.config_formatter(std::make_shared<SessionConfig>(&app_, program_, std::move(user_option), &user_devices_));
    app_.allow_config_extras(CLI::config_extras_mode::error);
    app_.add_flag("--print-config", print_config_,
                  "write the effective settings as a session file section [" + program_ + "] and exit")
        ->configurable(false)
        ->group("Session file");
  }

  // Returns -1 to go on, or the exit code (help, --print-config, a parse error). `after` runs once the
  // command line and the file are read, before --print-config: the place for defaults that depend on
  // other options (set_default below).
  int parse(int argc, char** argv, const std::function<void()>& after = {}) {
    std::vector<std::string> args;
    for (int i = 1; i < argc; ++i) args.push_back(rewrite(argv[i]));
    std::reverse(args.begin(), args.end());   // CLI11's parse(vector) takes them last-first
    try {
      app_.parse(args);
    } catch (const CLI::ParseError& e) {
      return app_.exit(e);
    }
    if (after) after();
    if (print_config_) {
      std::fputs(effective_config(app_, program_).c_str(), stdout);
      return 0;
    }
    return -1;
  }

  // The launcher's users N >= 1 whose [user.N] section names a device (empty for other programs).
  const std::map<int, UserDevice>& file_user_devices() const { return user_devices_; }

 private:
  std::string rewrite(const std::string& arg) const {
    for (const auto& [old_name, new_name] : renamed_) {
      if (arg == old_name || arg.rfind(old_name + "=", 0) == 0) {
        std::fprintf(stderr, "%s: %s is deprecated (accepted for one release): use %s\n", program_.c_str(),
                     old_name.c_str(), new_name.c_str());
        return new_name + arg.substr(old_name.size());
      }
    }
    return arg;
  }
  CLI::App& app_;
  std::string program_;
  std::vector<std::pair<std::string, std::string>> renamed_;
  bool print_config_ = false;
  std::map<int, UserDevice> user_devices_;
};

}  // namespace haptree::bus
