// haptree._core: pybind11 bindings over the C++ libraries (haptree, haptree_io, haptree_molecule).
//
// Nothing here computes dynamics: every call forwards to the library function of the same name.
// What this file adds is ownership, shape checks and numpy views (docs/python.md):
//   * State, Data and AdaptiveData keep a reference to the Model they were sized for; every algorithm
//     checks that the objects passed together belong to the same Model (by fingerprint) and raises
//     haptree.ModelError otherwise, instead of reading out of bounds.
//   * Array attributes (State.q, qd, tau, f_ext, Data.qdd, R, r, v, CouplingSnapshot.ints, ...) are
//     numpy VIEWS on the C++ buffers, not copies. A view holds a reference to its owner (numpy's
//     `base`), so the buffer lives as long as any view does. The buffers are sized once and never
//     reallocated: assigning (`state.q = x`) copies x INTO the existing buffer (shape-checked), so
//     earlier views stay valid and see the new values.
//   * The long calls (forward_dynamics, adaptive_step, the force field, coupling_forces) release the
//     GIL. Do not resize or share one State/Data between threads while a call runs.
//   * C++ exceptions become Python exceptions with the same message: ModelError → haptree.ModelError
//     (a ValueError), io::UrdfError → haptree.UrdfError (a ModelError), io::StateJsonError →
//     haptree.StateJsonError, mol::StructureError → haptree.StructureError (ValueErrors),
//     std::invalid_argument → ValueError, std::runtime_error → RuntimeError.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstring>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "haptree/adaptive.hpp"
#include "haptree/coupling.hpp"
#include "haptree/dca.hpp"
#include "haptree/io/state_json.hpp"
#include "haptree/io/urdf.hpp"
#include "haptree/molecule/scene.hpp"
#include "haptree/scenes.hpp"

namespace py = pybind11;
using namespace haptree;

namespace {

using ModelPtr = std::shared_ptr<Model>;   // held const in C++; Python never gets a setter
using Arr = py::array_t<double, py::array::c_style | py::array::forcecast>;

ModelPtr hold(std::shared_ptr<const Model> m) { return std::const_pointer_cast<Model>(std::move(m)); }

struct PyState {
  explicit PyState(ModelPtr m) : model(std::move(m)), s(*model) {}
  PyState(ModelPtr m, State st) : model(std::move(m)), s(std::move(st)) {}
  ModelPtr model;
  State s;
};
struct PyData {
  explicit PyData(ModelPtr m) : model(std::move(m)), d(*model) {}
  ModelPtr model;
  Data d;
};
struct PyAdaptive {
  explicit PyAdaptive(ModelPtr m) : model(std::move(m)), ad(*model) {}
  ModelPtr model;
  AdaptiveData ad;
};

void same_model(const Model& m, const ModelPtr& other, const char* what) {
  if (other.get() != &m && other->fingerprint != m.fingerprint) {
    std::ostringstream os;
    os << what << " was made for another Model (fingerprint " << std::hex << other->fingerprint
       << ", this model " << m.fingerprint << ")";
    throw ModelError(os.str());
  }
}

std::string shape_str(const py::array& a) {
  std::string s = "(";
  for (py::ssize_t i = 0; i < a.ndim(); ++i) s += (i ? ", " : "") + std::to_string(a.shape(i));
  return s + (a.ndim() == 1 ? ",)" : ")");
}

// Checks that `a` holds exactly `n` doubles in the given shape (rows × cols; cols = 0: 1-D).
void check_shape(const py::array& a, py::ssize_t rows, py::ssize_t cols, const char* what) {
  const bool ok = cols == 0 ? (a.ndim() == 1 && a.shape(0) == rows)
                            : (a.ndim() == 2 && a.shape(0) == rows && a.shape(1) == cols);
  if (!ok) {
    std::string want = cols == 0 ? "(" + std::to_string(rows) + ",)"
                                 : "(" + std::to_string(rows) + ", " + std::to_string(cols) + ")";
    throw py::value_error(std::string(what) + ": expected shape " + want + ", got " + shape_str(a));
  }
}

// A writable numpy view on `p`; `owner` becomes the array's base and is kept alive by it.
py::array view(double* p, std::vector<py::ssize_t> shape, std::vector<py::ssize_t> strides, py::handle owner) {
  return py::array_t<double>(shape, strides, p, owner);
}
py::array cview(const double* p, std::vector<py::ssize_t> shape, std::vector<py::ssize_t> strides,
                py::handle owner) {
  py::array a = py::array_t<double>(shape, strides, const_cast<double*>(p), owner);
  a.attr("setflags")(py::arg("write") = false);
  return a;
}
constexpr py::ssize_t D = sizeof(double);

// Copies `a` into a fixed buffer of n doubles (memmove: `a` may be a view on that same buffer).
void assign(double* dst, py::ssize_t rows, py::ssize_t cols, const Arr& a, const char* what) {
  check_shape(a, rows, cols, what);
  std::memmove(dst, a.data(), sizeof(double) * rows * (cols ? cols : 1));
}

Vec3 vec3(const Arr& a, const char* what) {
  check_shape(a, 3, 0, what);
  return Vec3(a.data()[0], a.data()[1], a.data()[2]);
}
Vec6 vec6(const Arr& a, const char* what) {
  check_shape(a, 6, 0, what);
  Vec6 v;
  std::memcpy(v.data(), a.data(), sizeof(double) * 6);
  return v;
}
py::array to_np(const Vec3& v) {
  py::array_t<double> a(3);
  std::memcpy(a.mutable_data(), v.data(), 3 * D);
  return a;
}
py::array to_np(const Vec6& v) {
  py::array_t<double> a(6);
  std::memcpy(a.mutable_data(), v.data(), 6 * D);
  return a;
}
py::array to_np(const Mat3& m) {   // row-major numpy copy of a column-major 3×3
  py::array_t<double> a({3, 3});
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) a.mutable_at(i, j) = m(i, j);
  return a;
}
py::array to_np(const Eigen::VectorXd& v) {
  py::array_t<double> a(v.size());
  std::memcpy(a.mutable_data(), v.data(), v.size() * D);
  return a;
}
template <class T>
py::array_t<T> to_np(const std::vector<T>& v) {
  py::array_t<T> a(static_cast<py::ssize_t>(v.size()));
  if (!v.empty()) std::memcpy(a.mutable_data(), v.data(), v.size() * sizeof(T));
  return a;
}

