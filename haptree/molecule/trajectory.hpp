// Trajectory files that VMD, MDAnalysis, MDTraj and PyMOL read: DCD (CHARMM/NAMD binary) and
// multi-model PDB (PdbTrajectoryWriter, scene.hpp). Positions come in nm and are written in Å.
//
// DCD layout (native byte order, every record framed by 4-byte Fortran length markers):
//   [84] "CORD" ICNTRL[20] [84]   ICNTRL: 0 NSET (frames), 1 ISTRT (first step), 2 NSAVC (steps
//        between frames), 3 NSTEP (steps covered), 4-7 0, 8 NAMNF (fixed atoms, 0), 9 DELTA
//        (float32, AKMA time units: 1 AKMA = 0.04888821 ps), 10 unit cell flag (0), 19 CHARMM
//        version (24)
//   [80·NTITLE+4] NTITLE title lines of 80 characters [..]
//   [4] NATOM [4]
//   per frame: [4N] X float32[N] [4N], the same for Y and Z (Å)
#pragma once

#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "haptree/molecule/scene.hpp"

namespace haptree::mol {

constexpr double kAkmaTimePs = 0.04888821;   // CHARMM's time unit: sqrt(Å² amu / (kcal/mol)) in ps

struct DcdHeader {
  int32_t natoms = 0;
  int32_t nframes = 0;     // NSET
  int32_t first_step = 0;  // ISTRT
  int32_t step_interval = 1;   // NSAVC
  float delta_akma = 0;    // time step, AKMA units
  std::vector<std::string> titles;
  bool unit_cell = false;
  double frame_interval_ps() const { return delta_akma * kAkmaTimePs * step_interval; }
};

class DcdWriter {
 public:
  // dt_ps: the simulation time step (written as DELTA in AKMA units); step_interval: steps between
  // frames (NSAVC). Throws std::runtime_error naming the file when it cannot be created.
  DcdWriter(const std::string& path, int natoms, double dt_ps, int step_interval, int first_step = 0,
            const std::string& title = "haptree trajectory");
  ~DcdWriter();
  DcdWriter(const DcdWriter&) = delete;
  DcdWriter& operator=(const DcdWriter&) = delete;
  // One frame (nm; written as float32 Å). Throws on a size mismatch or an I/O error. The header's
  // frame count is updated after every frame, so a file cut short by a crash is still readable.
  void write_frame(const std::vector<Vec3>& x_nm);
  void close();
  int frames() const { return frames_; }

 private:
  void patch_counts();
  std::string path_;
  std::FILE* f_ = nullptr;
  int natoms_;
  int step_interval_, first_step_;
  int frames_ = 0;
  std::vector<float> buf_;
};

struct DcdTrajectory {
  DcdHeader header;
  std::vector<std::vector<float>> xyz;   // per frame: x0 y0 z0 x1 ... (Å)
};
// Reads a DCD (either byte order; no fixed atoms). Throws std::runtime_error naming the file and the
// record that is wrong; sizes are checked against the file length before anything is allocated.
DcdTrajectory read_dcd(const std::string& path);

// One file of either format, chosen by extension (.dcd or .pdb), written every `every_steps` steps
// or every `every_time` scene time units (whichever is set; 0 = unset). For scenes without atoms
// (procedural, URDF) pass bodies_only: one pseudo-atom per body (CA of residue BOD k) at its origin,
// scene metres written as Å numerically (1 m -> 1 Å), so a 100-m tree shows at a viewable size.
struct TrajectoryOptions {
  std::string path;
  int every_steps = 100;
  double every_time = 0;     // > 0: overrides every_steps
  double dt = 0.0005;        // scene time step (DCD DELTA)
};
class TrajectoryRecorder {
 public:
  // structure: the molecule's atoms (names for the PDB); null for bodies (natoms pseudo-atoms).
  TrajectoryRecorder(const TrajectoryOptions& options, const Structure* structure, int natoms);
  ~TrajectoryRecorder();
  // Due at the first call, then each every_steps steps (or every_time of time) since the last frame.
  bool due(int64_t step, double time) const;
  // Writes the frame (positions in nm, or body origins in m for bodies) and remembers step/time.
  void write(const std::vector<Vec3>& x, int64_t step, double time);
  int frames() const;
  const std::string& path() const { return opt_.path; }
  void close();

 private:
  TrajectoryOptions opt_;
  Structure bodies_;   // pseudo-atoms when structure is null
  std::unique_ptr<DcdWriter> dcd_;
  std::unique_ptr<PdbTrajectoryWriter> pdb_;
  bool scale_bodies_ = false;
  bool any_ = false;
  int64_t last_step_ = 0;
  double last_time_ = 0;
  std::vector<Vec3> tmp_;
};

// "dcd" or "pdb" from the path's extension (case-insensitive); throws std::invalid_argument otherwise.
std::string trajectory_format(const std::string& path);

}  // namespace haptree::mol
