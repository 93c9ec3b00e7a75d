// Deep models. A 4096- and a 20 000-link URDF chain go through the URDF loader, the
// haptree-fd executable and sim_server (load + a few adaptive steps) without recursion on the call stack;
// a URDF whose joints close a loop (a link with two parents) is refused with both parents named.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <atomic>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>

#include "haptree/bus/bus.hpp"
#include "haptree/dca.hpp"
#include "haptree/io/urdf.hpp"
#include "sim_server/sim_server.hpp"

namespace haptree {
namespace {

// base (held by root_joint) -> l1 -> ... -> lN, revolute joints about z, 0.1 m apart along x.
std::string chain_urdf(int n) {
  std::ostringstream os;
  auto link = [&os](const std::string& name) {
    os << "<link name=\"" << name << "\"><inertial><mass value=\"1\"/>"
       << "<inertia ixx=\"0.01\" ixy=\"0\" ixz=\"0\" iyy=\"0.01\" iyz=\"0\" izz=\"0.01\"/></inertial></link>\n";
  };
  os << "<robot name=\"chain" << n << "\">\n";
  link("base");
  for (int k = 1; k <= n; ++k) {
    link("l" + std::to_string(k));
    os << "<joint name=\"j" << k << "\" type=\"revolute\"><parent link=\"" << (k == 1 ? "base" : "l" + std::to_string(k - 1))
       << "\"/><child link=\"l" << k << "\"/><origin xyz=\"0.1 0 0\"/><axis xyz=\"0 0 1\"/>"
       << "<limit lower=\"-3\" upper=\"3\" effort=\"1\" velocity=\"1\"/></joint>\n";
  }
  os << "</robot>\n";
  return os.str();
}

std::string write_chain(int n) {
  const std::string path = ::testing::TempDir() + "haptree_chain_" + std::to_string(n) + ".urdf";
  std::ofstream(path) << chain_urdf(n);
  return path;
}

class DeepChain : public ::testing::TestWithParam<int> {};

TEST_P(DeepChain, Loader) {
  const int n = GetParam();
  auto m = io::parse_urdf(chain_urdf(n), "chain.urdf");
  ASSERT_EQ(m->nbodies, n + 2);   // ground, base, l1..lN
  EXPECT_EQ(m->nv, n);
  for (int k = 2; k < m->nbodies; ++k) {
    ASSERT_EQ(m->parent[k], k - 1) << k;
    ASSERT_EQ(m->joint_name[k], "j" + std::to_string(k - 1));
  }
  // One forward-dynamics pass of the whole chain under gravity (along the joint axes: no motion).
  State st(*m);
  Data d(*m);
  const Eigen::VectorXd& qdd = forward_dynamics(*m, d, st);
  ASSERT_EQ(qdd.size(), n);
  // (No check on diag.singular_pivots: a straight 20 000-link, 2 km chain is conditioned so badly that its
  // tip pivots fall below the relative threshold; the point here is the depth.)
  EXPECT_TRUE(qdd.allFinite());
}

TEST_P(DeepChain, HaptreeFd) {
  const int n = GetParam();
  const std::string path = write_chain(n);
  const std::string cmd = std::string(HAPTREE_FD_EXE) + " --urdf " + path + " --indent -1 2>&1";
  FILE* p = ::popen(cmd.c_str(), "r");
  ASSERT_NE(p, nullptr);
  std::string out;
  char buf[65536];
  for (size_t k; (k = std::fread(buf, 1, sizeof buf, p)) > 0;) out.append(buf, k);
  const int st = ::pclose(p);
  ASSERT_TRUE(WIFEXITED(st)) << "haptree-fd died (signal " << WTERMSIG(st) << ") on a " << n << "-link chain";
  EXPECT_EQ(WEXITSTATUS(st), 0) << out.substr(0, 500);
  EXPECT_NE(out.find("\"j" + std::to_string(n) + "\":"), std::string::npos);
}

TEST_P(DeepChain, SimServer) {
  const int n = GetParam();
  SimServerOptions o;
  o.urdf = write_chain(n);
  o.steps = 3;
  o.gravity = Vec3::Zero();
  bus::Bus bus("memq://");
  SimServer server(bus, o);
  EXPECT_EQ(server.model().nv, n);
  std::atomic<bool> stop{false};
  EXPECT_EQ(server.run(stop), 0);
  EXPECT_EQ(server.steps_done(), 3);
  EXPECT_EQ(server.resets(), 0);
}

INSTANTIATE_TEST_SUITE_P(Links, DeepChain, ::testing::Values(4096, 20000));

TEST(Urdf, ClosedLoopIsRejectedNamingBothParents) {
  const std::string xml = R"(<robot name="loop">
  <link name="a"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="b"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="c"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="d"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <joint name="ab" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="ac" type="revolute"><parent link="a"/><child link="c"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="bd" type="revolute"><parent link="b"/><child link="d"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="cd" type="revolute"><parent link="c"/><child link="d"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>)";
  try {
    auto m = io::parse_urdf(xml, "loop.urdf");
    ADD_FAILURE() << "a closed loop was accepted as " << m->nbodies - 1 << " bodies";
  } catch (const io::UrdfError& e) {
    const std::string w = e.what();
    EXPECT_NE(w.find("link 'd' has two parents: 'b' (joint 'bd') and 'c' (joint 'cd')"), std::string::npos)
        << w;
  }
}

}  // namespace
}  // namespace haptree
