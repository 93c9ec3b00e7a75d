// Trajectories: DCD written and read back (own reader; MDAnalysis in trajectory_mdanalysis_test.py),
// multi-model PDB read back by gemmi, sim_server --trajectory, and trajectory_from_log on an LCM log.
#include <gtest/gtest.h>
#include <gemmi/pdb.hpp>
#include <lcm/lcm-cpp.hpp>

#include <sys/resource.h>
#include <unistd.h>

#include <csignal>

#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <cstring>
#include <random>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/dca.hpp"
#include "haptree/molecule/scene.hpp"
#include "haptree/molecule/trajectory.hpp"
#include "sim_server/sim_server.hpp"

namespace haptree::mol {
namespace {

namespace fs = std::filesystem;

std::string tmp(const std::string& name) {
  return (fs::temp_directory_path() / ("haptree_traj_" + std::to_string(::getpid()) + "_" + name)).string();
}

MolecularScene& ala20() {
  static MolecularScene s = [] {
    SceneOptions o;
    o.with_force_field = false;
    return load_molecular_scene("ala20", o);
  }();
  return s;
}

// Atom positions (nm) of configuration seed: the neutral one plus uniform ±0.4 rad on every joint.
std::vector<Vec3> frame(int seed, Data* d_out = nullptr) {
  MolecularScene& sc = ala20();
  std::mt19937 g(seed);
  std::uniform_real_distribution<double> u(-0.4, 0.4);
  Eigen::VectorXd q = neutral_configuration(*sc.model);
  for (int i = 0; i < q.size(); ++i) q[i] += u(g);
  Data d(*sc.model);
  forward_kinematics(*sc.model, d, q);
  std::vector<Vec3> x;
  sc.atom_positions(d, x);
  if (d_out) *d_out = d;
  return x;
}

TEST(Dcd, WrittenFramesReadBackAsFloat32Angstrom) {
  const std::string p = tmp("rt.dcd");
  const int n = ala20().natoms();
  std::vector<std::vector<Vec3>> frames = {frame(1), frame(2), frame(3)};
  {
    DcdWriter w(p, n, 0.0005, 100, 0, "ala20 test");
    for (const auto& f : frames) w.write_frame(f);
    EXPECT_EQ(w.frames(), 3);
  }
  const DcdTrajectory t = read_dcd(p);
  EXPECT_EQ(t.header.natoms, n);
  EXPECT_EQ(t.header.nframes, 3);
  EXPECT_EQ(t.header.step_interval, 100);
  EXPECT_FALSE(t.header.unit_cell);
  ASSERT_GE(t.header.titles.size(), 1u);
  EXPECT_EQ(t.header.titles[0], "ala20 test");
  // DELTA is float32 in AKMA units: 24-bit mantissa -> relative 6e-8.
  EXPECT_NEAR(t.header.frame_interval_ps(), 0.05, 0.05 * 1e-7);
  ASSERT_EQ(t.xyz.size(), 3u);
  for (size_t f = 0; f < 3; ++f)
    for (int a = 0; a < n; ++a)
      for (int c = 0; c < 3; ++c)   // the file holds exactly float(10 x): compare bit for bit
        ASSERT_EQ(t.xyz[f][3 * a + c], static_cast<float>(10.0 * frames[f][a][c])) << f << " " << a << " " << c;
  fs::remove(p);
}

TEST(Dcd, ReaderRefusesCorruptFilesNamingThem) {
  const std::string p = tmp("bad.dcd");
  const int n = ala20().natoms();
  {
    DcdWriter w(p, n, 0.001, 1);
    w.write_frame(frame(4));
    w.write_frame(frame(5));
  }
  std::string bytes;
  {
    std::ifstream in(p, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), {});
  }
  auto expect_refused = [&](const std::string& content, const char* what) {
    { std::ofstream o(p, std::ios::binary); o << content; }
    try {
      read_dcd(p);
      ADD_FAILURE() << what << ": accepted";
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find(p), std::string::npos) << e.what();
    }
  };
  expect_refused(bytes.substr(0, bytes.size() - 10), "truncated frame");
  std::string b = bytes;
  b[4] = 'X';
  expect_refused(b, "no CORD");
  b = bytes;
  const int32_t huge = 1 << 30;
  std::memcpy(&b[84 + 8 + 164 + 8 + 4], &huge, 4);   // NATOM: frames would be 12 GiB each
  expect_refused(b, "huge atom count");
  expect_refused("", "empty");
  fs::remove(p);
}

