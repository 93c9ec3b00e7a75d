// haptree-fd end to end: runs the executable, parses its JSON, and compares with in-process DCA
// (bit-exact, the output uses %.17g) and with the long-double oracle; checks the error paths.
#include <gtest/gtest.h>

#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <fstream>
#include <string>

#include "haptree/dca.hpp"
#include "haptree/io/state_json.hpp"
#include "haptree/io/urdf.hpp"
#include "haptree/scenes.hpp"
#include "tests/support/oracle.hpp"

namespace haptree {
namespace {

struct CliRun {
  int status;
  std::string out;
};

CliRun run(const std::string& args) {
  const std::string cmd = std::string(HAPTREE_FD_EXE) + " " + args + " 2>&1";
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return {-1, ""};
  std::string out;
  std::array<char, 4096> buf;
  size_t n;
  while ((n = fread(buf.data(), 1, buf.size(), p)) > 0) out.append(buf.data(), n);
  const int st = pclose(p);
  return {WIFEXITED(st) ? WEXITSTATUS(st) : -1, out};
}

// q̈ in the model's layout from the CLI's {"qdd": {...}}.
Eigen::VectorXd parse_qdd(const Model& m, const std::string& text) {
  const auto j = nlohmann::json::parse(text);
  Eigen::VectorXd qdd = Eigen::VectorXd::Constant(m.nv, std::nan(""));
  for (auto it = j.at("qdd").begin(); it != j.at("qdd").end(); ++it) {
    const int k = m.joint_index(it.key());
    EXPECT_GT(k, 0) << it.key();
    if (k <= 0) continue;
    if (m.v_num[k] == 1) {
      qdd(m.v_adr[k]) = it.value().get<double>();
    } else {
      for (int i = 0; i < m.v_num[k]; ++i) qdd(m.v_adr[k] + i) = it.value()[i].get<double>();
    }
  }
  return qdd;
}

std::string write_temp(const std::string& name, const std::string& text) {
  const std::string path = ::testing::TempDir() + "/haptree_fd_" + name;
  std::ofstream(path) << text;
  return path;
}

TEST(FdCli, SceneWithStateMatchesLibraryAndOracle) {
  SceneOptions o;
  o.n = 24;
  o.seed = 4;
  o.mixed_joints = true;
  o.free_root = true;
  auto m = make_scene("random_tree", o);
  State st = testing::random_state(*m, 17);
  // State document from the random state, by joint name (lists for multi-DOF joints).
  nlohmann::json doc = {{"q", nlohmann::json::object()},
                        {"qd", nlohmann::json::object()},
                        {"tau", nlohmann::json::object()}};
  for (int k = 1; k < m->nbodies; ++k) {
    if (m->v_num[k] == 0) continue;
    auto list = [](const Eigen::VectorXd& v, int a, int n) {
      nlohmann::json l = nlohmann::json::array();
      for (int i = 0; i < n; ++i) l.push_back(v(a + i));
      return l;
    };
    doc["q"][m->joint_name[k]] = list(st.q, m->q_adr[k], joint_nq(m->joint_type[k]));
    doc["qd"][m->joint_name[k]] = list(st.qd, m->v_adr[k], m->v_num[k]);
    doc["tau"][m->joint_name[k]] = list(st.tau, m->v_adr[k], m->v_num[k]);
  }
  const std::string path = write_temp("state.json", doc.dump(-1, ' ', false,
                                                             nlohmann::json::error_handler_t::strict));
  const CliRun r = run("--scene random_tree --n 24 --seed 4 --mixed-joints --free-root --state " +
                    path + " --gravity 0.5,-1,-9");
  ASSERT_EQ(r.status, 0) << r.out;
  Model mg = *m;
  mg.gravity = Vec3(0.5, -1, -9);
  // The same state as the CLI sees (JSON round trip, quaternions normalised), no f_ext.
  const State st2 = io::state_from_json(mg, doc, "doc");
  Data d(mg);
  const Eigen::VectorXd expect = forward_dynamics(mg, d, st2);
  const Eigen::VectorXd got = parse_qdd(mg, r.out);
  ASSERT_EQ(got.size(), expect.size());
  for (int i = 0; i < got.size(); ++i) EXPECT_EQ(got(i), expect(i)) << i;   // %.17g round trip
  // Tolerance: B = c·n·ε·κ(H)·cancel (tests/support/oracle.hpp).
  const auto orc = testing::oracle_forward_dynamics(mg, st2);
  EXPECT_LE(testing::rel_err(got, orc.qdd), testing::qdd_error_bound(orc, st2, testing::kBoundC));
}

TEST(FdCli, UrdfDefaultsAndNames) {
  const std::string urdf = std::string(HAPTREE_URDF_DIR) + "/arm.urdf";
  const std::string path = write_temp(
      "arm_state.json",
      R"({"q": {"shoulder": 0.4, "elbow": -0.7}, "qd": {"twist": 1.0}, "tau": {"slider": 0.2}})");
  const CliRun r = run("--urdf " + urdf + " --state " + path + " --indent -1");
  ASSERT_EQ(r.status, 0) << r.out;
  auto m = io::load_urdf(urdf);
  const auto j = nlohmann::json::parse(r.out);
  ASSERT_EQ(j.at("qdd").size(), 4u);   // fixed joints are not printed
  for (const char* name : {"shoulder", "elbow", "slider", "twist"})
    EXPECT_TRUE(j.at("qdd").contains(name)) << name;
  const State st = io::load_state_json(*m, path);
  Data d(*m);
  const Eigen::VectorXd expect = forward_dynamics(*m, d, st);
  EXPECT_EQ(parse_qdd(*m, r.out), expect);
  // Default gravity is (0, 0, -9.81).
  EXPECT_EQ(m->gravity, Vec3(0, 0, -9.81));
}

TEST(FdCli, ErrorsAreOneLineAndNonZero) {
  const std::string urdf = std::string(HAPTREE_URDF_DIR) + "/arm.urdf";
  const std::string bad_state = write_temp("bad.json", R"({"q": {"knee": 1}})");
  CliRun r = run("--urdf " + urdf + " --state " + bad_state);
  EXPECT_EQ(r.status, 1);
  EXPECT_NE(r.out.find("q.knee: unknown joint"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find(bad_state), std::string::npos) << r.out;
  EXPECT_EQ(r.out.find('\n'), r.out.size() - 1) << r.out;

  r = run("--urdf " + std::string(HAPTREE_URDF_DIR) + "/bad_planar.urdf");
  EXPECT_EQ(r.status, 1);
  EXPECT_NE(r.out.find("joint 'slide_plane'"), std::string::npos) << r.out;

  r = run("--scene chain --n 4 --gravity 1,2");
  EXPECT_NE(r.status, 0);
  r = run("");
  EXPECT_EQ(r.status, 1);
  EXPECT_NE(r.out.find("--urdf"), std::string::npos) << r.out;
  // A non-finite result (null in the JSON) is an error, naming the joints.
  const std::string huge = write_temp("huge.json", R"({"qd": {"j1": 1e300, "j2": 1e300}})");
  r = run("--scene chain --n 3 --state " + huge);
  EXPECT_EQ(r.status, 1) << r.out;
  EXPECT_NE(r.out.find("null"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("non-finite accelerations (null) for"), std::string::npos) << r.out;
  r = run("--help");
  EXPECT_EQ(r.status, 0);
  for (const char* s : {"--urdf", "--scene", "--state", "--gravity", "quaternion", "unknown"})
    EXPECT_NE(r.out.find(s), std::string::npos) << s;
}

}  // namespace
}  // namespace haptree