BuildOptions build_options(int max_children) {
  if (max_children < 0) throw py::value_error("max_children must be >= 0, got " + std::to_string(max_children));
  BuildOptions b;
  b.max_children = max_children;
  return b;
}

std::string model_repr(const Model& m) {
  std::ostringstream os;
  os << "<haptree.Model nbodies=" << m.nbodies << " nq=" << m.nq << " nv=" << m.nv << " depth=" << m.max_depth()
     << " fingerprint=0x" << std::hex << m.fingerprint << ">";
  return os.str();
}

std::string report_repr(const AdaptiveReport& r) {
  std::ostringstream os;
  os << "AdaptiveReport(active_dofs=" << r.active_dofs << ", active_nodes=" << r.active_nodes
     << ", frontier_nodes=" << r.frontier_nodes << ", neglected_metric=" << r.neglected_metric
     << ", total_metric=" << r.total_metric << ", nodes_bottom_up=" << r.nodes_bottom_up
     << ", nodes_top_down=" << r.nodes_top_down << ", reselected=" << (r.reselected ? "True" : "False")
     << ", selections=" << r.selections << ")";
  return os.str();
}

// Molecular scene held by a shared_ptr (it owns a unique_ptr evaluator: move-only).
struct PyScene {
  mol::MolecularScene sc;
  ModelPtr model;
  ff::Evaluator& ff() {
    if (!sc.force_field) throw py::value_error("scene '" + sc.name + "' was loaded with with_force_field=False");
    return *sc.force_field;
  }
  void check_atom(int atom) const {
    if (atom < 0 || atom >= sc.natoms())
      throw py::index_error("atom " + std::to_string(atom) + " out of range [0, " + std::to_string(sc.natoms()) + ")");
  }
};