TEST(PdbTrajectory, MultiModelFileParsesBackWithGemmi) {
  const std::string p = tmp("mm.pdb");
  MolecularScene& sc = ala20();
  std::vector<std::vector<Vec3>> frames = {frame(6), frame(7), frame(8)};
  {
    TrajectoryOptions o;
    o.path = p;
    o.every_steps = 10;
    TrajectoryRecorder r(o, &sc.structure, sc.natoms());
    int64_t step = 0;
    for (const auto& f : frames) {
      ASSERT_TRUE(r.due(step, 0));
      r.write(f, step, 0);
      EXPECT_FALSE(r.due(step + 9, 0));
      step += 10;
    }
    EXPECT_EQ(r.frames(), 3);
  }
  const gemmi::Structure st = gemmi::read_pdb_file(p);
  ASSERT_EQ(st.models.size(), 3u);
  for (size_t m = 0; m < 3; ++m) {
    int a = 0;
    for (const auto& ch : st.models[m].chains)
      for (const auto& res : ch.residues)
        for (const auto& at : res.atoms) {
          ASSERT_LT(a, sc.natoms());
          EXPECT_EQ(at.name, sc.structure.atoms[a].name);
          // %8.3f: half a unit of the third decimal, plus double rounding.
          for (int c = 0; c < 3; ++c) EXPECT_NEAR(at.pos.at(c), 10.0 * frames[m][a][c], 5e-4 + 1e-9) << m << " " << a;
          ++a;
        }
    EXPECT_EQ(a, sc.natoms());
  }
  fs::remove(p);
}

TEST(SimServerTrajectory, RecordsEveryNStepsFromTheFirst) {
  const std::string p = tmp("sim.dcd");
  bus::Bus bus("memq://");
  SimServerOptions o;
  o.scene = "ala20";
  o.dt = 0.0005;
  o.steps = 250;
  o.trajectory = p;
  o.trajectory_every_steps = 100;
  {
    SimServer s(bus, o);
    std::atomic<bool> stop{false};
    s.run(stop);
  }
  const DcdTrajectory t = read_dcd(p);
  EXPECT_EQ(t.header.nframes, 3);   // steps 1, 101, 201
  EXPECT_EQ(t.header.natoms, ala20().natoms());
  EXPECT_NEAR(t.header.frame_interval_ps(), 0.05, 1e-8);
  // The first frame is one step from rest at the input conformation: atoms within 0.01 Å of the PDB.
  double worst = 0;
  for (int a = 0; a < t.header.natoms; ++a)
    for (int c = 0; c < 3; ++c)
      worst = std::max(worst, std::abs(t.xyz[0][3 * a + c] - 10.0 * ala20().structure.atoms[a].pos[c]));
  EXPECT_LT(worst, 0.01);
  fs::remove(p);
}

TEST(Dcd, WriteErrorsAreReportedNamingTheFile) {
  const std::string p = tmp("full_writer.dcd");
  fs::create_symlink("/dev/full", p);
  try {
    DcdWriter w(p, ala20().natoms(), 0.0005, 1);
    w.write_frame(frame(9));
    ADD_FAILURE() << "writing to a full disk succeeded";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(p), std::string::npos) << e.what();
  }
  fs::remove(p);
}

// A trajectory that cannot be written at start-up is refused in words; one that fails mid-session
// (here: the file-size limit, EFBIG) stops the recording, never the session.
TEST(SimServerTrajectory, WriteErrorStopsTheRecordingNotTheSession) {
  bus::Bus bus("memq://");
  SimServerOptions o;
  o.scene = "ala20";
  o.dt = 0.0005;
  o.steps = 300;
  o.trajectory_every_steps = 10;   // 30 frames of 2.6 KB
  o.trajectory = tmp("full.dcd");
  fs::create_symlink("/dev/full", o.trajectory);
  try {
    SimServer s(bus, o);
    ADD_FAILURE() << "a trajectory on a full disk was accepted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(o.trajectory), std::string::npos) << e.what();
  }
  fs::remove(o.trajectory);
  o.trajectory = tmp("limited.dcd");
  rlimit old{};
  ::getrlimit(RLIMIT_FSIZE, &old);
  auto old_handler = std::signal(SIGXFSZ, SIG_IGN);
  rlimit lim = old;
  lim.rlim_cur = 20000;   // bytes: the header and a few frames fit
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &lim), 0);
  int64_t steps = 0;
  {
    SimServer s(bus, o);
    std::atomic<bool> stop{false};
    s.run(stop);
    steps = s.steps_done();
  }
  ::setrlimit(RLIMIT_FSIZE, &old);
  std::signal(SIGXFSZ, old_handler);
  EXPECT_EQ(steps, 300);
  EXPECT_LE(fs::file_size(o.trajectory), 20000u);
  fs::remove(o.trajectory);
}

