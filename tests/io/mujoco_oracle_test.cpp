// MuJoCo (libmujoco-dev) as an external oracle: the same model is compiled by MuJoCo from the MJCF
// text io::to_mjcf writes (or from the URDF file itself), the same state is set, mj_forward runs
// with contacts and constraints disabled, and MuJoCo's qacc is compared with haptree's DCA q̈.
// Conventions (see haptree/io/mjcf.hpp): hinge/slide/ball coordinates are identical; free joints
// are converted (MuJoCo: world-frame linear velocity of the body origin, local angular velocity).
#include <gtest/gtest.h>

#include <algorithm>
#include <cstring>
#include <memory>
#include <string>

#include <mujoco/mujoco.h>

#include "haptree/dca.hpp"
#include "haptree/io/mjcf.hpp"
#include "haptree/io/urdf.hpp"
#include "haptree/scenes.hpp"
#include "tests/support/oracle.hpp"

namespace haptree {
namespace {

struct MjModelDeleter {
  void operator()(mjModel* m) const { mj_deleteModel(m); }
};
struct MjDataDeleter {
  void operator()(mjData* d) const { mj_deleteData(d); }
};
using MjModelPtr = std::unique_ptr<mjModel, MjModelDeleter>;
using MjDataPtr = std::unique_ptr<mjData, MjDataDeleter>;

MjModelPtr compile_xml_text(const std::string& xml) {
  auto vfs = std::make_unique<mjVFS>();
  mj_defaultVFS(vfs.get());
  const char* fname = "haptree_model.xml";
  if (mj_makeEmptyFileVFS(vfs.get(), fname, static_cast<int>(xml.size())) != 0)
    throw std::runtime_error("mujoco VFS: cannot make file");
  const int idx = mj_findFileVFS(vfs.get(), fname);
  std::memcpy(vfs->filedata[idx], xml.data(), xml.size());
  char err[1000] = "";
  mjModel* m = mj_loadXML(fname, vfs.get(), err, sizeof err);
  mj_deleteVFS(vfs.get());
  if (!m) throw std::runtime_error(std::string("mujoco: ") + err);
  return MjModelPtr(m);
}

MjModelPtr compile_file(const std::string& path) {
  char err[1000] = "";
  mjModel* m = mj_loadXML(path.c_str(), nullptr, err, sizeof err);
  if (!m) throw std::runtime_error(std::string("mujoco: ") + path + ": " + err);
  // URDF cannot switch these off in the file; no contacts (no geoms) and no limits are wanted.
  m->opt.disableflags |= mjDSBL_CONTACT | mjDSBL_CONSTRAINT;
  return MjModelPtr(m);
}

// Runs MuJoCo on haptree's state and returns its qacc in haptree's coordinates (layout and
// free-joint convention of `model`). Joints are matched by name; bodies for f_ext by name.
Eigen::VectorXd mujoco_qdd(const Model& model, const State& st, const mjModel* mm,
                           bool use_f_ext = true) {
  MjDataPtr md(mj_makeData(mm));
  Data hd(model);
  forward_kinematics(model, hd, st.q);
  mju_zero(md->qpos, mm->nq);
  mju_zero(md->qvel, mm->nv);
  mju_zero(md->qfrc_applied, mm->nv);
  mju_zero(md->xfrc_applied, 6 * mm->nbody);
  std::vector<int> jid(model.nbodies, -1);
  int matched_dofs = 0;
  for (int k = 1; k < model.nbodies; ++k) {
    if (model.v_num[k] == 0) continue;
    const int j = mj_name2id(mm, mjOBJ_JOINT, model.joint_name[k].c_str());
    if (j < 0) throw std::runtime_error("mujoco has no joint '" + model.joint_name[k] + "'");
    jid[k] = j;
    const int qa = mm->jnt_qposadr[j], va = mm->jnt_dofadr[j];
    const int hq = model.q_adr[k], hv = model.v_adr[k];
    matched_dofs += model.v_num[k];
    switch (model.joint_type[k]) {
      case JointType::kRevolute:
      case JointType::kPrismatic:
      case JointType::kSpherical:
        for (int i = 0; i < joint_nq(model.joint_type[k]); ++i) md->qpos[qa + i] = st.q(hq + i);
        for (int i = 0; i < model.v_num[k]; ++i) {
          md->qvel[va + i] = st.qd(hv + i);
          md->qfrc_applied[va + i] = st.tau(hv + i);
        }
        break;
      case JointType::kFree: {
        EXPECT_EQ(mm->jnt_type[j], mjJNT_FREE);
        const Mat3& R = hd.R[k];
        const Quat Q(R);
        for (int i = 0; i < 3; ++i) md->qpos[qa + i] = hd.r[k](i);
        md->qpos[qa + 3] = Q.w();
        md->qpos[qa + 4] = Q.x();
        md->qpos[qa + 5] = Q.y();
        md->qpos[qa + 6] = Q.z();
        const Vec3 lin = R * st.qd.segment<3>(hv + 3);
        const Vec3 force = R * st.tau.segment<3>(hv + 3);
        for (int i = 0; i < 3; ++i) {
          md->qvel[va + i] = lin(i);
          md->qvel[va + 3 + i] = st.qd(hv + i);
          md->qfrc_applied[va + i] = force(i);
          md->qfrc_applied[va + 3 + i] = st.tau(hv + i);
        }
        break;
      }
      case JointType::kFixed: break;
    }
  }
  EXPECT_EQ(matched_dofs, mm->nv) << "MuJoCo has DOFs haptree does not";
  if (use_f_ext) {
    mj_kinematics(mm, md.get());   // body COMs (xipos) for the force transfer
    for (int k = 1; k < model.nbodies; ++k) {
      const Vec6& f = st.f_ext[k];
      if (f.isZero()) continue;
      const int b = mj_name2id(mm, mjOBJ_BODY, model.body_name[k].c_str());
      if (b < 0) throw std::runtime_error("mujoco has no body '" + model.body_name[k] + "'");
      // [moment at r_k; force] -> [force; moment about MuJoCo's body COM c]: n_c = n + (r_k − c) × f.
      // (MuJoCo's COM, since its URDF compiler fuses fixed links into their parent.)
      const Vec3 F = f.tail<3>();
      const Vec3 c(md->xipos[3 * b], md->xipos[3 * b + 1], md->xipos[3 * b + 2]);
      const Vec3 n_c = f.head<3>() + (hd.r[k] - c).cross(F);
      for (int i = 0; i < 3; ++i) {
        md->xfrc_applied[6 * b + i] = F(i);
        md->xfrc_applied[6 * b + 3 + i] = n_c(i);
      }
    }
  }
  mj_forward(mm, md.get());
  Eigen::VectorXd qdd = Eigen::VectorXd::Zero(model.nv);
  for (int k = 1; k < model.nbodies; ++k) {
    if (jid[k] < 0) continue;
    const int va = mm->jnt_dofadr[jid[k]], hv = model.v_adr[k];
    if (model.joint_type[k] == JointType::kFree) {
      const Mat3& R = hd.R[k];
      const Vec3 acc(md->qacc[va], md->qacc[va + 1], md->qacc[va + 2]);
      const Vec3 w = st.qd.segment<3>(hv), v = st.qd.segment<3>(hv + 3);
      for (int i = 0; i < 3; ++i) qdd(hv + i) = md->qacc[va + 3 + i];
      qdd.segment<3>(hv + 3) = R.transpose() * acc - w.cross(v);
    } else {
      for (int i = 0; i < model.v_num[k]; ++i) qdd(hv + i) = md->qacc[va + i];
    }
  }
  return qdd;
}

int kinematic_depth(const Model& m) {
  std::vector<int> depth(m.nbodies, 0);
  int mx = 0;
  for (int k = 1; k < m.nbodies; ++k) mx = std::max(mx, depth[k] = depth[m.parent[k]] + 1);
  return mx;
}

struct Result {
  double vs_mujoco, vs_oracle, mujoco_vs_oracle, bound, mujoco_bound;
};

// Tolerance: haptree's DCA is within B = c·n·ε·κ(H)·cancel of the long-double oracle
// (tests/support/oracle.hpp, c = kBoundC). MuJoCo (composite-rigid-body H, sparse LDLᵀ in double)
// is backward stable too, with a constant of the same order: H and the bias forces are sums of
// O(depth) products, each rounding a relative ε, and LDLᵀ of an SPD H is backward stable
// (Higham, Thm 10.3), so its error is ≲ n·ε·κ(H)·cancel as well (the MJCF text carries every
// double exactly, %.17g; MuJoCo's diagonalisation of each inertia is one more relative-ε
// perturbation of the data). Each is therefore asserted within B of the oracle, and the two within
// 2B of each other. MuJoCo's model is not quite the same data, though: its compiler diagonalises
// every body inertia with mju_eig3, a Jacobi iteration that stops when the off-diagonal entries
// are below eigEPS = 1000·mjMINVAL = 1e-12 (absolute, kg·m²). That perturbs each body's rotational
// inertia by η ≤ 1e-12, so H by ‖δH‖ ≤ nb·depth·η (each body's angular Jacobian has ≤ depth unit
// columns) and q̈ by ≤ κ(H)·‖δH‖/λ_max(H) relative, the bias forces likewise (factor 2);
// λ_max ≥ max_i H_ii keeps it an upper bound. So MuJoCo is held to B + that data term (measured on
// arm.urdf: 4.2e-12 against B = 9.3e-13). A real error (a wrong term, a wrong convention)
// moves q̈ by O(1) relative, far above these wherever κ(H) ≪ 1/(n·ε).

Result compare(const Model& model, const State& st, const mjModel* mm, bool use_f_ext = true) {
  Data d(model);
  const Eigen::VectorXd qdd = forward_dynamics(model, d, st);
  const Eigen::VectorXd mj = mujoco_qdd(model, st, mm, use_f_ext);
  const auto orc = testing::oracle_forward_dynamics(model, st);
  const double B = testing::qdd_error_bound(orc, st, testing::kBoundC);
  constexpr double kEigEps = 1e-12;   // MuJoCo's eigEPS (engine_util_solve.c)
  double hmax = 0;
  for (int i = 0; i < orc.H.rows(); ++i) hmax = std::max(hmax, static_cast<double>(orc.H(i, i)));
  const double data = 2 * testing::mass_matrix_condition(orc) * (model.nbodies - 1) *
                      kinematic_depth(model) * kEigEps / std::max(hmax, 1e-300);
  return {testing::rel_err(qdd, mj), testing::rel_err(qdd, orc.qdd), testing::rel_err(mj, orc.qdd),
          B, B + data};
}

// Largest err/B seen (printed by the last test; 1 would be a failure).
double worst_ratio = 0;

void check(const Result& r, const std::string& what) {
  EXPECT_LE(r.vs_oracle, r.bound) << what;
  EXPECT_LE(r.mujoco_vs_oracle, r.mujoco_bound) << what << " (MuJoCo itself)";
  EXPECT_LE(r.vs_mujoco, r.bound + r.mujoco_bound) << what << " (haptree vs oracle " << r.vs_oracle
                                      << ", mujoco vs oracle " << r.mujoco_vs_oracle << ")";
  worst_ratio = std::max({worst_ratio, r.vs_oracle / r.bound, r.mujoco_vs_oracle / r.mujoco_bound,
                          r.vs_mujoco / (r.bound + r.mujoco_bound)});
}

void check_scene(const std::string& name, const SceneOptions& o, int nstates, int max_depth = 16) {
  auto model = make_scene(name, o);
  const int depth = kinematic_depth(*model);
  EXPECT_LE(depth, max_depth) << name;
  auto mm = compile_xml_text(io::to_mjcf(*model));
  ASSERT_EQ(mm->nv, model->nv);
  for (int s = 0; s < nstates; ++s) {
    const State st = testing::random_state(*model, 1000 + s);
    const Result r = compare(*model, st, mm.get());
    check(r, name + " n=" + std::to_string(o.n) + " seed=" + std::to_string(o.seed) + " state " +
                 std::to_string(s));
    if (s == 0)
      std::printf("  %-12s n=%-5d depth=%-3d nv=%-5d |haptree-mujoco|/|mujoco| = %.2e  "
                  "(haptree-oracle %.2e, mujoco-oracle %.2e, B %.2e)\n",
                  name.c_str(), model->nbodies - 1, depth, model->nv, r.vs_mujoco, r.vs_oracle,
                  r.mujoco_vs_oracle, r.bound);
  }
}

TEST(MuJoCoOracle, Version) {
  // The comparison was written against MuJoCo 2.2.x (Debian 12's libmujoco-dev).
  EXPECT_GE(mj_version(), 220);
  std::printf("  MuJoCo %s\n", mj_versionString());
}

TEST(MuJoCoOracle, Chains) {
  for (int n : {1, 2, 5, 16})
    for (std::uint32_t seed : {0u, 1u, 2u}) {
      SceneOptions o;
      o.n = n;
      o.seed = seed;
      check_scene("chain", o, 3);
    }
}

TEST(MuJoCoOracle, BinaryTrees) {
  for (int n : {3, 15, 63, 1023})
    for (std::uint32_t seed : {0u, 3u}) {
      SceneOptions o;
      o.n = n;
      o.seed = seed;
      check_scene("binary_tree", o, 2);
    }
}

TEST(MuJoCoOracle, RandomTreesMixedJoints) {
  for (int n : {10, 40, 200})
    for (std::uint32_t seed : {1u, 5u, 9u}) {
      SceneOptions o;
      o.n = n;
      o.seed = seed;
      o.mixed_joints = true;
      check_scene("random_tree", o, 3);
    }
}

TEST(MuJoCoOracle, FreeRootRandomTrees) {
  for (int n : {1, 12, 60})
    for (std::uint32_t seed : {2u, 4u}) {
      SceneOptions o;
      o.n = n;
      o.seed = seed;
      o.mixed_joints = true;
      o.free_root = true;
      check_scene("random_tree", o, 3);
    }
}

TEST(MuJoCoOracle, Star) {
  SceneOptions o;
  o.n = 64;
  o.seed = 3;
  check_scene("star", o, 2);
}

TEST(MuJoCoOracle, NonDefaultGravity) {
  SceneOptions o;
  o.n = 30;
  o.seed = 11;
  o.mixed_joints = true;
  Model m = *make_scene("random_tree", o);
  m.gravity = Vec3(1.5, -2.0, -4.0);
  auto mm = compile_xml_text(io::to_mjcf(m));
  for (int s = 0; s < 3; ++s) {
    check(compare(m, testing::random_state(m, 300 + s), mm.get()), "state " + std::to_string(s));
  }
}

// The protein-like tree (backbone of 343 bodies) cannot be compared: its MJCF nesting exceeds
// MuJoCo 2.2's XML parser depth limit (tinyxml2 XML_ELEMENT_DEPTH_EXCEEDED). It is checked against
// the long-double oracle in tests/core instead.

// The URDF loader against MuJoCo's own URDF compiler (an independent reading of the same file).
TEST(MuJoCoOracle, UrdfArm) {
  const std::string path = std::string(HAPTREE_URDF_DIR) + "/arm.urdf";
  auto model = io::load_urdf(path);
  auto mm = compile_file(path);
  ASSERT_EQ(mm->nv, model->nv);
  for (int s = 0; s < 4; ++s) {
    State st = testing::random_state(*model, 50 + s);
    // External forces only on bodies MuJoCo keeps (fixed links are fused into their parent).
    for (int k = 0; k < model->nbodies; ++k)
      if (mj_name2id(mm.get(), mjOBJ_BODY, model->body_name[k].c_str()) < 0) st.f_ext[k].setZero();
    check(compare(*model, st, mm.get()), path + " state " + std::to_string(s));
  }
}

TEST(MuJoCoOracle, UrdfFloating) {
  const std::string path = std::string(HAPTREE_URDF_DIR) + "/floating.urdf";
  auto model = io::load_urdf(path);
  auto mm = compile_file(path);
  ASSERT_EQ(mm->nv, model->nv);
  for (int s = 0; s < 4; ++s) {
    State st = testing::random_state(*model, 70 + s);
    for (int k = 0; k < model->nbodies; ++k)
      if (mj_name2id(mm.get(), mjOBJ_BODY, model->body_name[k].c_str()) < 0) st.f_ext[k].setZero();
    check(compare(*model, st, mm.get()), path + " state " + std::to_string(s));
  }
}

TEST(MuJoCoOracle, WorstRatio) {
  std::printf("  worst err/bound (haptree and MuJoCo vs oracle, haptree vs MuJoCo): %.3g\n",
              worst_ratio);
}

}  // namespace
}  // namespace haptree
