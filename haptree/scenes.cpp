#include "haptree/scenes.hpp"

#include <random>
#include <stdexcept>

namespace haptree {

namespace {

struct LinkGen {
  std::mt19937 rng;
  bool random;
  explicit LinkGen(std::uint32_t seed) : rng(seed ? seed : 1), random(seed != 0) {}
  double uni(double a, double b) { return std::uniform_real_distribution<double>(a, b)(rng); }
  Vec3 unit() {
    Vec3 v;
    do { v = Vec3(uni(-1, 1), uni(-1, 1), uni(-1, 1)); } while (v.norm() < 0.1 || v.norm() > 1);
    return v.normalized();
  }
  Mat3 rot() { return Quat(Eigen::AngleAxisd(uni(-3.14, 3.14), unit())).toRotationMatrix(); }

  // A link of length L along its local x axis, COM at its middle, rod-like inertia.
  struct Link { double L, m; Vec3 com; Mat3 Ic; Vec3 axis; Mat3 rot; };
  Link link(int index) {
    Link l;
    if (random) {
      l.L = uni(0.2, 0.5);
      l.m = uni(0.5, 2.0);
      l.axis = unit();
      l.rot = rot();
      l.com = Vec3(l.L / 2, uni(-0.02, 0.02), uni(-0.02, 0.02));
    } else {
      l.L = 0.3;
      l.m = 1.0;
      // Alternate axes so a regular chain is not planar.
      l.axis = (index % 2 == 0) ? Vec3::UnitZ() : Vec3::UnitY();
      l.rot = Mat3::Identity();
      l.com = Vec3(l.L / 2, 0, 0);
    }
    // Box inertia (dimensions L × w × h) always satisfies the triangle inequality.
    const double w = random ? uni(0.02, 0.06) : 0.04, h = random ? uni(0.02, 0.06) : 0.04;
    const Vec3 moments(w * w + h * h, l.L * l.L + h * h, l.L * l.L + w * w);
    l.Ic = (l.m / 12.0 * moments).asDiagonal();
    if (random) {
      const Mat3 Rr = rot();
      l.Ic = Rr * l.Ic * Rr.transpose();
    }
    return l;
  }
};

JointType pick_type(LinkGen& g) {
  const double u = g.uni(0, 1);
  if (u < 0.5) return JointType::kRevolute;
  if (u < 0.65) return JointType::kPrismatic;
  if (u < 0.85) return JointType::kSpherical;
  return JointType::kFixed;
}

// Adds body `k` below `parent` whose own link has length parentL (offset along parent x).
int add_link(ModelBuilder& b, LinkGen& g, int parent, double parent_len, JointType type,
             const Vec3& base_offset, const std::string& name) {
  const auto l = g.link(b.nbodies());
  const Vec3 off = parent == 0 ? base_offset : Vec3(parent_len, 0, 0);
  return b.add_body(name, parent, type, off, parent == 0 ? Mat3::Identity() : l.rot, l.axis, l.m,
                    l.com, l.Ic);
}

}  // namespace

std::shared_ptr<const Model> make_chain(const SceneOptions& o) {
  ModelBuilder b;
  b.set_gravity(o.gravity);
  LinkGen g(o.seed);
  int prev = 0;
  double prev_len = 0;
  for (int i = 0; i < o.n; ++i) {
    const JointType t = (i == 0 && o.free_root) ? JointType::kFree
                        : o.mixed_joints ? pick_type(g) : JointType::kRevolute;
    const auto l = g.link(i + 1);
    const Vec3 off = prev == 0 ? o.base_offset : Vec3(prev_len, 0, 0);
    prev = b.add_body("link" + std::to_string(i + 1), prev, t, off, l.rot, l.axis, l.m, l.com, l.Ic,
                      "j" + std::to_string(i + 1));
    prev_len = l.L;
  }
  return b.build(o.build);
}

std::shared_ptr<const Model> make_binary_tree(const SceneOptions& o) {
  ModelBuilder b;
  b.set_gravity(o.gravity);
  LinkGen g(o.seed);
  std::vector<double> len(o.n + 1, 0.3);
  for (int k = 1; k <= o.n; ++k) {
    const int parent = k == 1 ? 0 : k / 2;
    const JointType t = (k == 1 && o.free_root) ? JointType::kFree : JointType::kRevolute;
    const auto l = g.link(k);
    len[k] = l.L;
    // Spread the two children of a node sideways so the tree does not fold onto itself.
    Mat3 rot = l.rot;
    if (!g.random && parent != 0)
      rot = Eigen::AngleAxisd(k % 2 ? 0.5 : -0.5, Vec3::UnitZ()).toRotationMatrix();
    const Vec3 off = parent == 0 ? o.base_offset : Vec3(len[parent], 0, 0);
    b.add_body("b" + std::to_string(k), parent, t, off, rot, l.axis, l.m, l.com, l.Ic,
               "j" + std::to_string(k));
  }
  return b.build(o.build);
}

std::shared_ptr<const Model> make_random_tree(const SceneOptions& o) {
  ModelBuilder b;
  b.set_gravity(o.gravity);
  LinkGen g(o.seed ? o.seed : 7);
  std::vector<double> len(o.n + 1, 0.3);
  for (int k = 1; k <= o.n; ++k) {
    const int parent = k == 1 ? 0 : 1 + static_cast<int>(g.uni(0, 1) * (k - 1)) % (k - 1);
    JointType t = JointType::kRevolute;
    if (k == 1 && o.free_root) t = JointType::kFree;
    else if (o.mixed_joints) t = pick_type(g);
    len[k] = 0;
    const int id = add_link(b, g, parent, len[parent], t, o.base_offset, "b" + std::to_string(k));
    len[id] = 0.3;
  }
  return b.build(o.build);
}

std::shared_ptr<const Model> make_star(const SceneOptions& o) {
  ModelBuilder b;
  b.set_gravity(o.gravity);
  LinkGen g(o.seed ? o.seed : 11);
  const int hub = add_link(b, g, 0, 0, o.free_root ? JointType::kFree : JointType::kSpherical,
                           o.base_offset, "hub");
  for (int k = 2; k <= o.n; ++k) {
    const JointType t = o.mixed_joints ? pick_type(g) : JointType::kRevolute;
    const auto l = g.link(k);
    b.add_body("leaf" + std::to_string(k), hub, t, 0.1 * g.unit(), l.rot, l.axis, l.m, l.com,
               l.Ic);
  }
  return b.build(o.build);
}

std::shared_ptr<const Model> make_protein_like(const SceneOptions& o) {
  ModelBuilder b;
  b.set_gravity(o.gravity);
  LinkGen g(o.seed);
  const int nbackbone = 343;
  int prev = 0;
  int side = 0;
  for (int i = 1; i <= nbackbone; ++i) {
    const auto l = g.link(i);
    const JointType t = i == 1 ? (o.free_root ? JointType::kFree : JointType::kFixed)
                               : JointType::kRevolute;
    const Vec3 off = i == 1 ? o.base_offset : Vec3(0.3, 0, 0);
    const Mat3 rot = g.random ? l.rot
                              : Mat3(Eigen::AngleAxisd(0.6, Vec3::UnitX()).toRotationMatrix());
    const int bb = b.add_body("bb" + std::to_string(i), prev, t, off, rot, l.axis, l.m, l.com,
                              l.Ic, "phi" + std::to_string(i));
    if (i % 2 == 1) {
      const int len = 2 + (side++ % 3);
      int sp = bb;
      for (int s = 1; s <= len; ++s) {
        const auto ls = g.link(i * 10 + s);
        const Mat3 srot = g.random ? ls.rot
                                   : Mat3(Eigen::AngleAxisd(1.2, Vec3::UnitZ()).toRotationMatrix());
        sp = b.add_body("sc" + std::to_string(i) + "_" + std::to_string(s), sp,
                        JointType::kRevolute, s == 1 ? Vec3(0.15, 0, 0) : Vec3(0.3, 0, 0), srot,
                        ls.axis, 0.5 * ls.m, ls.com, 0.5 * ls.Ic,
                        "chi" + std::to_string(i) + "_" + std::to_string(s));
      }
    }
    prev = bb;
  }
  return b.build(o.build);
}

std::shared_ptr<const Model> make_scene(const std::string& name, const SceneOptions& o) {
  if (name == "chain") return make_chain(o);
  if (name == "binary_tree") return make_binary_tree(o);
  if (name == "random_tree") return make_random_tree(o);
  if (name == "star") return make_star(o);
  if (name == "protein_like") return make_protein_like(o);
  throw std::invalid_argument("unknown scene '" + name +
                              "' (known: chain, binary_tree, random_tree, star, protein_like)");
}

}  // namespace haptree
