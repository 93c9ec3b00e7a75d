// The session file and the one vocabulary of options (docs/processes.md, "Session file" and "Options"):
// every program reads --config FILE (its part of it), the command line wins, an unknown key is refused
// with the file's line, --print-config reads back, old option names still work with a warning, the
// option table in docs/processes.md is exactly what every program's --help lists, molecules run with no
// extra option, haptree_run runs user 0 on the device it is given, and the status has no placeholder.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <sys/wait.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "haptree/bus/session_config.hpp"
#include "launcher/haptree_status.hpp"

namespace haptree {
namespace {

struct Output {
  int rc = -1;
  std::string out;   // stdout (and stderr with both)
};

// Runs a shell command line; stdout, and stderr too unless split.
Output run(const std::string& cmd, bool with_stderr = true) {
  Output r;
  const bool redirected = cmd.find(" 2>") != std::string::npos;   // the caller put stderr somewhere
  FILE* p = ::popen((cmd + (redirected ? "" : with_stderr ? " 2>&1" : " 2>/dev/null")).c_str(), "r");
  if (!p) return r;
  char buf[4096];
  for (size_t n; (n = std::fread(buf, 1, sizeof buf, p)) > 0;) r.out.append(buf, n);
  const int st = ::pclose(p);
  r.rc = WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
  return r;
}

std::string write_file(const std::string& name, const std::string& text) {
  const std::string path = ::testing::TempDir() + name;
  std::ofstream(path) << text;
  return path;
}

// key -> value of a --print-config output (quotes kept off strings, arrays as written).
std::map<std::string, std::string> settings(const std::string& text) {
  std::map<std::string, std::string> m;
  std::istringstream in(text);
  std::string line;
  const std::regex kv(R"(^([a-z0-9-]+) = (.*)$)");
  std::smatch s;
  while (std::getline(in, line))
    if (std::regex_match(line, s, kv)) {
      std::string v = s[2];
      if (v.size() >= 2 && v.front() == '"' && v.back() == '"') v = v.substr(1, v.size() - 2);
      m[s[1]] = v;
    }
  return m;
}

std::string slurp(const std::string& path) {
  std::ifstream f(path);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

// haptree_run's summary line "  user U: body B, ..., max |f| at device X N, ..."; -1 if absent.
double summary_max_force(const std::string& out, int user) {
  std::smatch m;
  const std::regex re("  user " + std::to_string(user) + R"(: body \d+, .*max \|f\| at device ([0-9.]+) N)");
  return std::regex_search(out, m, re) ? std::stod(m[1]) : -1.0;
}

const std::map<std::string, std::string>& programs() {
  static const std::map<std::string, std::string> p = {
      {"sim_server", HAPTREE_SIM_SERVER}, {"coupler", HAPTREE_COUPLER},       {"device_bridge", HAPTREE_DEVICE_BRIDGE},
      {"viewer", HAPTREE_VIEWER},         {"imd_bridge", HAPTREE_IMD_BRIDGE}, {"haptree_run", HAPTREE_RUN}};
  return p;
}

// The session file of the two-host recipe: every program reads it without an error.
const char* kSession = R"(# a session for every program
lcm-url = "memq://"
scene = "protein_like"
n = 32
sim-rate-hz = 500
coupler-rate-hz = 4000
max-force-n = 2.5

[sim_server]
dt = 0.002

[coupler]
stiffness = 30

[viewer]
viewer-port = 0

[imd_bridge]
imd-port = 0

[user.1]
stiffness = 40
device-kind = "virtual_hand"
device-option = ["mass_kg=0.2", "pull_distance_m=0.01"]
offset = [1.5, -2, 0.25]
)";

TEST(SessionFile, EveryProgramReadsItsPartAndTheCommandLineWins) {
  const std::string f = write_file("session_every.toml", kSession);
  auto cfg = [&](const std::string& prog, const std::string& extra) {
    const Output r = run(programs().at(prog) + " --config " + f + " " + extra + " --print-config", false);
    EXPECT_EQ(r.rc, 0) << prog << " " << extra << ":\n" << r.out;
    return settings(r.out);
  };
  auto sim = cfg("sim_server", "");
  EXPECT_EQ(sim["sim-rate-hz"], "500");
  EXPECT_EQ(sim["dt"], "0.002");
  EXPECT_EQ(sim["n"], "32");
  EXPECT_EQ(sim["lcm-url"], "memq://");
  auto c0 = cfg("coupler", "--user 0");
  EXPECT_EQ(c0["coupler-rate-hz"], "4000");
  EXPECT_EQ(c0["stiffness"], "30");   // [coupler]
  EXPECT_EQ(c0["max-force-n"], "2.5");
  auto c1 = cfg("coupler", "--user 1 --coupler-rate-hz 2000");
  EXPECT_EQ(c1["stiffness"], "40");            // [user.1] over [coupler]
  EXPECT_EQ(c1["coupler-rate-hz"], "2000");    // the command line over the file
  EXPECT_EQ(c1["offset"], "[1.5, -2, 0.25]");
  auto d1 = cfg("device_bridge", "--device 1");
  EXPECT_EQ(d1["device-kind"], "virtual_hand");
  EXPECT_EQ(d1["device-option"], "[\"mass_kg=0.2\", \"pull_distance_m=0.01\"]");
  auto d0 = cfg("device_bridge", "--device 0");
  EXPECT_EQ(d0["device-kind"], "scripted");
  auto v = cfg("viewer", "");
  EXPECT_EQ(v["viewer-port"], "0");
  EXPECT_EQ(v["n"], "32");
  auto i = cfg("imd_bridge", "");
  EXPECT_EQ(i["imd-port"], "0");
  auto h = cfg("haptree_run", "");
  EXPECT_EQ(h["sim-rate-hz"], "500");
  EXPECT_EQ(h["coupler-rate-hz"], "4000");
  EXPECT_EQ(h["device-kind"], "");   // [user.1] is not the launcher's user 0
}

TEST(SessionFile, PrintConfigReadsBackToTheSameSettings) {
  for (const auto& [prog, exe] : programs()) {
    std::string args = prog == "imd_bridge" ? "--scene ala20 " : "";
    if (prog == "coupler") args += "--offset 1,2,3 --sleep --shm --coupler-rate-hz 3000 ";
    if (prog == "device_bridge") args += "--device-option a=1 --device-option b=2 ";
    const Output a = run(exe + " " + args + "--print-config", false);
    ASSERT_EQ(a.rc, 0) << prog << ":\n" << a.out;
    const std::string f = write_file("readback_" + prog + ".toml", a.out);
    const Output b = run(exe + " --config " + f + " --print-config", false);
    EXPECT_EQ(b.rc, 0) << prog << ":\n" << b.out;
    EXPECT_EQ(a.out, b.out) << prog;
    EXPECT_GT(settings(a.out).size(), 5u) << prog << ":\n" << a.out;
  }
}

TEST(SessionFile, UnknownKeysAndSectionsNameTheFileLineAndKey) {
  struct Case {
    std::string text, program, expect;
  };
  const std::vector<Case> cases = {
      {"scene = \"chain\"\n\nsim-rate-hzz = 10\n", "sim_server", ":3: unknown key 'sim-rate-hzz'"},
      {"# c\n[coupler]\nstiffness = 10\ndt = 0.1\n", "coupler", ":4: unknown key 'dt' in [coupler]"},
      {"[viewer]\nviewer-port = 0\n[simserver]\nn = 3\n", "viewer", ":3: unknown section [simserver]"},
      {"[user.0]\nscene = \"chain\"\n", "coupler", ":2: key 'scene' does not belong in [user.0]"},
      // a section of another program is checked too: the typo is found whoever reads the file first
      {"[sim_server]\nsteps = 5\nstifness = 3\n", "device_bridge", ":3: unknown key 'stifness' in [sim_server]"},
  };
  int k = 0;
  for (const auto& c : cases) {
    const std::string f = write_file("bad_" + std::to_string(k++) + ".toml", c.text);
    const Output r = run(programs().at(c.program) + " --config " + f + " --print-config");
    EXPECT_NE(r.rc, 0) << c.text;
    EXPECT_NE(r.out.find(f + c.expect), std::string::npos) << "expected '" << f + c.expect << "' in:\n" << r.out;
  }
  const Output missing = run(std::string(HAPTREE_COUPLER) + " --config /nonexistent/session.toml");
  EXPECT_NE(missing.rc, 0);
  EXPECT_NE(missing.out.find("/nonexistent/session.toml"), std::string::npos) << missing.out;
}

TEST(SessionFile, OldOptionNamesWorkWithOneDeprecationLine) {
  struct Case {
    std::string program, args, key, value, old_name;
  };
  const std::vector<Case> cases = {
      {"sim_server", "--rate-hz 250", "sim-rate-hz", "250", "--rate-hz"},
      {"coupler", "--rate-hz=2500", "coupler-rate-hz", "2500", "--rate-hz"},
      {"device_bridge", "--kind virtual_hand --option mass_kg=0.3 --rate-hz 500", "device-kind", "virtual_hand", "--kind"},
      {"viewer", "--port 0 --bind 127.0.0.1 --users 3", "viewer-users", "3", "--users"},
      {"viewer", "--viewer-port 0 --no-token", "viewer-no-token", "true", "--no-token"},
      {"imd_bridge", "--scene ala20 --port 0 --user-id 4 --rate 7 --max-force 100", "imd-every-steps", "7", "--rate"},
  };
  for (const auto& c : cases) {
    const Output out = run(programs().at(c.program) + " " + c.args + " --print-config", false);
    EXPECT_EQ(out.rc, 0) << c.program << " " << c.args << ":\n" << out.out;
    EXPECT_EQ(settings(out.out)[c.key], c.value) << c.program << " " << c.args << ":\n" << out.out;
    const Output both = run(programs().at(c.program) + " " + c.args + " --print-config");
    EXPECT_NE(both.out.find(c.program + ": " + c.old_name + " is deprecated"), std::string::npos) << both.out;
  }
}

// Every option of every program is a row of the table in docs/processes.md with a mark in that
// program's column, and every marked cell is an option of that program's --help; the vocabulary of the
// session file (session_programs()) is the same.
TEST(Options, TableInDocsMatchesEveryHelp) {
  std::ifstream doc(HAPTREE_SOURCE_DIR "/docs/processes.md");
  ASSERT_TRUE(doc.good());
  std::string line;
  std::vector<std::string> columns;
  std::map<std::string, std::set<std::string>> table;   // program -> options marked
  bool in_table = false;
  while (std::getline(doc, line)) {
    if (line.rfind("| option |", 0) == 0) {
      in_table = true;
      std::istringstream h(line);
      std::string cell;
      while (std::getline(h, cell, '|')) columns.push_back(bus::detail::trim(cell));
      continue;
    }
    if (!in_table) continue;
    if (line.empty() || line[0] != '|') break;
    if (line.rfind("|--", 0) == 0 || line.rfind("| --- ", 0) == 0 || line.rfind("|---", 0) == 0) continue;
    std::vector<std::string> cells;
    std::istringstream r(line);
    std::string cell;
    while (std::getline(r, cell, '|')) cells.push_back(bus::detail::trim(cell));
    ASSERT_GE(cells.size(), columns.size()) << line;
    std::smatch m;
    ASSERT_TRUE(std::regex_search(cells[1], m, std::regex(R"(`--([a-z0-9-]+)`)"))) << line;
    for (size_t c = 0; c < columns.size(); ++c)
      if (programs().count(columns[c]) && cells[c] == "✓") table[columns[c]].insert(m[1]);
  }
  ASSERT_EQ(table.size(), programs().size()) << "the table's header must name every program";
  for (const auto& [prog, exe] : programs()) {
    const Output help = run(exe + " --help", false);
    ASSERT_EQ(help.rc, 0) << prog;
    std::set<std::string> have;
    std::istringstream in(help.out);
    const std::regex opt(R"(^\s+(?:-[a-zA-Z],)?--([a-z0-9-]+))");
    std::smatch m;
    while (std::getline(in, line))
      if (std::regex_search(line, m, opt) && m[1] != "help" && m[1] != "config" && m[1] != "print-config")
        have.insert(m[1]);
    for (const auto& o : have)
      EXPECT_TRUE(table[prog].count(o)) << prog << " --" << o << " is not marked for " << prog << " in docs/processes.md";
    for (const auto& o : table[prog])
      EXPECT_TRUE(have.count(o)) << "docs/processes.md marks --" << o << " for " << prog << ", whose --help has no such option";
    EXPECT_EQ(have, bus::session_programs().at(prog)) << prog << ": session_programs() differs from --help";
  }
}

// The "Two hosts" recipe of docs/processes.md is the file the two-host test runs, byte for byte.
TEST(SessionFile, TwoHostsRecipeInDocsIsTheTestedFile) {
  std::ifstream d(HAPTREE_SOURCE_DIR "/docs/processes.md"), f(HAPTREE_SOURCE_DIR "/examples/sessions/two_hosts.toml");
  std::stringstream ds, fs;
  ds << d.rdbuf();
  fs << f.rdbuf();
  const std::string doc = ds.str();
  const auto section = doc.find("\n## Two hosts");
  ASSERT_NE(section, std::string::npos);
  const auto open = doc.find("```toml\n", section);
  ASSERT_NE(open, std::string::npos);
  const auto close = doc.find("```\n", open + 8);
  ASSERT_NE(close, std::string::npos);
  EXPECT_EQ(doc.substr(open + 8, close - open - 8), fs.str());
  // and every program reads it (the viewer's token file must exist: the host's is not here)
  const std::string token = write_file("viewer.token", "session-test-token-0123456789\n");
  for (const auto& [prog, exe] : programs()) {
    const Output r = run(exe + " --config " HAPTREE_SOURCE_DIR "/examples/sessions/two_hosts.toml --print-config" +
                      (prog == "imd_bridge" ? " --scene ala20" : "") + (prog == "viewer" ? " --viewer-token-file " + token : ""),
                      false);
    EXPECT_EQ(r.rc, 0) << prog << ":\n" << r.out;
  }
}

TEST(SessionFile, MoleculeScenesCarryWorkingDefaults) {
  const Output r = run(std::string(HAPTREE_RUN) + " --scene ala20 --print-config", false);
  ASSERT_EQ(r.rc, 0) << r.out;
  auto s = settings(r.out);
  EXPECT_EQ(s["dt"], "0.0005");
  EXPECT_EQ(s["position-scale"], "1");
  EXPECT_EQ(s["stiffness"], "200");
  const Output given = run(std::string(HAPTREE_RUN) + " --scene ala20 --dt 0.001 --print-config", false);
  EXPECT_EQ(settings(given.out)["dt"], "0.001");
  const Output sim = run(std::string(HAPTREE_SIM_SERVER) + " --scene ala20 --print-config", false);
  EXPECT_EQ(settings(sim.out)["dt"], "0.0005");
  const Output proc = run(std::string(HAPTREE_SIM_SERVER) + " --scene chain --print-config", false);
  EXPECT_EQ(settings(proc.out)["dt"], "0.001");
  // And the molecule runs with nothing else given: steps, a grab, a force at the device within the clamp;
  // --json: every stdout line is one JSON object.
  const Output go = run(std::string(HAPTREE_RUN) + " --scene ala20 --duration-s 3 --viewer-port 0 --json 2>" +
                         ::testing::TempDir() + "ala20_summary.txt", false);
  ASSERT_EQ(go.rc, 0) << go.out;
  std::istringstream in(go.out);
  std::string line;
  int64_t steps = 0;
  int objects = 0;
  while (std::getline(in, line)) {
    const auto j = nlohmann::json::parse(line);   // throws (fails the test) on anything but JSON
    ++objects;
    if (!j["sim"]["steps"].is_null()) steps = j["sim"]["steps"].get<int64_t>();
  }
  const double fmax = summary_max_force(slurp(::testing::TempDir() + "ala20_summary.txt"), 0);
  std::printf("ala20 with no options: %d status objects, %lld steps in 3 s, max |f| at the device %.3f N\n", objects,
              static_cast<long long>(steps), fmax);
  EXPECT_GE(objects, 2);
  EXPECT_GT(steps, 100);
  EXPECT_GT(fmax, 0.01);
  EXPECT_LE(fmax, 3.0 + 1e-9);
}

// haptree_run --device-kind: user 0 on that device, the others on the script. A scripted device with
// no pull stands for "another device": user 0 grabs and holds still (no force beyond what the moving
// chain gives), user 1 pulls 3 cm as always. In the embedded mode and with --processes.
TEST(Launcher, DeviceKindRunsUserZeroOnThatDevice) {
  for (const std::string mode : {"", "--processes "}) {
    const std::string cmd = std::string(HAPTREE_RUN) + " " + mode +
                            "--duration-s 4 --scene protein_like --users 2 --viewer-port 0 "
                            "--device-kind scripted --device-option grab_m=0,0,0.01 --device-option pull_distance_m=0";
    const Output r = run(cmd);
    ASSERT_EQ(r.rc, 0) << cmd << "\n" << r.out;
    const double f0 = summary_max_force(r.out, 0), f1 = summary_max_force(r.out, 1);
    std::printf("%s: user 0 (no pull) peak |f| %.4f N, user 1 (3 cm pull) %.4f N\n", mode.empty() ? "embedded" : "processes",
                f0, f1);
    EXPECT_GT(f1, 0.05) << r.out;
    EXPECT_LT(f0, 0.5 * f1) << r.out;
    const Output bad = run(std::string(HAPTREE_RUN) + " " + mode + "--duration-s 2 --viewer-port 0 --device-kind no_such_kind");
    EXPECT_NE(bad.rc, 0) << bad.out;
    EXPECT_NE(bad.out.find("no_such_kind"), std::string::npos) << bad.out;
  }
}

TEST(Launcher, SessionFileGivesEachUserItsDevice) {
  // User 1's device from [user.1] (holding still), user 0 the scripted pull: the reverse of the test above.
  const std::string file = write_file("users_devices.toml",
                                      "[haptree_run]\nusers = 2\n[user.1]\ndevice-kind = \"scripted\"\n"
                                      "device-option = [\"grab_m=0,0,0.01\", \"pull_distance_m=0\"]\n");
  for (const std::string mode : {"", "--processes "}) {
    const std::string cmd = std::string(HAPTREE_RUN) + " " + mode + "--config " + file +
                            " --duration-s 4 --scene protein_like --viewer-port 0";
    const Output r = run(cmd);
    ASSERT_EQ(r.rc, 0) << cmd << "\n" << r.out;
    const double f0 = summary_max_force(r.out, 0), f1 = summary_max_force(r.out, 1);
    std::printf("%s: user 0 (3 cm pull) peak |f| %.4f N, user 1 ([user.1], no pull) %.4f N\n",
                mode.empty() ? "embedded" : "processes", f0, f1);
    EXPECT_GT(f0, 0.05) << r.out;
    EXPECT_LT(f1, 0.5 * f0) << r.out;
  }
  const std::string beyond = write_file("users_beyond.toml", "[user.3]\ndevice-kind = \"scripted\"\n");
  Output bad = run(std::string(HAPTREE_RUN) + " --config " + beyond + " --users 2 --duration-s 2 --viewer-port 0");
  EXPECT_EQ(bad.rc, 2) << bad.out;
  EXPECT_NE(bad.out.find("[user.3]"), std::string::npos) << bad.out;
  const std::string no_kind = write_file("users_no_kind.toml", "[user.1]\ndevice-option = [\"hold_s=1\"]\n");
  bad = run(std::string(HAPTREE_RUN) + " --config " + no_kind + " --users 2 --duration-s 2 --viewer-port 0");
  EXPECT_EQ(bad.rc, 2) << bad.out;
  EXPECT_NE(bad.out.find("no device-kind"), std::string::npos) << bad.out;
}

TEST(Status, NoPlaceholderValues) {
  launcher::StatusSample s;
  s.t_s = 0.5;
  launcher::UserStatus u;
  u.user = 0;
  u.started = true;
  u.rate_hz = 0;    // no window closed yet
  u.force_n = 0;
  u.grab_body = 0;  // holds nothing
  u.snapshot_age_ms = -1;
  s.users.push_back(u);
  const std::string text = launcher::status_text(s);
  EXPECT_EQ(text.find("0 Hz"), std::string::npos) << text;
  EXPECT_EQ(text.find("-1"), std::string::npos) << text;
  EXPECT_NE(text.find("no grab"), std::string::npos) << text;
  EXPECT_NE(text.find("sim starting"), std::string::npos) << text;
  const auto j = nlohmann::json::parse(launcher::status_json(s));
  EXPECT_TRUE(j["users"][0]["rate_hz"].is_null());
  EXPECT_TRUE(j["users"][0]["snapshot_age_ms"].is_null());
  EXPECT_TRUE(j["users"][0]["grab_body"].is_null());
  EXPECT_TRUE(j["sim"]["step_ms"].is_null());
  EXPECT_EQ(j["users"][0]["force_n"].get<double>(), 0.0);
  s.sim.started = true;
  s.sim.step_ms = 0.25;
  s.sim.active_dofs = 48;
  s.users[0].rate_hz = 9990;
  s.users[0].grab_body = 7;
  s.users[0].snapshot_age_ms = 1.25;
  const std::string t2 = launcher::status_text(s);
  EXPECT_NE(t2.find("9990 Hz"), std::string::npos) << t2;
  EXPECT_NE(t2.find("body 7, snapshot age 1.2 ms"), std::string::npos) << t2;
  const auto j2 = nlohmann::json::parse(launcher::status_json(s));
  EXPECT_EQ(j2["users"][0]["grab_body"].get<int>(), 7);
  EXPECT_DOUBLE_EQ(j2["users"][0]["snapshot_age_ms"].get<double>(), 1.25);
  EXPECT_DOUBLE_EQ(j2["sim"]["step_ms"].get<double>(), 0.25);
}

// The launcher's own text status, first second included: no "0 Hz", no negative snapshot age.
TEST(Status, LauncherTextHasNoPlaceholder) {
  const Output r = run(std::string(HAPTREE_RUN) + " --duration-s 2 --scene protein_like --n 32 --viewer-port 0", false);
  ASSERT_EQ(r.rc, 0) << r.out;
  std::istringstream in(r.out);
  std::string line;
  int status_lines = 0;
  while (std::getline(in, line)) {
    if (line.rfind("t ", 0) != 0) continue;
    ++status_lines;
    EXPECT_EQ(line.find(" 0 Hz"), std::string::npos) << line;
    EXPECT_EQ(line.find("age -"), std::string::npos) << line;
  }
  EXPECT_GE(status_lines, 2) << r.out;
}

}  // namespace
}  // namespace haptree
