#pragma once
// A URDF robot as it looks: the <visual> elements of its links (meshes: STL binary and ASCII, Collada
// DAE, Wavefront OBJ; boxes, cylinders, spheres; with their origins, mesh scales and material colours)
// as one triangle mesh per body, in that body's frame, for the viewer to draw at the live body poses.
// Links lumped into their parent (massless links on fixed joints: haptree/io/urdf.hpp) bring their
// visuals to that body through the fixed joints' origins.
// Mesh file names: `package://PKG/path` and relative paths are looked up in each mesh directory (PKG/path,
// then path), then beside the URDF; absolute paths and file:// as given. A mesh that cannot be found
// or read is drawn as a sphere of the body's size (the solid sphere of its mass and inertia), with
// one warning per file.
#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "haptree/model.hpp"

namespace haptree {

struct TriMesh {
  std::vector<Vec3> v;
  std::vector<std::array<uint32_t, 3>> f;
};

// Reads a mesh file by its extension (.stl binary or ASCII, .obj, .dae; case-insensitive): triangles in
// the file's own units (Collada: its <unit meter> applied, node transforms applied). Throws
// std::runtime_error "<file>: <what>" on a missing, unreadable or malformed file.
TriMesh load_mesh_file(const std::string& path);

// One body's visuals: flat-shaded triangles (3 vertices each, with the face normal and the material's
// colour), positions in the body frame, metres.
struct BodyVisual {
  int body = 0;
  std::vector<float> position, normal, color;   // 9 floats per triangle each
};

struct RobotVisuals {
  std::vector<BodyVisual> bodies;   // only bodies with something to draw
  int meshes = 0, primitives = 0, missing = 0;
  std::vector<std::string> warnings;   // one per missing mesh file
};

// The visuals of the URDF file `urdf_path`, whose model (io::load_urdf of the same file) is `model`.
// Throws std::runtime_error only for an unreadable URDF; missing meshes are warnings.
RobotVisuals load_robot_visuals(const std::string& urdf_path, const Model& model,
                                const std::vector<std::string>& mesh_paths);

}  // namespace haptree
