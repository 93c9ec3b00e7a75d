#include "haptree/io/urdf.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <sstream>
#include <vector>

#include <console_bridge/console.h>
#include <urdf_parser/urdf_parser.h>

#include <Eigen/Eigenvalues>

namespace haptree::io {

namespace {

// Offset of the first byte that is not well-formed UTF-8 (RFC 3629), or npos. TinyXML 2.6 skips a
// multibyte character by its lead byte's length without looking at what follows, so a lead byte at the
// end of the text made it read past the terminator (heap overflow found by the fuzz smoke run).
std::string fmt_hex(unsigned char c) {
  const char* d = "0123456789abcdef";
  return {d[c >> 4], d[c & 15]};
}

size_t utf8_error(const std::string& s) {
  const auto* p = reinterpret_cast<const unsigned char*>(s.data());
  const size_t n = s.size();
  for (size_t i = 0; i < n;) {
    const unsigned c = p[i];
    if (c < 0x80) { ++i; continue; }
    size_t len = 0;
    unsigned lo = 0x80, hi = 0xBF;   // allowed range of the second byte
    if (c >= 0xC2 && c <= 0xDF) len = 2;
    else if (c >= 0xE0 && c <= 0xEF) { len = 3; if (c == 0xE0) lo = 0xA0; if (c == 0xED) hi = 0x9F; }
    else if (c >= 0xF0 && c <= 0xF4) { len = 4; if (c == 0xF0) lo = 0x90; if (c == 0xF4) hi = 0x8F; }
    else return i;
    if (i + len > n || p[i + 1] < lo || p[i + 1] > hi) return i;
    for (size_t k = 2; k < len; ++k)
      if (p[i + k] < 0x80 || p[i + k] > 0xBF) return i;
    i += len;
  }
  return std::string::npos;
}


// Captures urdfdom's console_bridge messages so a parse failure becomes one exception line
// instead of text on stderr.
class CaptureHandler : public console_bridge::OutputHandler {
 public:
  void log(const std::string& text, console_bridge::LogLevel level, const char*, int) override {
    if (level >= console_bridge::CONSOLE_BRIDGE_LOG_ERROR && first_error.empty()) first_error = text;
  }
  std::string first_error;
};

struct ScopedCapture {
  CaptureHandler handler;
  // quiet: no handler at all, so console_bridge formats no message (see parse_with_urdfdom).
  explicit ScopedCapture(bool quiet) {
    if (quiet)
      console_bridge::noOutputHandler();
    else
      console_bridge::useOutputHandler(&handler);
  }
  ~ScopedCapture() { console_bridge::restorePreviousOutputHandler(); }
};

// urdfdom's parseURDF; on failure `err` is its first error message (or the exception's text).
urdf::ModelInterfaceSharedPtr urdfdom_parse(const std::string& xml, bool quiet, std::string& err) {
  ScopedCapture capture(quiet);
  urdf::ModelInterfaceSharedPtr urdf;
  try {
    urdf = urdf::parseURDF(xml);
  } catch (const std::exception& e) {
    err = e.what();
  }
  if (err.empty()) err = capture.handler.first_error;
  return urdf;
}

// urdfdom 3.0 passes some of the file's own text to printf as the format (a material's name, the
// text of a malformed vector: link.cpp, pose.cpp), so a '%' there is read as a conversion and a
// "%s" crashes the parse (found by fuzz_urdf). A text with a '%' is parsed with no output handler,
// so nothing is formatted; only if that parse fails is a copy with each '%' as '?' parsed, with
// messages, to say why (the copy fails the same way: '%' is in no URDF keyword or number).
urdf::ModelInterfaceSharedPtr parse_with_urdfdom(const std::string& xml, std::string& err) {
  if (xml.find('%') == std::string::npos) return urdfdom_parse(xml, false, err);
  std::string ignored;
  if (auto urdf = urdfdom_parse(xml, true, ignored)) return urdf;
  std::string safe = xml;
  std::replace(safe.begin(), safe.end(), '%', '?');
  urdfdom_parse(safe, false, err);
  if (!err.empty()) err += " (each '%' of the file shown as '?')";
  return nullptr;
}

std::string one_line(std::string s) {
  for (char& c : s)
    if (c == '\n' || c == '\r') c = ' ';
  while (!s.empty() && s.back() == ' ') s.pop_back();
  return s;
}

Mat3 to_mat(const urdf::Rotation& r) {
  return Quat(r.w, r.x, r.y, r.z).normalized().toRotationMatrix();
}
Vec3 to_vec(const urdf::Vector3& v) { return Vec3(v.x, v.y, v.z); }

// Mass properties in one body frame.
struct MassProps {
  double mass = 0;
  Vec3 com = Vec3::Zero();
  Mat3 inertia = Mat3::Zero();   // about the COM
};

Mat3 parallel_axis(double m, const Vec3& d) {
  return m * (d.squaredNorm() * Mat3::Identity() - d * d.transpose());
}

void combine(MassProps& acc, const MassProps& add) {
  if (add.mass <= 0) return;
  const double m = acc.mass + add.mass;
  const Vec3 c = (acc.mass * acc.com + add.mass * add.com) / m;
  acc.inertia = acc.inertia + parallel_axis(acc.mass, acc.com - c) + add.inertia +
                parallel_axis(add.mass, add.com - c);
  acc.com = c;
  acc.mass = m;
}

struct BodyRec {
  std::string name, joint_name;
  int parent;   // index into recs; -1 = ground
  JointType type;
  Vec3 offset;
  Mat3 rotation;
  Vec3 axis;
  MassProps mp;
};

class Converter {
 public:
  Converter(const std::string& source, const UrdfOptions& o) : src_(source), opt_(o) {}