std::vector<Vec3> positions_from(const Arr& x, int n, const char* what) {
  check_shape(x, n, 3, what);
  static_assert(sizeof(Vec3) == 3 * sizeof(double), "Vec3 must be 3 packed doubles");
  std::vector<Vec3> v(n);
  if (n > 0) std::memcpy(v[0].data(), x.data(), sizeof(double) * 3 * n);
  return v;
}

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() = "haptree: adaptive divide-and-conquer articulated-body dynamics with O(log n) force feedback";

  // Exceptions (same messages as C++). Registered base first: pybind11 tries the last one first.
  static py::exception<ModelError> model_error(m, "ModelError", PyExc_ValueError);
  static py::exception<io::UrdfError> urdf_error(m, "UrdfError", model_error.ptr());
  static py::exception<io::StateJsonError> json_error(m, "StateJsonError", PyExc_ValueError);
  static py::exception<mol::StructureError> structure_error(m, "StructureError", PyExc_ValueError);
  py::register_exception_translator([](std::exception_ptr p) {
    try {
      if (p) std::rethrow_exception(p);
    } catch (const io::UrdfError& e) {
      PyErr_SetString(urdf_error.ptr(), e.what());
    } catch (const ModelError& e) {
      PyErr_SetString(model_error.ptr(), e.what());
    } catch (const io::StateJsonError& e) {
      PyErr_SetString(json_error.ptr(), e.what());
    } catch (const mol::StructureError& e) {
      PyErr_SetString(structure_error.ptr(), e.what());
    }
  });

  // ---------------------------------------------------------------- Model and loaders
  py::enum_<JointType>(m, "JointType")
      .value("revolute", JointType::kRevolute)
      .value("prismatic", JointType::kPrismatic)
      .value("spherical", JointType::kSpherical)
      .value("free", JointType::kFree)
      .value("fixed", JointType::kFixed);

  py::class_<Model, ModelPtr>(m, "Model", "Immutable articulated body (read-only attributes are copies).")
      .def_readonly("nbodies", &Model::nbodies)
      .def_readonly("nq", &Model::nq)
      .def_readonly("nv", &Model::nv)
      .def_readonly("body_name", &Model::body_name)
      .def_readonly("joint_name", &Model::joint_name)
      .def_readonly("parent", &Model::parent)
      .def_readonly("joint_type", &Model::joint_type)
      .def_readonly("q_adr", &Model::q_adr)
      .def_readonly("v_adr", &Model::v_adr)
      .def_readonly("v_num", &Model::v_num)
      .def_readonly("mass", &Model::mass)
      .def_property_readonly("gravity", [](const Model& mo) { return to_np(mo.gravity); })
      .def_readonly("fingerprint", &Model::fingerprint)
      .def_property_readonly("max_depth", &Model::max_depth)
      .def_property_readonly("nnodes", [](const Model& mo) { return mo.tree.nnodes(); })
      .def("joint_index", &Model::joint_index, "Joint id by name, -1 if absent.")
      .def("body_index", &Model::body_index, "Body id by name, -1 if absent.")
      .def("__repr__", &model_repr);

  m.def(
      "make_scene",
      [](const std::string& name, int n, std::uint32_t seed, bool mixed_joints, bool free_root, const Arr& gravity,
         const Arr& base_offset, int max_children) {
        if (n < 1) throw py::value_error("make_scene: n must be >= 1, got " + std::to_string(n));
        SceneOptions o;
        o.n = n;
        o.seed = seed;
        o.mixed_joints = mixed_joints;
        o.free_root = free_root;
        o.gravity = vec3(gravity, "gravity");
        o.base_offset = vec3(base_offset, "base_offset");
        o.build = build_options(max_children);
        return hold(make_scene(name, o));
      },
      py::arg("name"), py::arg("n") = 16, py::arg("seed") = 0, py::arg("mixed_joints") = false,
      py::arg("free_root") = false, py::arg("gravity") = Arr(py::array_t<double>({3}, {D}, Vec3(0, 0, -9.81).data())),
      py::arg("base_offset") = Arr(py::array_t<double>({3}, {D}, Vec3::Zero().eval().data())),
      py::arg("max_children") = 0,
      "Procedural scene: chain, binary_tree, random_tree, star, protein_like (haptree/scenes.hpp).");

  m.def(
      "load_urdf",
      [](const std::string& path, bool floating_base, bool lump_fixed, const std::string& root_joint_name,
         const Arr& gravity, int max_children) {
        io::UrdfOptions o;
        o.floating_base = floating_base;
        o.lump_fixed = lump_fixed;
        o.root_joint_name = root_joint_name;
        o.gravity = vec3(gravity, "gravity");
        o.build = build_options(max_children);
        return hold(io::load_urdf(path, o));
      },
      py::arg("path"), py::arg("floating_base") = false, py::arg("lump_fixed") = false,
      py::arg("root_joint_name") = "root_joint",
      py::arg("gravity") = Arr(py::array_t<double>({3}, {D}, Vec3(0, 0, -9.81).data())), py::arg("max_children") = 0,
      "URDF file -> Model (haptree/io/urdf.hpp). Raises UrdfError naming the file and element.");
  m.def(
      "parse_urdf",
      [](const std::string& xml, const std::string& source, bool floating_base, bool lump_fixed) {
        io::UrdfOptions o;
        o.floating_base = floating_base;
        o.lump_fixed = lump_fixed;
        return hold(io::parse_urdf(xml, source, o));
      },
      py::arg("xml"), py::arg("source") = "<string>", py::arg("floating_base") = false, py::arg("lump_fixed") = false);
  m.def("neutral_configuration", [](const Model& mo) { return to_np(neutral_configuration(mo)); }, py::arg("model"));

  // ---------------------------------------------------------------- State and Data
  py::class_<PyState>(m, "State",
                      "Joint state of one Model. q, qd, tau, f_ext are numpy views on the C++ buffers "
                      "(assignment copies into them).")
      .def(py::init<ModelPtr>(), py::arg("model"), py::keep_alive<1, 2>())
      .def_property_readonly("model", [](const PyState& s) { return s.model; })
      .def_property(
          "q", [](py::object self) { auto& s = self.cast<PyState&>(); return view(s.s.q.data(), {s.s.q.size()}, {D}, self); },
          [](PyState& s, const Arr& a) { assign(s.s.q.data(), s.s.q.size(), 0, a, "State.q"); })
      .def_property(
          "qd", [](py::object self) { auto& s = self.cast<PyState&>(); return view(s.s.qd.data(), {s.s.qd.size()}, {D}, self); },
          [](PyState& s, const Arr& a) { assign(s.s.qd.data(), s.s.qd.size(), 0, a, "State.qd"); })
      .def_property(
          "tau", [](py::object self) { auto& s = self.cast<PyState&>(); return view(s.s.tau.data(), {s.s.tau.size()}, {D}, self); },
          [](PyState& s, const Arr& a) { assign(s.s.tau.data(), s.s.tau.size(), 0, a, "State.tau"); })
      .def_property(
          "f_ext",
          [](py::object self) {
            auto& s = self.cast<PyState&>();
            return view(s.s.f_ext[0].data(), {static_cast<py::ssize_t>(s.s.f_ext.size()), 6}, {6 * D, D}, self);
          },
          [](PyState& s, const Arr& a) {
            assign(s.s.f_ext[0].data(), static_cast<py::ssize_t>(s.s.f_ext.size()), 6, a, "State.f_ext");
          },
          "(nbodies, 6) applied spatial forces [moment; force], world axes, at each body origin r_k.")
      .def_property("t", [](const PyState& s) { return s.s.t; }, [](PyState& s, double t) { s.s.t = t; })
      .def("copy", [](const PyState& s) { return PyState(s.model, s.s); }, "An independent copy (new buffers).");

  py::class_<PyData>(m, "Data", "Preallocated workspace of one Model; arrays are read-only views.")
      .def(py::init<ModelPtr>(), py::arg("model"), py::keep_alive<1, 2>())
      .def_property_readonly("model", [](const PyData& d) { return d.model; })
      .def_property_readonly(
          "qdd", [](py::object self) { auto& d = self.cast<PyData&>(); return cview(d.d.qdd.data(), {d.d.qdd.size()}, {D}, self); },
          "(nv,) joint accelerations of the last forward_dynamics / adaptive step.")
      .def_property_readonly(
          "R",
          [](py::object self) {
            auto& d = self.cast<PyData&>();   // Mat3 is column-major: R[k][i, j] = R_k(i, j)
            return cview(d.d.R[0].data(), {static_cast<py::ssize_t>(d.d.R.size()), 3, 3}, {9 * D, D, 3 * D}, self);
          },
          "(nbodies, 3, 3) body rotations (body -> world).")
      .def_property_readonly(
          "r",
          [](py::object self) {
            auto& d = self.cast<PyData&>();
            return cview(d.d.r[0].data(), {static_cast<py::ssize_t>(d.d.r.size()), 3}, {3 * D, D}, self);
          },
          "(nbodies, 3) body origins r_k, world frame.")
      .def_property_readonly(
          "v",
          [](py::object self) {
            auto& d = self.cast<PyData&>();
            return cview(d.d.v[0].data(), {static_cast<py::ssize_t>(d.d.v.size()), 6}, {6 * D, D}, self);
          },
          "(nbodies, 6) spatial velocities [ω; v] at r_k, world axes.")
      .def_property_readonly(
          "f_total",
          [](py::object self) {
            auto& d = self.cast<PyData&>();
            return cview(d.d.f_total[0].data(), {static_cast<py::ssize_t>(d.d.f_total.size()), 6}, {6 * D, D}, self);
          },
          "(nbodies, 6) gravity + State.f_ext at r_k.")
      .def_property_readonly("singular_pivots", [](const PyData& d) { return d.d.diag.singular_pivots; })
      .def_property_readonly("nonfinite", [](const PyData& d) { return d.d.diag.nonfinite; })
      .def_property_readonly("nodes_bottom_up", [](const PyData& d) { return d.d.diag.nodes_bottom_up; })
      .def_property_readonly("nodes_top_down", [](const PyData& d) { return d.d.diag.nodes_top_down; });

  m.def(
      "load_state_json",
      [](ModelPtr mo, const std::string& path) { return PyState(mo, io::load_state_json(*mo, path)); },
      py::arg("model"), py::arg("path"), py::keep_alive<0, 1>(),
      "State from a haptree-fd JSON document (haptree/io/state_json.hpp).");
  m.def(
      "state_from_json",
      [](ModelPtr mo, const std::string& text, const std::string& source) {
        nlohmann::json doc;
        try {
          doc = nlohmann::json::parse(text);
        } catch (const nlohmann::json::exception& e) {
          throw io::StateJsonError(source + ": " + e.what());
        }
        return PyState(mo, io::state_from_json(*mo, doc, source));
      },
      py::arg("model"), py::arg("text"), py::arg("source") = "<string>", py::keep_alive<0, 1>());

  // ---------------------------------------------------------------- Dynamics
  m.def(
      "forward_kinematics",
      [](const Model& mo, PyData& d, const PyState& s) {
        same_model(mo, d.model, "Data");
        same_model(mo, s.model, "State");
        py::gil_scoped_release nogil;
        forward_kinematics(mo, d.d, s.s.q);
      },
      py::arg("model"), py::arg("data"), py::arg("state"));
  m.def(
      "forward_dynamics",
      [](const Model& mo, py::object dobj, const PyState& s) {
        auto& d = dobj.cast<PyData&>();
        same_model(mo, d.model, "Data");
        same_model(mo, s.model, "State");
        {
          py::gil_scoped_release nogil;
          forward_dynamics(mo, d.d, s.s);
        }
        return cview(d.d.qdd.data(), {d.d.qdd.size()}, {D}, dobj);
      },
      py::arg("model"), py::arg("data"), py::arg("state"),
      "Full DCA pass; returns data.qdd (a view, overwritten by the next pass).");
  m.def(
      "integrate",
      [](const Model& mo, PyState& s, const PyData& d, double dt) {
        same_model(mo, d.model, "Data");
        same_model(mo, s.model, "State");
        integrate(mo, s.s.q, s.s.qd, d.d.qdd, dt);
        s.s.t += dt;
      },
      py::arg("model"), py::arg("state"), py::arg("data"), py::arg("dt"),
      "Semi-implicit Euler with data.qdd: qd += dt·qdd, then q with the new qd; t += dt.");
  m.def(
      "kinetic_energy",
      [](const Model& mo, const PyData& d) {
        same_model(mo, d.model, "Data");
        return kinetic_energy(mo, d.d);
      },
      py::arg("model"), py::arg("data"), "Needs body velocities (after forward_dynamics).");
  m.def(
      "potential_energy",
      [](const Model& mo, const PyData& d) {
        same_model(mo, d.model, "Data");
        return potential_energy(mo, d.d);
      },
      py::arg("model"), py::arg("data"));

  // ---------------------------------------------------------------- Adaptive
  py::enum_<AdaptiveOptions::Mode>(m, "AdaptiveMode")
      .value("threshold", AdaptiveOptions::Mode::kThreshold)
      .value("budget", AdaptiveOptions::Mode::kBudget);
  py::class_<AdaptiveOptions>(m, "AdaptiveOptions")
      .def(py::init([](AdaptiveOptions::Mode mode, double epsilon, int budget, int reselect_every) {
             if (budget < 0) throw py::value_error("AdaptiveOptions: budget must be >= 0, got " + std::to_string(budget));
             if (reselect_every < 1)
               throw py::value_error("AdaptiveOptions: reselect_every must be >= 1, got " + std::to_string(reselect_every));
             if (!(epsilon >= 0)) throw py::value_error("AdaptiveOptions: epsilon must be >= 0");
             AdaptiveOptions o;
             o.mode = mode;
             o.epsilon = epsilon;
             o.budget = budget;
             o.reselect_every = reselect_every;
             return o;
           }),
           py::arg("mode") = AdaptiveOptions::Mode::kBudget, py::arg("epsilon") = 1e-3, py::arg("budget") = 48,
           py::arg("reselect_every") = 10)
      .def_readwrite("mode", &AdaptiveOptions::mode)
      .def_readwrite("epsilon", &AdaptiveOptions::epsilon)
      .def_readwrite("budget", &AdaptiveOptions::budget)
      .def_readwrite("reselect_every", &AdaptiveOptions::reselect_every)
      .def_readwrite("background_selection", &AdaptiveOptions::background_selection,
                     "reselections computed on a worker thread, installed by a later step (default True)");
  py::class_<AdaptiveReport>(m, "AdaptiveReport", "Copy of AdaptiveData.report after a step.")
      .def_readonly("active_dofs", &AdaptiveReport::active_dofs)
      .def_readonly("active_nodes", &AdaptiveReport::active_nodes)
      .def_readonly("frontier_nodes", &AdaptiveReport::frontier_nodes)
      .def_readonly("neglected_metric", &AdaptiveReport::neglected_metric)
      .def_readonly("total_metric", &AdaptiveReport::total_metric)
      .def_readonly("nodes_bottom_up", &AdaptiveReport::nodes_bottom_up)
      .def_readonly("nodes_top_down", &AdaptiveReport::nodes_top_down)
      .def_readonly("reselected", &AdaptiveReport::reselected)
      .def_readonly("selections", &AdaptiveReport::selections)
      .def("__repr__", &report_repr);
  py::class_<PyAdaptive>(m, "AdaptiveData")
      .def(py::init<ModelPtr>(), py::arg("model"), py::keep_alive<1, 2>())
      .def_property_readonly("report", [](const PyAdaptive& a) { return a.ad.report; })
      .def_property_readonly("active_joints", [](const PyAdaptive& a) { return to_np(a.ad.active_joints); },
                             "Copy: joint (= body) ids of the active region, ascending.")
      .def_property_readonly("frontier_of_body", [](const PyAdaptive& a) { return to_np(a.ad.frontier_of_body); },
                             "Copy: per body the frontier node holding it (rigid region id).");
  auto check3 = [](const Model& mo, const PyData& d, const PyState& s, const PyAdaptive& a) {
    same_model(mo, d.model, "Data");
    same_model(mo, s.model, "State");
    same_model(mo, a.model, "AdaptiveData");
  };
  m.def(
      "adaptive_step",
      [check3](const Model& mo, PyData& d, PyState& s, PyAdaptive& a, const AdaptiveOptions& o, double dt) {
        check3(mo, d, s, a);
        py::gil_scoped_release nogil;
        return adaptive_step(mo, d.d, s.s, a.ad, o, dt);   // copied into the returned AdaptiveReport
      },
      py::arg("model"), py::arg("data"), py::arg("state"), py::arg("adaptive"), py::arg("options"), py::arg("dt"),
      "One adaptive step (reselect if due, hybrid DCA, Euler on the active joints); returns the report.");
  m.def(
      "select_active_region",
      [check3](const Model& mo, PyData& d, PyState& s, PyAdaptive& a, const AdaptiveOptions& o) {
        check3(mo, d, s, a);
        py::gil_scoped_release nogil;
        return select_active_region(mo, d.d, s.s, a.ad, o);
      },
      py::arg("model"), py::arg("data"), py::arg("state"), py::arg("adaptive"), py::arg("options"));
  m.def(
      "adaptive_forward_dynamics",
      [check3](const Model& mo, py::object dobj, const PyState& s, PyAdaptive& a) {
        auto& d = dobj.cast<PyData&>();
        check3(mo, d, s, a);
        {
          py::gil_scoped_release nogil;
          adaptive_forward_dynamics(mo, d.d, s.s, a.ad);
        }
        return cview(d.d.qdd.data(), {d.d.qdd.size()}, {D}, dobj);
      },
      py::arg("model"), py::arg("data"), py::arg("state"), py::arg("adaptive"));
  m.def(
      "update_all_body_poses",
      [](const Model& mo, PyData& d, const PyAdaptive& a) {
        same_model(mo, d.model, "Data");
        same_model(mo, a.model, "AdaptiveData");
        update_all_body_poses(mo, d.d, a.ad);
      },
      py::arg("model"), py::arg("data"), py::arg("adaptive"));

  // ---------------------------------------------------------------- Coupling
  py::class_<Grab>(m, "Grab")
      .def(py::init([](int body, const Arr& point, const Arr& velocity) {
             Grab g;
             g.body = body;
             g.point = vec3(point, "Grab.point");
             g.velocity = vec3(velocity, "Grab.velocity");
             return g;
           }),
           py::arg("body"), py::arg("point"), py::arg("velocity") = Arr(py::array_t<double>({3}, {D}, Vec3::Zero().eval().data())))
      .def_readwrite("body", &Grab::body)
      .def_property("point", [](const Grab& g) { return to_np(g.point); },
                    [](Grab& g, const Arr& a) { g.point = vec3(a, "Grab.point"); })
      .def_property("velocity", [](const Grab& g) { return to_np(g.velocity); },
                    [](Grab& g, const Arr& a) { g.velocity = vec3(a, "Grab.velocity"); });
  m.def(
      "make_grab",
      [](const PyData& d, int body, const Arr& local_point) { return make_grab(d.d, body, vec3(local_point, "local_point")); },
      py::arg("data"), py::arg("body"), py::arg("local_point"),
      "Grab of a body-local point (world point and point velocity from Data after forward_dynamics).");

  py::enum_<CouplingStatus>(m, "CouplingStatus")
      .value("ok", CouplingStatus::kOk)
      .value("empty", CouplingStatus::kEmpty)
      .value("bad_snapshot", CouplingStatus::kBadSnapshot)
      .value("workspace_too_small", CouplingStatus::kWorkspaceTooSmall)
      .value("nonfinite", CouplingStatus::kNonFinite);

  py::class_<CouplingSnapshot, std::shared_ptr<CouplingSnapshot>>(m, "CouplingSnapshot", "Coefficient snapshot; ints/values are views.")
      .def(py::init<>())
      .def_readwrite("model_fingerprint", &CouplingSnapshot::model_fingerprint)
      .def_readwrite("version", &CouplingSnapshot::version)
      .def_readwrite("sim_time", &CouplingSnapshot::sim_time)
      .def_readonly("grabs", &CouplingSnapshot::grabs)
      .def_property_readonly("ints",
                             [](py::object self) {
                               auto& s = self.cast<CouplingSnapshot&>();
                               py::array a = py::array_t<std::int32_t>({static_cast<py::ssize_t>(s.ints.size())},
                                                                       {static_cast<py::ssize_t>(sizeof(std::int32_t))},
                                                                       s.ints.data(), self);
                               a.attr("setflags")(py::arg("write") = false);
                               return a;
                             })
      .def_property_readonly("values",
                             [](py::object self) {
                               auto& s = self.cast<CouplingSnapshot&>();
                               return cview(s.values.data(), {static_cast<py::ssize_t>(s.values.size())}, {D}, self);
                             })
      .def_property_readonly("payload_bytes", [](const CouplingSnapshot& s) { return snapshot_payload_bytes(s); });

  m.def(
      "make_coupling_snapshot",
      [](const Model& mo, const PyData& d, const std::vector<Grab>& grabs, py::object f_u_applied, std::int64_t version,
         double sim_time, std::shared_ptr<CouplingSnapshot> out) {
        same_model(mo, d.model, "Data");
        std::vector<Vec6> fu;
        if (!f_u_applied.is_none()) {
          Arr a = f_u_applied.cast<Arr>();
          check_shape(a, static_cast<py::ssize_t>(grabs.size()), 6, "f_u_applied");
          fu.resize(grabs.size());
          if (!fu.empty()) std::memcpy(fu[0].data(), a.data(), sizeof(double) * 6 * grabs.size());
        }
        if (!out) out = std::make_shared<CouplingSnapshot>();
        make_coupling_snapshot(mo, d.d, grabs, fu, version, sim_time, *out);
        return out;
      },
      py::arg("model"), py::arg("data"), py::arg("grabs"), py::arg("f_u_applied") = py::none(),
      py::arg("version") = 0, py::arg("sim_time") = 0.0, py::arg("out") = nullptr,
      "Snapshot for `grabs` after a DCA pass. f_u_applied: (len(grabs), 6) user forces that pass applied "
      "(at the grab points) or None. out: a snapshot to reuse (no allocation once sized).");

  py::class_<CouplingWorkspace>(m, "CouplingWorkspace")
      .def(py::init<const CouplingSnapshot&>(), py::arg("snapshot"))
      .def(py::init<int, int>(), py::arg("max_nodes"), py::arg("max_slots"))
      .def("reserve_for", &CouplingWorkspace::reserve_for)
      .def("fits", &CouplingWorkspace::fits)
      .def_readonly("nodes_read", &CouplingWorkspace::nodes_read);

  m.def(
      "coupling_forces",
      [](const CouplingSnapshot& s, const Arr& f_u, CouplingWorkspace& ws, py::object out) {
        const auto ng = static_cast<py::ssize_t>(s.grabs.size());
        check_shape(f_u, ng, 6, "f_u");
        py::array_t<double, py::array::c_style> f_feed;
        if (out.is_none()) {
          f_feed = py::array_t<double, py::array::c_style>({ng, py::ssize_t(6)});
        } else {
          // The output must BE a C-contiguous float64 array (no silent conversion into a temporary).
          if (!py::isinstance<py::array_t<double, py::array::c_style>>(out))
            throw py::value_error("out: expected a C-contiguous float64 array");
          f_feed = out.cast<py::array_t<double, py::array::c_style>>();
          check_shape(f_feed, ng, 6, "out");
          if (!f_feed.writeable()) throw py::value_error("out: array is read-only");
        }
        static_assert(sizeof(Vec6) == 6 * sizeof(double), "Vec6 must be 6 packed doubles");
        const Vec6* in = reinterpret_cast<const Vec6*>(f_u.data());
        Vec6* o = reinterpret_cast<Vec6*>(f_feed.mutable_data());
        CouplingStatus st;
        {
          py::gil_scoped_release nogil;
          st = coupling_forces(s, in, ws, o);
        }
        return py::make_tuple(st, f_feed);
      },
      py::arg("snapshot"), py::arg("f_u"), py::arg("workspace"), py::arg("out") = py::none(),
      "f_feed for every grab under user forces f_u ((n_grabs, 6), at the grab points). Returns "
      "(CouplingStatus, f_feed); pass out= (a (n_grabs, 6) float64 array) to avoid allocating.");
  m.def("validate_coupling_snapshot", &validate_coupling_snapshot, py::arg("snapshot"));
  auto check_grab = [](const CouplingSnapshot& s, int g) {
    if (validate_coupling_snapshot(s) != CouplingStatus::kOk) throw py::value_error("snapshot is not valid");
    if (g < 0 || g >= static_cast<int>(s.grabs.size()))
      throw py::index_error("grab " + std::to_string(g) + " out of range [0, " + std::to_string(s.grabs.size()) + ")");
  };
  m.def(
      "grab_force_at_body_origin",
      [check_grab](const CouplingSnapshot& s, int g, const Arr& f) {
        check_grab(s, g);
        return to_np(grab_force_at_body_origin(s, g, vec6(f, "f")));
      },
      py::arg("snapshot"), py::arg("grab"), py::arg("f"), "f (at grab g's point) moved to the body origin.");
  m.def("snapshot_grab_offset", [check_grab](const CouplingSnapshot& s, int g) { check_grab(s, g); return to_np(snapshot_grab_offset(s, g)); });
  m.def("snapshot_grab_rotation", [check_grab](const CouplingSnapshot& s, int g) { check_grab(s, g); return to_np(snapshot_grab_rotation(s, g)); });

  py::class_<VirtualCoupling3>(m, "VirtualCoupling3")
      .def(py::init([](double k_s, double b_s) { return VirtualCoupling3{k_s, b_s}; }), py::arg("k_s"), py::arg("b_s") = 0.0)
      .def_readwrite("k_s", &VirtualCoupling3::k_s)
      .def_readwrite("b_s", &VirtualCoupling3::b_s)
      .def(
          "user_force",
          [](const VirtualCoupling3& c, const Arr& x_h, const Arr& xd_h, const Arr& x_s, const Arr& xd_s) {
            return to_np(c.user_force(vec3(x_h, "x_h"), vec3(xd_h, "xd_h"), vec3(x_s, "x_s"), vec3(xd_s, "xd_s")));
          },
          py::arg("x_h"), py::arg("xd_h"), py::arg("x_s"), py::arg("xd_s"));

  // ---------------------------------------------------------------- Molecules
  py::class_<ff::EnergyTerms>(m, "EnergyTerms", "Force-field energy terms, kJ/mol.")
      .def_readonly("coulomb", &ff::EnergyTerms::coulomb)
      .def_readonly("coulomb14", &ff::EnergyTerms::coulomb14)
      .def_readonly("lj", &ff::EnergyTerms::lj)
      .def_readonly("lj14", &ff::EnergyTerms::lj14)
      .def_readonly("torsion", &ff::EnergyTerms::torsion)
      .def_readonly("rigid_constant", &ff::EnergyTerms::rigid_constant)
      .def_property_readonly("total", &ff::EnergyTerms::total)
      .def("as_dict", [](const ff::EnergyTerms& e) {
        py::dict d;
        d["coulomb"] = e.coulomb;
        d["coulomb14"] = e.coulomb14;
        d["lj"] = e.lj;
        d["lj14"] = e.lj14;
        d["torsion"] = e.torsion;
        d["rigid_constant"] = e.rigid_constant;
        d["total"] = e.total();
        return d;
      });

  py::class_<PyScene, std::shared_ptr<PyScene>>(m, "MolecularScene",
                                               "PDB/mmCIF structure as a torsion-angle Model with the "
                                               "force field (units: nm, ps, amu, kJ/mol, e).")
      .def_property_readonly("name", [](const PyScene& p) { return p.sc.name; })
      .def_property_readonly("path", [](const PyScene& p) { return p.sc.path; })
      .def_property_readonly("model", [](const PyScene& p) { return p.model; })
      .def_property_readonly("natoms", [](const PyScene& p) { return p.sc.natoms(); })
      .def_property_readonly("dof", [](const PyScene& p) { return p.sc.dof(); })
      .def_property_readonly("messages", [](const PyScene& p) { return p.sc.messages; })
      .def_property_readonly("atom_labels",
                             [](const PyScene& p) {
                               std::vector<std::string> v;
                               for (int i = 0; i < p.sc.natoms(); ++i) v.push_back(p.sc.structure.atom_label(i));
                               return v;
                             })
      .def_property_readonly("atom_body", [](const PyScene& p) { return to_np(p.sc.torsion.atom_model_body); },
                             "Copy: per atom its Model body id.")
      .def_property_readonly("masses", [](const PyScene& p) { return to_np(p.sc.topology.mass); })
      .def_property_readonly("charges", [](const PyScene& p) { return to_np(p.sc.topology.charge); })
      .def("file_positions",
           [](const PyScene& p) {
             py::array_t<double> a({p.sc.natoms(), 3});
             for (int i = 0; i < p.sc.natoms(); ++i)
               for (int c = 0; c < 3; ++c) a.mutable_at(i, c) = p.sc.structure.atoms[i].pos[c];
             return a;
           },
           "(natoms, 3) atom positions read from the file, nm (= the neutral configuration).")
      .def(
          "compute",
          [](PyScene& p, const PyData& d, PyState& s) {
            same_model(*p.model, d.model, "Data");
            same_model(*p.model, s.model, "State");
            ff::Evaluator& e = p.ff();
            py::gil_scoped_release nogil;
            return e.compute(*p.model, d.d, s.s.f_ext);
          },
          py::arg("data"), py::arg("state"),
          "Potential energy (kJ/mol) at the configuration in `data` (after forward_kinematics or "
          "update_all_body_poses); OVERWRITES state.f_ext with the force-field wrenches.")
      .def(
          "compute_atoms",
          [](PyScene& p, const Arr& x) {
            std::vector<Vec3> xv = positions_from(x, p.sc.natoms(), "x");
            std::vector<Vec3> F;
            ff::EnergyTerms t;
            const double E = p.ff().compute_atoms(xv, F, &t);
            py::array_t<double> Fa({p.sc.natoms(), 3});
            std::memcpy(Fa.mutable_data(), F.data(), sizeof(double) * 3 * F.size());
            return py::make_tuple(E, Fa, t);
          },
          py::arg("x"), "(E, F (natoms, 3) kJ/mol/nm, EnergyTerms) of the scene evaluator at positions x (nm).")
      .def(
          "evaluate_all_pairs",
          [](const PyScene& p, const Arr& x) {
            std::vector<Vec3> xv = positions_from(x, p.sc.natoms(), "x");
            std::vector<Vec3> F;
            ff::EnergyTerms t;
            // load_molecular_scene here always uses the default NonbondedOptions.
            const double E = ff::evaluate_all_pairs(p.sc.topology, ff::NonbondedOptions{}, xv, &F, &t);
            py::array_t<double> Fa({p.sc.natoms(), 3});
            std::memcpy(Fa.mutable_data(), F.data(), sizeof(double) * 3 * F.size());
            return py::make_tuple(E, Fa, t);
          },
          py::arg("x"), "Reference O(N²) evaluation (every pair, nothing skipped): (E, F, EnergyTerms).")
      .def_property_readonly("energy_terms", [](PyScene& p) { return p.ff().last_terms(); },
                             "Terms of the last compute (copy).")
      .def_property_readonly(
          "atom_forces",
          [](py::object self) {
            auto& p = self.cast<PyScene&>();
            const auto& F = p.ff().atom_forces();
            if (F.empty()) throw py::value_error("atom_forces: no compute() yet");
            return cview(F[0].data(), {static_cast<py::ssize_t>(F.size()), 3}, {3 * D, D}, self);
          },
          "(natoms, 3) read-only view of the per-atom forces of the last compute (kJ/mol/nm; without the "
          "terms inside one rigid body). Overwritten by the next compute.")
      .def(
          "atom_positions",
          [](const PyScene& p, const PyData& d, py::object out) {
            same_model(*p.model, d.model, "Data");
            const py::ssize_t n = p.sc.natoms();
            py::array_t<double, py::array::c_style> a;
            if (out.is_none()) {
              a = py::array_t<double, py::array::c_style>({n, py::ssize_t(3)});
            } else {
              if (!py::isinstance<py::array_t<double, py::array::c_style>>(out))
                throw py::value_error("out: expected a C-contiguous float64 array");
              a = out.cast<py::array_t<double, py::array::c_style>>();
              check_shape(a, n, 3, "out");
            }
            double* o = a.mutable_data();
            for (int i = 0; i < n; ++i) {
              const Vec3 x = p.sc.atom_position(d.d, i);
              o[3 * i] = x.x(), o[3 * i + 1] = x.y(), o[3 * i + 2] = x.z();
            }
            return a;
          },
          py::arg("data"), py::arg("out") = py::none(), "(natoms, 3) world atom positions (nm) from data's poses.")
      .def(
          "atom_position",
          [](const PyScene& p, const PyData& d, int atom) {
            same_model(*p.model, d.model, "Data");
            p.check_atom(atom);
            return to_np(p.sc.atom_position(d.d, atom));
          },
          py::arg("data"), py::arg("atom"))
      .def(
          "add_atom_force",
          [](const PyScene& p, const PyData& d, int atom, const Arr& F, PyState& s) {
            same_model(*p.model, d.model, "Data");
            same_model(*p.model, s.model, "State");
            p.check_atom(atom);
            p.sc.add_atom_force(d.d, atom, vec3(F, "F"), s.s.f_ext);
          },
          py::arg("data"), py::arg("atom"), py::arg("F"), py::arg("state"),
          "Adds a force F (kJ/mol/nm, world) on `atom` to state.f_ext (e.g. a pull).")
      .def(
          "set_rigid_regions",
          [](PyScene& p, const PyAdaptive& a) {
            same_model(*p.model, a.model, "AdaptiveData");
            p.ff().set_rigid_regions(a.ad.frontier_of_body);
          },
          py::arg("adaptive"),
          "Skip the terms inside each rigid region of the last selection (AdaptiveData.frontier_of_body).")
      .def("clear_rigid_regions", [](PyScene& p) { p.ff().clear_rigid_regions(); })
      .def_property_readonly("neighbour_rebuilds", [](PyScene& p) { return p.ff().neighbour_rebuilds(); })
      .def_property_readonly("neighbour_pairs", [](PyScene& p) { return p.ff().neighbour_pairs(); })
      .def("__repr__", [](const PyScene& p) {
        return "<haptree.MolecularScene '" + p.sc.name + "' atoms=" + std::to_string(p.sc.natoms()) +
               " dof=" + std::to_string(p.sc.dof()) + ">";
      });

  m.def(
      "load_molecular_scene",
      [](const std::string& name_or_path, bool with_force_field, bool free_root, bool require_hydrogens) {
        mol::SceneOptions o;
        o.with_force_field = with_force_field;
        o.torsion.root_joint = free_root ? JointType::kFree : JointType::kFixed;
        o.topology.require_hydrogens = require_hydrogens;
        auto p = std::make_shared<PyScene>();
        {
          py::gil_scoped_release nogil;
          p->sc = mol::load_molecular_scene(name_or_path, o);
        }
        p->model = hold(p->sc.model);
        return p;
      },
      py::arg("name_or_path"), py::arg("with_force_field") = true, py::arg("free_root") = false,
      py::arg("require_hydrogens") = false,
      "bacteriorhodopsin | ala20 | polyaniline | a PDB/mmCIF path -> MolecularScene (haptree/molecule/scene.hpp).");
  m.def("molecular_scene_names", &mol::molecular_scene_names);
  m.def("data_dir", &mol::data_dir, "The data directory (HAPTREE_DATA_DIR, next to the binaries, or the source tree).");
}
