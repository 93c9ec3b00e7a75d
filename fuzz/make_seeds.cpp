// Writes the generated seeds of the LCM fuzz targets (one small, valid message of each lcmt type, and
// real coupling snapshots from small scenes), in the targets' input format (lcm_input.hpp):
//   fuzz_make_seeds OUT_DIR      → OUT_DIR/lcm_decode/*, OUT_DIR/coupling_snapshot/*
// scripts/fuzz.sh seeds writes them into fuzz/corpus/; the CTest smoke runs also start from a fresh set
// written into the build tree, so they follow the current message layouts.
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "haptree/bus/snapshot.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/coupling.hpp"
#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"

namespace fs = std::filesystem;
using namespace haptree;

namespace {

template <class T>
void write(const fs::path& dir, const std::string& name, int selector, const T& msg) {
  const int n = msg.getEncodedSize();
  std::vector<uint8_t> buf(static_cast<size_t>(n));
  if (msg.encode(buf.data(), 0, n) != n) throw std::runtime_error("encode failed: " + name);
  fs::create_directories(dir);
  std::ofstream out(dir / name, std::ios::binary);
  if (selector >= 0) out.put(static_cast<char>(selector));
  out.write(reinterpret_cast<const char*>(buf.data()) + 8, n - 8);   // without the fingerprint
  if (!out) throw std::runtime_error("cannot write " + (dir / name).string());
}

lcmt_coupling_snapshot snapshot_of(const std::string& scene, int n, const std::vector<int>& bodies) {
  SceneOptions o;
  o.n = n;
  o.seed = 5;
  o.mixed_joints = scene != "binary_tree";
  const auto model = make_scene(scene, o);
  const Model& m = *model;
  State st(m);
  st.q = neutral_configuration(m);
  for (int i = 0; i < m.nv; ++i) st.qd[i] = 0.1 * (i % 3) - 0.1;
  Data d(m);
  forward_dynamics(m, d, st);
  std::vector<Grab> grabs;
  for (int b : bodies) grabs.push_back(make_grab(d, b, Vec3(0.05, -0.02, 0.01)));
  CouplingSnapshot snap;
  make_coupling_snapshot(m, d, grabs, {}, 42, 0.125, snap);
  lcmt_coupling_snapshot msg;
  bus::to_lcmt(snap, msg);
  bus::stamp(msg, 1, 1700000000000000);
  msg.user_id = 0;
  return msg;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: %s OUT_DIR\n", argv[0]);
    return 2;
  }
  const fs::path out(argv[1]);
  try {
    const fs::path lcm = out / "lcm_decode", cs = out / "coupling_snapshot";
    const auto s1 = snapshot_of("chain", 4, {4});
    const auto s2 = snapshot_of("binary_tree", 7, {5, 7});
    const auto s3 = snapshot_of("random_tree", 6, {3, 3});
    write(cs, "chain4_one_grab", -1, s1);
    write(cs, "binary_tree7_two_grabs", -1, s2);
    write(cs, "random_tree6_same_body_twice", -1, s3);
    write(lcm, "coupling_snapshot_chain4", 0, s1);

    lcmt_device_state ds{};
    bus::stamp(ds, 1, 1700000000000001);
    ds.seq = 7;
    ds.device_id = 0;
    ds.position_m[0] = 0.01;
    ds.orientation[0] = 1;
    ds.linear_velocity_mps[2] = -0.05;
    ds.buttons = 1;
    write(lcm, "device_state", 1, ds);

    lcmt_feedback fb{};
    bus::stamp(fb, 1, 1700000000000002);
    fb.seq = 9;
    fb.echo_device_seq = 7;
    fb.snapshot_version = 42;
    fb.force_n[1] = 1.5;
    fb.flags = lcmt_feedback::FLAG_CLAMPED;
    write(lcm, "feedback", 2, fb);

    lcmt_process_stats ps{};
    bus::stamp(ps, 1, 1700000000000003);
    ps.seq = 3;
    ps.process_name = "coupler";
    ps.loop_rate_hz = 10000;
    ps.snapshot_age_ms = 1.5;
    ps.n_extra = 2;
    ps.extra_names = {"restarts", "p99_us"};
    ps.extra_values = {0, 42.5};
    write(lcm, "process_stats", 3, ps);

    lcmt_scene_state ss{};
    bus::stamp(ss, 1, 1700000000000004);
    ss.version = 42;
    ss.sim_time = 0.125;
    ss.nbodies = 2;
    ss.body_active.assign(ss.nbodies, 0);
    ss.total_bodies = ss.nbodies;
    ss.body_position = {{0, 0, 0}, {0.1, 0.2, 0.3}};
    ss.body_orientation = {{1, 0, 0, 0}, {0, 1, 0, 0}};
    ss.active_dofs = 12;
    write(lcm, "scene_state", 4, ss);

    lcmt_user_force uf{};
    bus::stamp(uf, 1, 1700000000000005);
    uf.seq = 11;
    uf.grab_body = 4;
    uf.grab_point[0] = 0.3;
    uf.force[4] = -2;
    uf.snapshot_version = 42;
    uf.active = true;
    write(lcm, "user_force", 5, uf);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "fuzz_make_seeds: %s\n", e.what());
    return 1;
  }
  std::printf("seeds written under %s\n", out.c_str());
  return 0;
}