// An LCM log of scene states (as lcm-logger writes it) -> trajectory_from_log -> DCD: the atoms are
// those of the scene's own kinematics for the logged poses.
TEST(TrajectoryFromLog, MoleculeAtomsFromLoggedPoses) {
  const std::string log = tmp("session.lcmlog"), out = tmp("fromlog.dcd");
  MolecularScene& sc = ala20();
  std::vector<std::vector<Vec3>> want;
  {
    lcm::LogFile f(log, "w");
    ASSERT_TRUE(f.good());
    for (int i = 0; i < 6; ++i) {
      Data d(*sc.model);
      const auto x = frame(20 + i, &d);
      lcmt_scene_state s{};
      bus::stamp(s, 1);
      s.version = 1 + 50 * i;     // a state every 50 steps
      s.sim_time = 0.0005 * s.version;
      s.nbodies = sc.model->nbodies;
      s.body_active.assign(s.nbodies, 0);
      s.first_body = 0;
      s.total_bodies = s.nbodies;
      for (int k = 0; k < s.nbodies; ++k) {
        s.body_position.push_back({d.r[k].x(), d.r[k].y(), d.r[k].z()});
        const Quat q(d.R[k]);
        s.body_orientation.push_back({q.w(), q.x(), q.y(), q.z()});
      }
      std::vector<uint8_t> buf(static_cast<size_t>(s.getEncodedSize()));
      s.encode(buf.data(), 0, static_cast<int>(buf.size()));
      lcm::LogEvent ev{};
      ev.eventnum = i;
      ev.timestamp = s.utime;
      ev.channel = bus::channel::scene_state();
      ev.datalen = static_cast<int32_t>(buf.size());
      ev.data = buf.data();
      ASSERT_EQ(f.writeEvent(&ev), 0);
      if (i % 2 == 0) want.push_back(x);   // --every-steps 100 keeps states 0, 2, 4
    }
    // One coupling snapshot: it names the model (scene states do not).
    lcmt_coupling_snapshot snap{};
    bus::stamp(snap, 1);
    const uint64_t fp = sc.model->fingerprint;
    std::memcpy(&snap.model_fingerprint, &fp, 8);
    std::vector<uint8_t> buf(static_cast<size_t>(snap.getEncodedSize()));
    snap.encode(buf.data(), 0, static_cast<int>(buf.size()));
    lcm::LogEvent ev{};
    ev.eventnum = 6;
    ev.timestamp = snap.utime;
    ev.channel = bus::channel::coeffs(0);
    ev.datalen = static_cast<int32_t>(buf.size());
    ev.data = buf.data();
    ASSERT_EQ(f.writeEvent(&ev), 0);
  }
  const std::string cmd = std::string(HAPTREE_TRAJECTORY_FROM_LOG) + " " + log + " --out " + out +
                          " --scene ala20 --every-steps 100 > /dev/null";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  const DcdTrajectory t = read_dcd(out);
  ASSERT_EQ(t.header.nframes, 3);
  EXPECT_NEAR(t.header.frame_interval_ps(), 0.05, 1e-8);   // dt 0.0005 inferred from the log × 100
  // float32 of |x| ≤ 50 Å: ≤ 3e-6 Å; the quaternion round trip ~1e-14 Å.
  for (int f = 0; f < 3; ++f)
    for (int a = 0; a < t.header.natoms; ++a)
      for (int c = 0; c < 3; ++c) ASSERT_NEAR(t.xyz[f][3 * a + c], 10.0 * want[f][a][c], 1e-5) << f << " " << a;
  // A wrong scene is refused in words: another body count (bacteriorhodopsin), or the same body
  // count (polyaniline: 41 bodies like ala20) but another model fingerprint than the logged snapshot's.
  for (const char* wrong : {"bacteriorhodopsin", "polyaniline"}) {
    const std::string bad = std::string(HAPTREE_TRAJECTORY_FROM_LOG) + " " + log + " --out " + out + " --scene " +
                            wrong + " 2> " + out + ".err";
    EXPECT_NE(std::system(bad.c_str()), 0) << wrong;
    std::ifstream err(out + ".err");
    const std::string msg((std::istreambuf_iterator<char>(err)), {});
    EXPECT_NE(msg.find("wrong --scene"), std::string::npos) << msg;
  }
  fs::remove(log);
  fs::remove(out);
  fs::remove(out + ".err");
}

}  // namespace
}  // namespace haptree::mol
