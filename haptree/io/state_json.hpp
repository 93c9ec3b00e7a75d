// JSON states and results keyed by joint name (the haptree-fd format).
//
// State document: {"q": {...}, "qd": {...}, "tau": {...}, "f_ext": {...}} — every section optional.
//   q, qd, tau are keyed by joint name; a missing joint is 0 (q: the neutral configuration, i.e.
//   angle 0 and identity quaternions). 1-DOF joints (revolute, prismatic) take a number (or a
//   one-element list); multi-DOF joints take a list:
//     spherical: q = [qw, qx, qy, qz] (normalised on input; must not be zero),
//                qd = angular velocity [wx, wy, wz] in the child body frame, tau = moment [3] in
//                the child body frame;
//     free:      q = [x, y, z, qw, qx, qy, qz] (position and orientation of the child frame in
//                the joint frame), qd = [wx, wy, wz, vx, vy, vz] (angular velocity, then velocity
//                of the body origin, both in the child body frame), tau = [moment; force] in the
//                child body frame.
//   Fixed joints carry no values (naming one is an error), unknown joint names are errors.
//   f_ext is keyed by body (link) name: [mx, my, mz, fx, fy, fz], world axes, moment about the
//   body origin (its joint point).
// Result: {"qdd": {"<joint>": value or [list], ...}} over the joints with DOFs, in model order.
#pragma once

#include <string>

#include <nlohmann/json.hpp>

#include "haptree/data.hpp"

namespace haptree::io {

struct StateJsonError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// `source` names the document in error messages (one line: "<source>: <section>.<name>: <what>").
State state_from_json(const Model& model, const nlohmann::json& doc, const std::string& source);
State load_state_json(const Model& model, const std::string& path);

nlohmann::ordered_json qdd_to_json(const Model& model, const Eigen::VectorXd& qdd);
// Serialises with full double precision (%.17g) and the given indent (-1: one line).
std::string dump_json_exact(const nlohmann::ordered_json& j, int indent = 2);

}  // namespace haptree::io
