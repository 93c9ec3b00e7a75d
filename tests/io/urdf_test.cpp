// URDF loader: structure, URDF frame semantics (checked against a model built by hand with
// ModelBuilder from independently composed transforms), lumping rules, and one-line errors.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "haptree/dca.hpp"
#include "haptree/io/state_json.hpp"
#include "haptree/io/urdf.hpp"
#include "tests/support/oracle.hpp"

namespace haptree {
namespace {

const std::string kDir = HAPTREE_URDF_DIR;

// URDF rpy: fixed-axis roll about x, pitch about y, yaw about z, i.e. R = Rz(y) Ry(p) Rx(r).
Mat3 rpy(double r, double p, double y) {
  return (Eigen::AngleAxisd(y, Vec3::UnitZ()) * Eigen::AngleAxisd(p, Vec3::UnitY()) *
          Eigen::AngleAxisd(r, Vec3::UnitX()))
      .toRotationMatrix();
}

Mat3 sym(double xx, double xy, double xz, double yy, double yz, double zz) {
  Mat3 I;
  I << xx, xy, xz, xy, yy, yz, xz, yz, zz;
  return I;
}

TEST(Urdf, ArmStructure) {
  auto m = io::load_urdf(kDir + "/arm.urdf");
  // ground + base (fixed root) + upper, fore, carriage, tool (fixed, massive: kept), side;
  // the massless "mount" frame is lumped into "fore".
  ASSERT_EQ(m->nbodies, 7);
  EXPECT_EQ(m->nv, 4);
  EXPECT_EQ(m->body_index("mount"), -1);
  const int base = m->body_index("base"), upper = m->body_index("upper"),
            fore = m->body_index("fore"), carriage = m->body_index("carriage"),
            tool = m->body_index("tool"), side = m->body_index("side");
  ASSERT_GT(base, 0);
  ASSERT_GT(upper, 0);
  ASSERT_GT(fore, 0);
  ASSERT_GT(carriage, 0);
  ASSERT_GT(tool, 0);
  ASSERT_GT(side, 0);
  EXPECT_EQ(m->joint_name[base], "root_joint");
  EXPECT_EQ(m->joint_type[base], JointType::kFixed);
  EXPECT_EQ(m->parent[base], 0);
  EXPECT_EQ(m->joint_name[upper], "shoulder");
  EXPECT_EQ(m->joint_type[upper], JointType::kRevolute);
  EXPECT_EQ(m->joint_name[fore], "elbow");
  EXPECT_EQ(m->joint_type[fore], JointType::kRevolute);   // continuous
  EXPECT_EQ(m->joint_name[carriage], "slider");
  EXPECT_EQ(m->joint_type[carriage], JointType::kPrismatic);
  EXPECT_EQ(m->parent[carriage], fore);
  EXPECT_EQ(m->joint_type[tool], JointType::kFixed);
  EXPECT_EQ(m->joint_name[tool], "tool_fix");
  EXPECT_EQ(m->parent[side], base);

  // Joint frames.
  EXPECT_LT((m->joint_offset[upper] - Vec3(0, 0, 0.1)).norm(), 1e-15);
  EXPECT_LT((m->joint_rotation[upper] - rpy(0, 0, 0.3)).norm(), 1e-14);
  EXPECT_LT((m->joint_axis[fore] - Vec3(0, 0.6, 0.8)).norm(), 1e-15);
  // Slider composed through the lumped mount frame: p = p_mount + R_mount p_slider.
  const Mat3 Rm = rpy(0, 0.5, 0);
  EXPECT_LT((m->joint_offset[carriage] - (Vec3(0.25, 0, 0) + Rm * Vec3(0.02, 0, 0))).norm(), 1e-15);
  EXPECT_LT((m->joint_rotation[carriage] - Rm * rpy(0.1, 0.2, 0.3)).norm(), 1e-14);

  // Inertials rotated into the link frame.
  const Mat3 Ri = rpy(0.2, -0.1, 0.4);
  const Mat3 I_upper = Ri * sym(0.01, 0.001, -0.0005, 0.03, 0.0002, 0.035) * Ri.transpose();
  EXPECT_DOUBLE_EQ(m->mass[upper], 1.5);
  EXPECT_LT((m->com[upper] - Vec3(0.15, 0.01, 0)).norm(), 1e-16);
  EXPECT_LT((m->inertia[upper] - I_upper).norm(), 1e-16);
  EXPECT_DOUBLE_EQ(m->mass[base], 3.0);
}

// The same arm built by hand from the URDF numbers (no URDF code involved).
std::shared_ptr<const Model> arm_by_hand() {
  ModelBuilder b;
  const Mat3 I3 = Mat3::Identity();
  const int base = b.add_body("base", 0, JointType::kFixed, Vec3::Zero(), I3, Vec3::UnitZ(), 3.0,
                              Vec3(0, 0, 0.05), sym(0.02, 0, 0, 0.02, 0, 0.03), "root_joint");
  const Mat3 Ru = rpy(0.2, -0.1, 0.4);
  const int upper = b.add_body("upper", base, JointType::kRevolute, Vec3(0, 0, 0.1), rpy(0, 0, 0.3),
                               Vec3::UnitZ(), 1.5, Vec3(0.15, 0.01, 0),
                               Ru * sym(0.01, 0.001, -0.0005, 0.03, 0.0002, 0.035) * Ru.transpose(),
                               "shoulder");
  const int fore = b.add_body("fore", upper, JointType::kRevolute, Vec3(0.3, 0, 0),
                              rpy(M_PI / 2, 0, 0), Vec3(0, 0.6, 0.8), 0.8, Vec3(0.12, 0, 0.01),
                              sym(0.002, 0.0003, 0, 0.01, 0, 0.011), "elbow");
  const Mat3 Rm = rpy(0, 0.5, 0);
  const Mat3 Rc = rpy(0.3, 0, 0);
  const int carriage = b.add_body(
      "carriage", fore, JointType::kPrismatic, Vec3(0.25, 0, 0) + Rm * Vec3(0.02, 0, 0),
      Rm * rpy(0.1, 0.2, 0.3), Vec3::UnitX(), 0.3, Vec3(0.01, 0.02, -0.01),
      Rc * sym(0.0004, 0, 0, 0.0005, 0, 0.0006) * Rc.transpose(), "slider");
  b.add_body("tool", carriage, JointType::kFixed, Vec3(0.05, 0.01, 0), rpy(0, 0, 0.7),
             Vec3::UnitZ(), 0.2, Vec3(0.03, 0, 0), sym(0.0001, 0, 0, 0.0003, 0, 0.0003), "tool_fix");
  b.add_body("side", base, JointType::kRevolute, Vec3(0, 0.2, 0.05), I3, Vec3::UnitX(), 0.5,
             Vec3(0, 0.1, 0), sym(0.002, 0, 0, 0.0005, 0, 0.002), "twist");
  return b.build();
}

// q̈ by joint name, so models with different body orders compare.
std::map<std::string, double> qdd_by_name(const Model& m, const State& st) {
  Data d(m);
  const Eigen::VectorXd qdd = forward_dynamics(m, d, st);
  std::map<std::string, double> out;
  for (int k = 1; k < m.nbodies; ++k)
    if (m.v_num[k] == 1) out[m.joint_name[k]] = qdd(m.v_adr[k]);
  return out;
}

State arm_state(const Model& m) {
  const nlohmann::json doc = {
      {"q", {{"shoulder", 0.4}, {"elbow", -0.7}, {"slider", 0.03}, {"twist", 0.2}}},
      {"qd", {{"shoulder", 1.1}, {"elbow", -0.5}, {"slider", 0.2}, {"twist", -0.8}}},
      {"tau", {{"shoulder", 0.3}, {"elbow", -0.2}, {"slider", 0.1}, {"twist", 0.05}}},
      {"f_ext", {{"tool", {0.01, -0.02, 0.03, 0.5, -0.4, 0.3}}}}};
  return io::state_from_json(m, doc, "arm_state");
}

TEST(Urdf, ArmMatchesHandBuiltModel) {
  auto m = io::load_urdf(kDir + "/arm.urdf");
  auto h = arm_by_hand();
  const auto a = qdd_by_name(*m, arm_state(*m));
  const auto b = qdd_by_name(*h, arm_state(*h));
  ASSERT_EQ(a.size(), 4u);
  ASSERT_EQ(b.size(), 4u);
  for (const auto& [name, v] : b) {
    ASSERT_TRUE(a.count(name)) << name;
    EXPECT_NEAR(a.at(name), v, 1e-12 * std::max(1.0, std::abs(v))) << name;
  }
  // And the DCA result on the loaded model agrees with the long-double oracle.
  const State st = arm_state(*m);
  Data d(*m);
  const Eigen::VectorXd qdd = forward_dynamics(*m, d, st);
  {  // Tolerance from the error analysis: c·n·ε·κ(H)·cancel (tests/support/oracle.hpp).
    const auto orc = testing::oracle_forward_dynamics(*m, st);
    EXPECT_LT(testing::rel_err(qdd, orc.qdd), testing::qdd_error_bound(orc, st, testing::kBoundC));
  }
}

TEST(Urdf, LumpFixedKeepsTheDynamics) {
  io::UrdfOptions o;
  o.lump_fixed = true;
  auto lumped = io::load_urdf(kDir + "/arm.urdf", o);
  auto plain = io::load_urdf(kDir + "/arm.urdf");
  // base is welded to the ground (lumped into it), tool into carriage.
  EXPECT_EQ(lumped->nbodies, 5);
  EXPECT_EQ(lumped->body_index("tool"), -1);
  EXPECT_EQ(lumped->body_index("base"), -1);
  const int c = lumped->body_index("carriage");
  ASSERT_GT(c, 0);
  EXPECT_NEAR(lumped->mass[c], 0.5, 1e-15);
  const auto a = qdd_by_name(*lumped, arm_state(*plain));   // f_ext on "tool" is not in lumped
  (void)a;
  // Compare without the tool force (the lumped model has no "tool" body to push).
  nlohmann::json doc = {{"q", {{"shoulder", 0.4}, {"elbow", -0.7}, {"slider", 0.03}}},
                        {"qd", {{"shoulder", 1.1}, {"elbow", -0.5}, {"twist", -0.8}}},
                        {"tau", {{"slider", 0.1}, {"twist", 0.05}}}};
  const auto x = qdd_by_name(*lumped, io::state_from_json(*lumped, doc, "s"));
  const auto y = qdd_by_name(*plain, io::state_from_json(*plain, doc, "s"));
  ASSERT_EQ(x.size(), y.size());
  for (const auto& [name, v] : y) EXPECT_NEAR(x.at(name), v, 1e-11 * std::max(1.0, std::abs(v)));
}

TEST(Urdf, WorldRootWithFloatingJoint) {
  auto m = io::load_urdf(kDir + "/floating.urdf");
  const int torso = m->body_index("torso");
  ASSERT_GT(torso, 0);
  EXPECT_EQ(m->parent[torso], 0);
  EXPECT_EQ(m->joint_type[torso], JointType::kFree);
  EXPECT_EQ(m->joint_name[torso], "base_free");
  EXPECT_EQ(m->body_index("world"), 0);   // the ground itself, no extra body
  EXPECT_EQ(m->nv, 8);
  EXPECT_LT((m->joint_offset[torso] - Vec3(0, 0, 1)).norm(), 1e-15);
  const State st = testing::random_state(*m, 7);
  Data d(*m);
  const Eigen::VectorXd qdd = forward_dynamics(*m, d, st);
  {  // Tolerance from the error analysis: c·n·ε·κ(H)·cancel (tests/support/oracle.hpp).
    const auto orc = testing::oracle_forward_dynamics(*m, st);
    EXPECT_LT(testing::rel_err(qdd, orc.qdd), testing::qdd_error_bound(orc, st, testing::kBoundC));
  }
}

TEST(Urdf, FloatingBaseOption) {
  io::UrdfOptions o;
  o.floating_base = true;
  auto m = io::load_urdf(kDir + "/arm.urdf", o);
  const int base = m->body_index("base");
  ASSERT_GT(base, 0);
  EXPECT_EQ(m->joint_type[base], JointType::kFree);
  EXPECT_EQ(m->joint_name[base], "root_joint");
  EXPECT_EQ(m->nv, 10);
  // Free fall of the whole arm with no joint torques and no velocity: every body falls with g,
  // so the base's linear acceleration (body axes) is g and nothing rotates.
  State st(*m);
  st.q = neutral_configuration(*m);
  Data d(*m);
  const Eigen::VectorXd qdd = forward_dynamics(*m, d, st);
  const int a = m->v_adr[base];
  EXPECT_LT(qdd.segment<3>(a).norm(), 1e-10);
  EXPECT_LT((qdd.segment<3>(a + 3) - m->gravity).norm(), 1e-10);
}

// Expects an UrdfError whose single-line message names the file and the given element.
void expect_error(const std::string& file, const std::string& element, const std::string& name,
                  const std::string& what) {
  try {
    io::load_urdf(kDir + "/" + file);
    ADD_FAILURE() << file << ": no error";
  } catch (const io::UrdfError& e) {
    const std::string msg = e.what();
    EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
    EXPECT_NE(msg.find(file), std::string::npos) << msg;
    if (!element.empty()) {
      EXPECT_NE(msg.find(element + " '" + name + "'"), std::string::npos) << msg;
    }
    EXPECT_NE(msg.find(what), std::string::npos) << msg;
  }
}

TEST(Urdf, ErrorsNameFileAndElement) {
  expect_error("does_not_exist.urdf", "", "", "cannot open");
  expect_error("bad_xml.urdf", "", "", "bad_xml.urdf:4:");
  expect_error("bad_missing_link.urdf", "", "", "parse error");
  expect_error("bad_planar.urdf", "joint", "slide_plane", "planar");
  expect_error("bad_massless.urdf", "link", "ghost", "no mass");
  expect_error("bad_inertia.urdf", "link", "rod", "triangle inequality");
  expect_error("bad_negative_mass.urdf", "link", "rod", "mass");
}

// Joints that do not form a tree are refused before urdfdom sees them: urdfdom 3.0 leaks the link graph
// on these (fuzz/regressions/urdf/joint_cycle_leaks_in_urdfdom), and its own message names no line.
TEST(Urdf, JointCyclesAndSecondParentsAreRefusedWithTheJointsLine) {
  const std::string link = "<link name='%'><inertial><mass value='1'/>"
                           "<inertia ixx='1' ixy='0' ixz='0' iyy='1' iyz='0' izz='1'/></inertial></link>\n";
  auto L = [&](const std::string& n) {
    std::string s = link;
    s.replace(s.find('%'), 1, n);
    return s;
  };
  auto J = [](const std::string& n, const std::string& p, const std::string& c) {
    return "<joint name='" + n + "' type='revolute'><parent link='" + p + "'/><child link='" + c +
           "'/><axis xyz='0 0 1'/><limit lower='-1' upper='1' effort='1' velocity='1'/></joint>\n";
  };
  auto msg = [](const std::string& xml) {
    try {
      io::parse_urdf(xml, "t.urdf");
    } catch (const io::UrdfError& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  const std::string cycle = "<robot name='r'>\n" + L("a") + L("b") + L("c") + J("j1", "a", "b") +
                            J("j2", "b", "c") + J("j3", "c", "b") + "</robot>\n";
  EXPECT_NE(msg(cycle).find("t.urdf:7: joint 'j3': link 'b' already has parent link 'a'"), std::string::npos)
      << msg(cycle);
  const std::string loop = "<robot name='r'>\n" + L("a") + L("b") + J("j1", "a", "b") + J("j2", "b", "a") +
                           "</robot>\n";
  EXPECT_NE(msg(loop).find("the joints form a cycle through link"), std::string::npos) << msg(loop);
  const std::string self = "<robot name='r'>\n" + L("a") + J("j1", "a", "a") + "</robot>\n";
  EXPECT_NE(msg(self).find("t.urdf:3: joint 'j1': link 'a' is its own parent"), std::string::npos) << msg(self);
}

TEST(StateJson, HugeFiniteQuaternionIsNormalisedNotZeroed) {
  // norm() overflowed to inf for entries ~1e300 and the quaternion came out all zeros
  // (fuzz/regressions/state_json/huge_quaternion_became_zero).
  auto m = io::load_urdf(kDir + "/floating.urdf");
  const nlohmann::json doc = {{"q", {{"base_free", {1, 2, 3, 1e300, 1e300, 0, 0}}}}};
  const State st = io::state_from_json(*m, doc, "t.json");
  const int k = m->joint_index("base_free");
  const Eigen::Vector4d q = st.q.segment<4>(m->q_adr[k] + 3);
  EXPECT_NEAR(q(0), std::sqrt(0.5), 1e-15);
  EXPECT_NEAR(q(1), std::sqrt(0.5), 1e-15);
  EXPECT_EQ(q(2), 0.0);
  EXPECT_EQ(q(3), 0.0);
}

TEST(StateJson, ConventionsAndErrors) {
  auto m = io::load_urdf(kDir + "/floating.urdf");
  const nlohmann::json doc = {{"q", {{"base_free", {1, 2, 3, 2, 0, 0, 0}}, {"left_hip", 0.5}}},
                              {"qd", {{"base_free", {1, 2, 3, 4, 5, 6}}}}};
  const State st = io::state_from_json(*m, doc, "doc");
  const int t = m->body_index("torso");
  EXPECT_DOUBLE_EQ(st.q(m->q_adr[t] + 3), 1.0);   // quaternion normalised
  EXPECT_DOUBLE_EQ(st.q(m->q_adr[t] + 2), 3.0);
  EXPECT_DOUBLE_EQ(st.qd(m->v_adr[t] + 5), 6.0);
  EXPECT_DOUBLE_EQ(st.q(m->q_adr[m->joint_index("left_hip")]), 0.5);
  EXPECT_DOUBLE_EQ(st.q(m->q_adr[m->joint_index("right_hip")]), 0.0);
  auto throws_with = [&](const nlohmann::json& j, const std::string& what) {
    try {
      io::state_from_json(*m, j, "doc");
      ADD_FAILURE() << "no error for " << j.dump();
    } catch (const io::StateJsonError& e) {
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  };
  throws_with({{"q", {{"knee", 1.0}}}}, "q.knee: unknown joint");
  throws_with({{"q", {{"neck", 1.0}}}}, "fixed joint");
  throws_with({{"qd", {{"base_free", {1, 2, 3}}}}}, "expected 6 numbers");
  throws_with({{"q", {{"base_free", {0, 0, 0, 0, 0, 0, 0}}}}}, "quaternion is zero");
  throws_with({{"qdd", {}}}, "unknown section");
}

}  // namespace
}  // namespace haptree

// TinyXML 2.6 skips a multibyte character by its lead byte without checking what follows: a text ending
// in a lead byte made it read past the string (heap overflow, fuzz smoke run). The text is refused
// before any XML parsing, and well-formed UTF-8 (names, comments) still loads.
TEST(UrdfInput, TextThatIsNotUtf8IsRefusedBeforeTinyXmlReadsIt) {
  auto msg = [](const std::string& xml) {
    try {
      haptree::io::parse_urdf(xml, "t.urdf");
    } catch (const haptree::io::UrdfError& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  const std::string ok = "<robot name='r\xC3\xA9'><!-- \xE2\x82\xAC --><link name='a'><inertial><mass value='1'/>"
                         "<inertia ixx='1' ixy='0' ixz='0' iyy='1' iyz='0' izz='1'/></inertial></link></robot>";
  EXPECT_EQ(msg(ok).find("not UTF-8"), std::string::npos) << msg(ok);
  EXPECT_NE(msg("<robot name='r'><link name='a\xE0\xE0").find("t.urdf: not UTF-8 text (byte 29 is 0xe0)"),
            std::string::npos)
      << msg("<robot name='r'><link name='a\xE0\xE0");
  EXPECT_NE(msg(std::string("<robot name='r'>\xC0\xAF</robot>")).find("not UTF-8"), std::string::npos);   // overlong
  EXPECT_NE(msg(std::string("<robot name='r'>\xED\xA0\x80</robot>")).find("not UTF-8"), std::string::npos);   // surrogate
  EXPECT_NE(msg(std::string("<robot>\xF4\x90\x80\x80</robot>")).find("not UTF-8"), std::string::npos);   // > U+10FFFF
}

// urdfdom 3.0 hands a material's name and a malformed vector's text to printf as the format: "%s" in
// either crashed the parse (fuzz smoke run, SEGV in vfprintf). A '%' is now plain text: a good file
// with one loads, and a bad one is refused with urdfdom's reason, its '%' shown as '?'.
TEST(UrdfInput, PercentInTheFileIsNeverAPrintfFormat) {
  const std::string conversions(40, '%');   // "%%..." is harmless; "%s%n..." is what crashed
  std::string specs;
  for (int i = 0; i < 20; ++i) specs += "%s%n";
  const std::string body = "<link name='a'><inertial><mass value='1'/><inertia ixx='1' ixy='0' ixz='0' iyy='1' "
                           "iyz='0' izz='1'/></inertial><visual><geometry><box size='1 1 1'/></geometry>"
                           "<material name='" + specs + "'/></visual></link>"
                           "<link name='b'><inertial><mass value='2'/><inertia ixx='1' ixy='0' ixz='0' iyy='1' "
                           "iyz='0' izz='1'/></inertial></link>";
  auto urdf = [&](const std::string& xyz) {
    return "<robot name='r" + conversions + "'><material name='" + specs + "'><color rgba='1 0 0 1'/></material>" +
           body + "<joint name='j' type='continuous'><parent link='a'/><child link='b'/><origin xyz='" + xyz +
           "'/><axis xyz='0 0 1'/></joint></robot>";
  };
  const auto m = haptree::io::parse_urdf(urdf("0 0 1"), "t.urdf");
  ASSERT_NE(m, nullptr);
  EXPECT_EQ(m->nbodies, 3);   // the world and the two links
  EXPECT_EQ(m->nv, 1);
  try {
    haptree::io::parse_urdf(urdf(specs + " 0 0"), "t.urdf");
    ADD_FAILURE() << "a malformed origin was accepted";
  } catch (const haptree::io::UrdfError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("t.urdf: URDF parse error"), std::string::npos) << what;
    EXPECT_NE(what.find("?s?n?s?n"), std::string::npos) << what;   // urdfdom's text, the value in it
    EXPECT_NE(what.find("each '%' of the file shown as '?'"), std::string::npos) << what;
  }
}
