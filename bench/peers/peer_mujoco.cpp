// MuJoCo translation: one MJCF body per haptree body, hinge joint at the body origin, inertial with
// fullinertia (about the COM, body frame), contacts/constraints disabled, zero armature/damping.
#include "bench/peers/peer_engine.hpp"

#include <mujoco/mujoco.h>

#include <Eigen/Eigenvalues>
#include <cstdio>
#include <cstring>
#include <sstream>
#include <stdexcept>

namespace haptree::peers {

namespace {

std::string num(double x) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.17g", x);
  return buf;
}
std::string vec(const Vec3& v) { return num(v.x()) + " " + num(v.y()) + " " + num(v.z()); }

// MuJoCo 2.2.2 parses MJCF with tinyxml2, which rejects element nesting deeper than 100, so a
// chain of more than ~95 bodies cannot be written as one file. <include> files are parsed one by
// one and spliced into the tree afterwards, so every kMaxDepth levels the children of a body go
// into their own file "part<k>.xml" that the body includes.
constexpr int kMaxDepth = 60;
using XmlFiles = std::vector<std::pair<std::string, std::string>>;   // (name, text)

void emit_body(const Model& m, int k, bool diag, int depth, std::ostringstream& os, XmlFiles& files);

void emit_children(const Model& m, int k, bool diag, int depth, std::ostringstream& os,
                   XmlFiles& files) {
  if (m.children[k].empty()) return;
  if (depth < kMaxDepth) {
    for (int c : m.children[k]) emit_body(m, c, diag, depth + 1, os, files);
    return;
  }
  std::ostringstream part;
  part << "<mujoco>\n";
  for (int c : m.children[k]) emit_body(m, c, diag, 1, part, files);
  part << "</mujoco>\n";
  const std::string name = "part" + std::to_string(k) + ".xml";
  files.emplace_back(name, part.str());
  os << "<include file=\"" << name << "\"/>\n";
}

void emit_body(const Model& m, int k, bool diag, int depth, std::ostringstream& os, XmlFiles& files) {
  const Quat qr(m.joint_rotation[k]);
  os << "<body name=\"b" << k << "\" pos=\"" << vec(m.joint_offset[k]) << "\" quat=\""
     << num(qr.w()) << " " << num(qr.x()) << " " << num(qr.y()) << " " << num(qr.z()) << "\">\n";
  const Mat3& I = m.inertia[k];
  if (!diag) {
    os << "<inertial pos=\"" << vec(m.com[k]) << "\" mass=\"" << num(m.mass[k])
       << "\" fullinertia=\"" << num(I(0, 0)) << " " << num(I(1, 1)) << " " << num(I(2, 2)) << " "
       << num(I(0, 1)) << " " << num(I(0, 2)) << " " << num(I(1, 2)) << "\"/>\n";
  } else {
    // Principal axes computed here in double (Eigen) instead of by MuJoCo's compiler.
    Eigen::SelfAdjointEigenSolver<Mat3> es(0.5 * (I + I.transpose()));
    Mat3 Q = es.eigenvectors();
    if (Q.determinant() < 0) Q.col(2) = -Q.col(2);
    const Quat qi(Q);
    os << "<inertial pos=\"" << vec(m.com[k]) << "\" mass=\"" << num(m.mass[k]) << "\" quat=\""
       << num(qi.w()) << " " << num(qi.x()) << " " << num(qi.y()) << " " << num(qi.z())
       << "\" diaginertia=\"" << vec(es.eigenvalues()) << "\"/>\n";
  }
  switch (m.joint_type[k]) {
    case JointType::kRevolute:
      os << "<joint name=\"j" << k << "\" type=\"hinge\" pos=\"0 0 0\" axis=\""
         << vec(m.joint_axis[k]) << "\" armature=\"0\" damping=\"0\" limited=\"false\"/>\n";
      break;
    case JointType::kFixed: break;   // a body without a joint is welded to its parent
    default:
      throw std::runtime_error("mujoco peer: joint " + std::to_string(k) + " of type " +
                               joint_type_name(m.joint_type[k]) + " is not translated");
  }
  emit_children(m, k, diag, depth, os, files);
  os << "</body>\n";
}

class MujocoEngine final : public PeerEngine {
 public:
  MujocoEngine(const Model& model, bool diag) : hm_(model), diag_(diag) {
    const auto files = mujoco_xml(model, diag);
    auto vfs = std::make_unique<mjVFS>();   // large struct: keep it off the stack
    mj_defaultVFS(vfs.get());
    for (const auto& [fname, text] : files) {
      if (mj_makeEmptyFileVFS(vfs.get(), fname.c_str(), static_cast<int>(text.size())) != 0)
        throw std::runtime_error("mujoco peer: cannot create VFS file " + fname);
      const int id = mj_findFileVFS(vfs.get(), fname.c_str());
      std::memcpy(vfs->filedata[id], text.data(), text.size());
    }
    char err[1000] = "";
    m_ = mj_loadXML("haptree.xml", vfs.get(), err, sizeof err);
    mj_deleteVFS(vfs.get());
    if (!m_) throw std::runtime_error(std::string("mujoco peer: mj_loadXML: ") + err);
    d_ = mj_makeData(m_);
    qadr_.assign(model.nv, -1);
    dadr_.assign(model.nv, -1);
    hq_.assign(model.nv, -1);
    for (int k = 1; k < model.nbodies; ++k) {
      if (model.v_num[k] == 0) continue;
      const int j = mj_name2id(m_, mjOBJ_JOINT, ("j" + std::to_string(k)).c_str());
      if (j < 0) throw std::runtime_error("mujoco peer: joint j" + std::to_string(k) + " missing");
      qadr_[model.v_adr[k]] = m_->jnt_qposadr[j];
      dadr_[model.v_adr[k]] = m_->jnt_dofadr[j];
      hq_[model.v_adr[k]] = model.q_adr[k];
    }
    if (m_->nv != model.nv) throw std::runtime_error("mujoco peer: nv mismatch");
    qdd_.setZero(model.nv);
  }
  ~MujocoEngine() override {
    mj_deleteData(d_);
    mj_deleteModel(m_);
  }
  std::string name() const override { return diag_ ? "mujoco_diaginertia" : "mujoco"; }
  std::string timed_call() const override {
    return "copy qpos/qvel/qfrc_applied + mj_forward (contact, constraint, passive disabled)";
  }
  void compute(const State& st) override {
    const int nv = hm_.nv;
    for (int i = 0; i < nv; ++i) {
      d_->qpos[qadr_[i]] = st.q(hq_[i]);
      d_->qvel[dadr_[i]] = st.qd(i);
      d_->qfrc_applied[dadr_[i]] = st.tau(i);
    }
    mj_forward(m_, d_);
    for (int i = 0; i < nv; ++i) qdd_(i) = d_->qacc[dadr_[i]];
  }
  const Eigen::VectorXd& qdd() const override { return qdd_; }

