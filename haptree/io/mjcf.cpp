#include "haptree/io/mjcf.hpp"

#include <cstdio>
#include <sstream>
#include <vector>

#include <Eigen/Eigenvalues>

namespace haptree::io {

namespace {

std::string num(double x) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.17g", x == 0 ? 0.0 : x);
  return buf;
}
std::string vec(const Vec3& v) { return num(v.x()) + " " + num(v.y()) + " " + num(v.z()); }
std::string quat(const Mat3& R) {
  Quat q(R);
  q.normalize();
  return num(q.w()) + " " + num(q.x()) + " " + num(q.y()) + " " + num(q.z());
}
std::string esc(const std::string& s) {
  std::string o;
  for (char c : s) {
    switch (c) {
      case '&': o += "&amp;"; break;
      case '<': o += "&lt;"; break;
      case '>': o += "&gt;"; break;
      case '"': o += "&quot;"; break;
      default: o += c;
    }
  }
  return o;
}

// Opening tag, joint and inertial of body k (its children and closing tag follow).
void open_body(const Model& m, int k, int depth, std::ostringstream& os) {
  const std::string ind(2 * depth, ' ');
  os << ind << "<body name=\"" << esc(m.body_name[k]) << "\" pos=\"" << vec(m.joint_offset[k])
     << "\" quat=\"" << quat(m.joint_rotation[k]) << "\">\n";
  const char* type = nullptr;
  switch (m.joint_type[k]) {
    case JointType::kRevolute: type = "hinge"; break;
    case JointType::kPrismatic: type = "slide"; break;
    case JointType::kSpherical: type = "ball"; break;
    case JointType::kFree:
      if (m.parent[k] != 0)
        throw ModelError("to_mjcf: free joint '" + m.joint_name[k] +
                         "' is not on a child of the ground (MuJoCo allows free joints only there)");
      type = "free";
      break;
    case JointType::kFixed: break;
  }
  if (type) {
    os << ind << "  <joint name=\"" << esc(m.joint_name[k]) << "\" type=\"" << type
       << "\" pos=\"0 0 0\"";
    if (m.joint_type[k] == JointType::kRevolute || m.joint_type[k] == JointType::kPrismatic)
      os << " axis=\"" << vec(m.joint_axis[k]) << "\"";
    os << " damping=\"0\" armature=\"0\" stiffness=\"0\" limited=\"false\"/>\n";
  }
  // Principal axes, right-handed.
  Eigen::SelfAdjointEigenSolver<Mat3> es(m.inertia[k]);
  Mat3 V = es.eigenvectors();
  if (V.determinant() < 0) V.col(2) = -V.col(2);
  os << ind << "  <inertial pos=\"" << vec(m.com[k]) << "\" quat=\"" << quat(V)
     << "\" diaginertia=\"" << vec(es.eigenvalues()) << "\" mass=\"" << num(m.mass[k]) << "\"/>\n";
}

// Depth-first with an explicit stack (no recursion as deep as the model). An entry with close set writes
// the closing tag of its body once its subtree is done.
void write_body(const Model& m, int root, int depth, std::ostringstream& os) {
  struct Item {
    int k, depth;
    bool close;
  };
  std::vector<Item> stack{{root, depth, false}};
  while (!stack.empty()) {
    const Item it = stack.back();
    stack.pop_back();
    if (it.close) {
      os << std::string(2 * it.depth, ' ') << "</body>\n";
      continue;
    }
    open_body(m, it.k, it.depth, os);
    stack.push_back({it.k, it.depth, true});
    const auto& ch = m.children[it.k];
    for (auto c = ch.rbegin(); c != ch.rend(); ++c) stack.push_back({*c, it.depth + 1, false});
  }
}

}  // namespace

std::string to_mjcf(const Model& m, const MjcfOptions& o) {
  std::ostringstream os;
  os << "<mujoco model=\"" << esc(o.model_name) << "\">\n"
     << "  <compiler angle=\"radian\" inertiafromgeom=\"false\"/>\n"
     << "  <option timestep=\"" << num(o.timestep) << "\" gravity=\"" << vec(m.gravity) << "\">\n"
     << "    <flag contact=\"disable\" constraint=\"disable\"/>\n"
     << "  </option>\n"
     << "  <worldbody>\n";
  for (int c : m.children[0]) write_body(m, c, 2, os);
  os << "  </worldbody>\n</mujoco>\n";
  return os.str();
}

}  // namespace haptree::io
