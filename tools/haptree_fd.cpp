// haptree-fd: one forward-dynamics evaluation, printed as {"qdd": {"<joint>": value, ...}}.
// Lets people and external checks compare haptree's DCA with other engines.
#include <CLI/CLI.hpp>

#include <cmath>
#include <cstdio>
#include <iostream>
#include <string>
#include <vector>

#include "haptree/dca.hpp"
#include "haptree/io/state_json.hpp"
#include "haptree/io/urdf.hpp"
#include "haptree/scenes.hpp"

namespace {

const char* kFooter = R"(
Model source (exactly one):
  --urdf FILE         URDF through liburdfdom. revolute/continuous -> revolute, prismatic,
                      fixed, floating -> free; planar is rejected. A root link named "world" is the
                      ground; any other root link is held by a joint named "root_joint" (fixed, or
                      free with --floating-base). Links without mass on fixed joints are lumped
                      into their parent; a massless link on a moving joint is an error.
  --scene NAME        generator: chain, binary_tree, random_tree, star, protein_like (857 DOF;
                      ignores --n). Joint names: chain and binary_tree j1..jN, random_tree
                      b1..bN, star hub/leafK, protein_like phiK (backbone) / chiK_J (side chains).
                      Print the names once with an empty state to see them.

STATE.json (every section optional, keys are joint names; a missing joint is 0, i.e. angle 0 and
identity quaternions; unknown names are errors; fixed joints take no values):
  {"q":   {"elbow": 0.3, "ball": [qw, qx, qy, qz], "base": [x, y, z, qw, qx, qy, qz]},
   "qd":  {"elbow": 1.0, "ball": [wx, wy, wz],     "base": [wx, wy, wz, vx, vy, vz]},
   "tau": {"elbow": 0.5, "ball": [nx, ny, nz],     "base": [nx, ny, nz, fx, fy, fz]},
   "f_ext": {"<link/body name>": [mx, my, mz, fx, fy, fz]}}
  1-DOF joints (revolute [rad, rad/s, N m], prismatic [m, m/s, N]) take a number.
  spherical: q is a unit quaternion w,x,y,z (normalised on input); qd is the angular velocity in the
    child body frame; tau the moment in the child body frame.
  free: q = position then quaternion (w,x,y,z) of the child frame in the joint frame; qd = angular
    velocity then velocity of the body origin, both in the child body frame; tau = [moment; force]
    in the child body frame. qdd is the time derivative of qd in that convention.
  f_ext: world axes, moment about the body origin (its joint point).

Output (stdout): {"qdd": {"<joint>": value | [list], ...}} for every joint with DOFs, in model
order, numbers printed with %.17g (null if not finite). Errors: one line on stderr, exit status 1;
non-finite accelerations are an error too (the JSON is still printed).

Example: haptree-fd --scene chain --n 16 --gravity 0,0,-9.81
         haptree-fd --urdf tests/data/urdf/arm.urdf --state examples/arm_state.json
)";

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"haptree-fd: forward dynamics (divide-and-conquer ABA) of one state, as JSON"};
  std::string urdf, scene, state_path;
  int n = 16, indent = 2, max_children = 0;
  unsigned seed = 0;
  bool floating_base = false, lump_fixed = false, mixed = false, free_root = false;
  std::vector<double> gravity{0, 0, -9.81};
  auto* o_urdf = app.add_option("--urdf", urdf, "URDF file")->check(CLI::ExistingFile);
  auto* o_scene = app.add_option("--scene", scene,
                                 "generated scene: chain, binary_tree, random_tree, star, protein_like");
  o_urdf->excludes(o_scene);
  o_scene->excludes(o_urdf);
  app.add_option("--n", n, "bodies of the generated scene")
      ->capture_default_str()->check(CLI::Range(1, 1 << 22));
  app.add_option("--seed", seed, "scene seed (0: regular geometry, else random links)")
      ->capture_default_str();
  app.add_flag("--mixed-joints", mixed, "random_tree: mix revolute/prismatic/spherical/fixed joints");
  app.add_flag("--free-root", free_root, "scene: attach the root body by a free joint");
  app.add_flag("--floating-base", floating_base, "URDF: hold the root link by a free joint");
  app.add_flag("--lump-fixed", lump_fixed, "URDF: also lump massive links on fixed joints");
  app.add_option("--state", state_path, "STATE.json (see below); default: all zero")
      ->check(CLI::ExistingFile);
  app.add_option("--gravity", gravity, "gravity X,Y,Z [m/s^2] (scene units for molecules)")
      ->delimiter(',')->expected(3)->capture_default_str();
  app.add_option("--max-children", max_children,
                 "split bodies with more children than this into rigid pieces so the assembly stays "
                 "logarithmic; exact (pieces are assembled in inertia form). 0: off; use it for "
                 "hubs with dozens of children")->capture_default_str();
  app.add_option("--indent", indent, "JSON indent (-1: one line)")->capture_default_str();
  std::string refine = "double";
  app.add_option("--refine", refine,
                 "iterative refinement of qdd: off (one pass, 1.2-1.3x faster), double (one step, "
                 "residual in double: within 1e-12 on trees and proteins), extended (residual in "
                 "long double from q: the inputs' own solution, about 2x)")
      ->check(CLI::IsMember({"off", "double", "extended"}))
      ->capture_default_str();
  app.footer(kFooter);
  CLI11_PARSE(app, argc, argv);

  try {
    if (urdf.empty() && scene.empty())
      throw std::runtime_error("give --urdf FILE or --scene NAME (see --help)");
    const haptree::Vec3 g(gravity[0], gravity[1], gravity[2]);
    if (!g.allFinite()) throw std::runtime_error("--gravity: non-finite value");
    std::shared_ptr<const haptree::Model> model;
    if (!urdf.empty()) {
      haptree::io::UrdfOptions uo;
      uo.floating_base = floating_base;
      uo.lump_fixed = lump_fixed;
      uo.gravity = g;
      uo.build.max_children = max_children;
      model = haptree::io::load_urdf(urdf, uo);
    } else {
      haptree::SceneOptions so;
      so.n = n;
      so.seed = seed;
      so.mixed_joints = mixed;
      so.free_root = free_root;
      so.build.max_children = max_children;
      auto m = haptree::make_scene(scene, so);
      haptree::Model copy = *m;   // generators use the default gravity
      copy.gravity = g;
      model = std::make_shared<const haptree::Model>(std::move(copy));
    }
    haptree::State st(*model);
    st.q = haptree::neutral_configuration(*model);
    if (!state_path.empty()) st = haptree::io::load_state_json(*model, state_path);
    haptree::Data data(*model);
    haptree::set_refinement(*model, data,
                            refine == "off"        ? haptree::Refinement::kOff
                            : refine == "extended" ? haptree::Refinement::kExtended
                                                   : haptree::Refinement::kDouble);
    const Eigen::VectorXd& qdd = haptree::forward_dynamics(*model, data, st);
    std::cout << haptree::io::dump_json_exact(haptree::io::qdd_to_json(*model, qdd), indent)
              << "\n";
    if (data.diag.singular_pivots > 0)
      std::cerr << "haptree-fd: warning: " << data.diag.singular_pivots
                << " singular joint systems (result may be meaningless)\n";
    if (!qdd.allFinite()) {   // printed as null above; a result nobody can use is a failure
      std::string joints;
      int count = 0;
      for (int k = 1; k < model->nbodies; ++k) {
        bool bad = false;
        for (int i = 0; i < model->v_num[k]; ++i) bad |= !std::isfinite(qdd(model->v_adr[k] + i));
        if (bad && count++ < 5) joints += (joints.empty() ? "" : ", ") + model->joint_name[k];
      }
      std::cerr << "haptree-fd: error: non-finite accelerations (null) for " << count << " joint(s): " << joints
                << (count > 5 ? ", ..." : "") << " (state or model out of range)\n";
      return 1;
    }
    return 0;
  } catch (const std::exception& e) {
    std::cerr << "haptree-fd: error: " << e.what() << "\n";
    return 1;
  }
}