  std::shared_ptr<const Model> run(const urdf::ModelInterface& urdf) {
    const auto root = urdf.getRoot();
    if (!root) fail("robot", urdf.getName(), "no root link");
    if (root->name == "world") {
      if (opt_.floating_base)
        fail("link", "world", "floating_base is set but the root link is \"world\": declare a "
                              "floating joint from world instead");
      // The ground itself: its children hang from body -1.
      std::vector<Pending> stack;
      push_children(*root, -1, Mat3::Identity(), Vec3::Zero(), stack);
      while (!stack.empty()) {
        Pending w = std::move(stack.back());
        stack.pop_back();
        attach(std::move(w));
      }
    } else {
      const JointType t = opt_.floating_base ? JointType::kFree : JointType::kFixed;
      attach(Pending{root.get(), opt_.root_joint_name, "root", t, -1, Mat3::Identity(), Vec3::Zero(), Vec3::UnitZ()});
    }
    if (recs_.empty()) fail("robot", urdf.getName(), "no body with mass is attached to the ground");
    ModelBuilder b;
    b.set_gravity(opt_.gravity);
    for (size_t i = 0; i < recs_.size(); ++i) {
      const BodyRec& r = recs_[i];
      try {
        b.add_body(r.name, r.parent + 1, r.type, r.offset, r.rotation, r.axis, r.mp.mass, r.mp.com,
                   r.mp.inertia, r.joint_name);
      } catch (const ModelError& e) {
        fail("link", r.name, e.what());
      }
    }
    try {
      return b.build(opt_.build);
    } catch (const ModelError& e) {
      throw UrdfError(src_ + ": " + one_line(e.what()));
    }
  }

 private:
  [[noreturn]] void fail(const std::string& element, const std::string& name,
                         const std::string& what) const {
    throw UrdfError(src_ + ": " + element + " '" + name + "': " + one_line(what));
  }

  MassProps link_mass(const urdf::Link& link) const {
    MassProps mp;
    if (!link.inertial) return mp;
    const urdf::Inertial& in = *link.inertial;
    if (!std::isfinite(in.mass) || in.mass < 0)
      fail("link", link.name, "<inertial><mass> must be finite and non-negative, got " +
                                  std::to_string(in.mass));
    if (in.mass == 0) return mp;
    Mat3 I;
    I << in.ixx, in.ixy, in.ixz, in.ixy, in.iyy, in.iyz, in.ixz, in.iyz, in.izz;
    if (!I.allFinite()) fail("link", link.name, "<inertial><inertia> is not finite");
    Eigen::SelfAdjointEigenSolver<Mat3> es(I);
    const Vec3 ev = es.eigenvalues();
    if (ev(0) <= 1e-14 * std::max(1.0, ev(2)) || ev(0) + ev(1) < ev(2) * (1 - 1e-9)) {
      std::ostringstream os;
      os << "<inertial><inertia> must be positive definite and satisfy the triangle inequality "
            "(principal moments "
         << ev(0) << ", " << ev(1) << ", " << ev(2) << ")";
      fail("link", link.name, os.str());
    }
    const Mat3 R = to_mat(in.origin.rotation);
    mp.mass = in.mass;
    mp.com = to_vec(in.origin.position);
    mp.inertia = R * I * R.transpose();
    return mp;
  }