 private:
  const Model& hm_;
  bool diag_;
  mjModel* m_ = nullptr;
  mjData* d_ = nullptr;
  std::vector<int> qadr_, dadr_, hq_;   // per haptree DOF
  Eigen::VectorXd qdd_;
};

}  // namespace

std::vector<std::pair<std::string, std::string>> mujoco_xml(const Model& model, bool diag) {
  for (int k = 1; k < model.nbodies; ++k)
    if (model.joint_type[k] != JointType::kRevolute && model.joint_type[k] != JointType::kFixed)
      throw std::runtime_error("mujoco peer: only revolute/fixed joints are translated (joint " +
                               std::to_string(k) + ")");
  std::ostringstream os;
  os << "<mujoco model=\"haptree\">\n<compiler angle=\"radian\" inertiafromgeom=\"false\" "
        "boundmass=\"0\" boundinertia=\"0\"/>\n"
     << "<option gravity=\"" << vec(model.gravity) << "\" timestep=\"0.001\">\n"
     << "<flag contact=\"disable\" constraint=\"disable\" passive=\"disable\" "
        "equality=\"disable\" limit=\"disable\" frictionloss=\"disable\"/>\n</option>\n"
     << "<worldbody>\n";
  XmlFiles files;
  files.emplace_back("haptree.xml", "");
  for (int c : model.children[0]) emit_body(model, c, diag, 1, os, files);
  os << "</worldbody>\n</mujoco>\n";
  files[0].second = os.str();
  return files;
}

std::unique_ptr<PeerEngine> make_mujoco_engine(const Model& model, bool diaginertia) {
  return std::make_unique<MujocoEngine>(model, diaginertia);
}

}  // namespace haptree::peers