  // One link to attach: the link, its joint (type, frame (R, p) in the parent body, axis) and the
  // parent body (-1 = ground).
  struct Pending {
    const urdf::Link* link;
    std::string joint_name, element;
    JointType type;
    int parent;
    Mat3 R;
    Vec3 p, axis;
  };

  // Depth-first over the link tree with an explicit stack (a 20 000-link chain must not overflow the
  // call stack); children are pushed in reverse so bodies come out in the same pre-order as a recursion.
  void attach(Pending first) {
    std::vector<Pending> stack;
    stack.push_back(std::move(first));
    while (!stack.empty()) {
      Pending w = std::move(stack.back());
      stack.pop_back();
      const urdf::Link& link = *w.link;
      MassProps mp = link_mass(link);
      const bool massless = !(mp.mass > 0);
      int body = static_cast<int>(recs_.size());
      Mat3 R = Mat3::Identity();
      Vec3 p = Vec3::Zero();
      if (w.type == JointType::kFixed && (massless || opt_.lump_fixed)) {
        // Lump: the link is a frame of the parent body.
        if (w.parent >= 0 && !massless) {
          MassProps moved;
          moved.mass = mp.mass;
          moved.com = w.p + w.R * mp.com;
          moved.inertia = w.R * mp.inertia * w.R.transpose();
          combine(recs_[w.parent].mp, moved);
        }
        body = w.parent;
        R = w.R;
        p = w.p;
      } else {
        if (massless)
          fail("link", link.name,
               std::string("has no mass (no <inertial> or mass 0) but is attached by the moving ") + w.element +
                   " '" + w.joint_name +
                   "'; haptree needs positive mass on every moving body (give it an <inertial>, or "
                   "attach it by a fixed joint to be lumped)");
        recs_.push_back(BodyRec{link.name, w.joint_name, w.parent, w.type, w.p, w.R, w.axis, mp});
      }
      push_children(link, body, R, p, stack);
    }
  }

  // Children of `link`, whose frame is (R, p) in body `body`, onto the stack (first child on top).
  void push_children(const urdf::Link& link, int body, const Mat3& R, const Vec3& p, std::vector<Pending>& stack) {
    for (auto it = link.child_joints.rbegin(); it != link.child_joints.rend(); ++it) {
      const auto& j = *it;
      const auto child = link_of(j->child_link_name);
      JointType t = JointType::kFixed;
      switch (j->type) {
        case urdf::Joint::REVOLUTE:
        case urdf::Joint::CONTINUOUS: t = JointType::kRevolute; break;
        case urdf::Joint::PRISMATIC: t = JointType::kPrismatic; break;
        case urdf::Joint::FIXED: t = JointType::kFixed; break;
        case urdf::Joint::FLOATING: t = JointType::kFree; break;
        case urdf::Joint::PLANAR:
          fail("joint", j->name, "type \"planar\" is not supported");
        default: fail("joint", j->name, "unknown joint type");
      }
      const urdf::Pose& o = j->parent_to_joint_origin_transform;
      const Mat3 Rj = R * to_mat(o.rotation);
      const Vec3 pj = p + R * to_vec(o.position);
      Vec3 axis = to_vec(j->axis);
      if ((t == JointType::kRevolute || t == JointType::kPrismatic) &&
          (!axis.allFinite() || axis.norm() < 1e-12))
        fail("joint", j->name, "<axis> is zero or not finite");
      if (t != JointType::kRevolute && t != JointType::kPrismatic) axis = Vec3::UnitZ();
      stack.push_back(Pending{child, j->name, "joint", t, body, Rj, pj, axis});
    }
  }

  const urdf::Link* link_of(const std::string& name) const {
    auto it = model_links_->find(name);
    if (it == model_links_->end()) fail("link", name, "not found");
    return it->second.get();
  }

 public:
  const std::map<std::string, urdf::LinkSharedPtr>* model_links_ = nullptr;

 private:
  std::string src_;
  UrdfOptions opt_;
  std::vector<BodyRec> recs_;
};

// A URDF's joints must form a tree: every link has at most one parent joint and no chain of parents
// comes back to where it started. urdfdom 3.0 finds both faults itself, but only after linking the
// links to each other with shared_ptr, and then leaks the whole cyclic graph (found by fuzz/urdf, as
// a LeakSanitizer report). So they are refused here first, with the joint's line.
void check_joint_tree(const TiXmlDocument& doc, const std::string& source) {
  const TiXmlElement* robot = doc.FirstChildElement("robot");
  if (!robot) return;   // urdfdom reports a missing <robot>
  std::map<std::string, std::string> parent_of;   // child link -> parent link
  std::map<std::string, std::string> joint_of;    // child link -> its parent joint
  for (const TiXmlElement* j = robot->FirstChildElement("joint"); j; j = j->NextSiblingElement("joint")) {
    const TiXmlElement* p = j->FirstChildElement("parent");
    const TiXmlElement* c = j->FirstChildElement("child");
    const char* pl = p ? p->Attribute("link") : nullptr;
    const char* cl = c ? c->Attribute("link") : nullptr;
    if (!pl || !cl) continue;   // urdfdom reports the missing element
    const char* jn = j->Attribute("name");
    const std::string where = source + ":" + std::to_string(j->Row()) + ": joint '" + (jn ? jn : "") + "': ";
    if (std::string(pl) == cl) throw UrdfError(where + "link '" + cl + "' is its own parent");
    const auto [it, fresh] = parent_of.emplace(cl, pl);
    if (!fresh)
      throw UrdfError(where + "link '" + cl + "' already has parent link '" + it->second + "': link '" + cl +
                      "' has two parents: '" + it->second + "' (joint '" + joint_of[cl] + "') and '" + pl +
                      "' (joint '" + (jn ? jn : "") + "') (a URDF is a tree: one parent joint per link)");
    joint_of[cl] = jn ? jn : "";
  }
  for (const auto& entry : parent_of) {   // walk up from every link; more steps than joints = a cycle
    const std::string* link = &entry.first;
    for (size_t steps = 0;; ++steps) {
      const auto up = parent_of.find(*link);
      if (up == parent_of.end()) break;
      if (steps > parent_of.size())
        throw UrdfError(source + ": the joints form a cycle through link '" + entry.first +
                        "' (a URDF is a tree)");
      link = &up->second;
    }
  }
}

}  // namespace

std::shared_ptr<const Model> parse_urdf(const std::string& xml, const std::string& source,
                                        const UrdfOptions& options) {
  if (const size_t bad = utf8_error(xml); bad != std::string::npos)
    throw UrdfError(source + ": not UTF-8 text (byte " + std::to_string(bad) + " is 0x" +
                    fmt_hex(static_cast<unsigned char>(xml[bad])) + "); a URDF is XML in UTF-8");
  {
    // XML well-formedness first, so the message carries the line and column.
    TiXmlDocument doc;
    doc.Parse(xml.c_str());
    if (doc.Error())
      throw UrdfError(source + ":" + std::to_string(doc.ErrorRow()) + ":" +
                      std::to_string(doc.ErrorCol()) + ": XML parse error: " +
                      one_line(doc.ErrorDesc()));
    check_joint_tree(doc, source);
  }
  std::string err;
  const urdf::ModelInterfaceSharedPtr urdf = parse_with_urdfdom(xml, err);
  if (!urdf)
    throw UrdfError(source + ": URDF parse error: " + one_line(err.empty() ? "unknown" : err));
  // A link with two parents closes a loop; haptree simulates trees only (and urdfdom would hand the
  // link to both parents, i.e. a duplicated body). Name the link and both parents.
  {
    std::map<std::string, const urdf::Joint*> parent_joint;
    for (const auto& [name, j] : urdf->joints_) {
      if (!j) continue;
      auto [it, fresh] = parent_joint.emplace(j->child_link_name, j.get());
      if (!fresh)
        throw UrdfError(source + ": link '" + j->child_link_name + "' has two parents: '" +
                        it->second->parent_link_name + "' (joint '" + it->second->name + "') and '" +
                        j->parent_link_name + "' (joint '" + j->name +
                        "'); the joints form a closed loop, and haptree simulates trees only (remove one of "
                        "the joints, or model the loop as a constraint outside the URDF)");
    }
  }
  Converter c(source, options);
  c.model_links_ = &urdf->links_;
  return c.run(*urdf);
}

std::shared_ptr<const Model> load_urdf(const std::string& path, const UrdfOptions& options) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw UrdfError(path + ": cannot open URDF file");
  std::ostringstream ss;
  ss << in.rdbuf();
  if (in.bad()) throw UrdfError(path + ": cannot read URDF file");
  return parse_urdf(ss.str(), path, options);
}

}  // namespace haptree::io
