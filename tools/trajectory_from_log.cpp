// trajectory_from_log: an LCM log of a session (lcm-logger) -> a trajectory file (.dcd or .pdb) that
// VMD, MDAnalysis and MDTraj read. Reads the HAPTREE_SCENE_STATE messages (body poses), places the
// atoms with the scene's torsion model (molecules) or writes one pseudo-atom per body (other scenes).
// Frames: every --every-steps steps or --every-time scene time of the logged states; the log holds
// the states at sim_server's --display-rate-hz, so the finest interval is that rate.
#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/spdlog.h>

#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/molecule/body_poses.hpp"
#include "haptree/molecule/scene.hpp"
#include "haptree/molecule/trajectory.hpp"

int main(int argc, char** argv) {
  CLI::App app{"trajectory_from_log: HAPTREE_SCENE_STATE of an LCM log -> DCD or multi-model PDB (angstrom).\n"
               "Molecules: atoms placed from the body poses with the torsion model of --scene. Other scenes:\n"
               "one pseudo-atom per body at its origin (1 scene metre written as 1 angstrom)."};
  std::string log, out, scene, suffix;
  int every_steps = 1;
  double every_time = 0, dt = 0;
  app.add_option("log", log, "LCM log file (lcm-logger)")->required()->check(CLI::ExistingFile);
  app.add_option("--out,-o", out, "trajectory to write: .dcd or .pdb")->required();
  app.add_option("--scene", scene,
                 "the session's molecule (name or PDB path) to place atoms; omit for body origins");
  app.add_option("--channel-suffix", suffix, "channel suffix of the session (e.g. _R1234 of haptree_run --processes)");
  app.add_option("--every-steps", every_steps, "simulation steps between frames (of the logged states)")
      ->check(CLI::Range(1, 100000000))->capture_default_str();
  app.add_option("--every-time", every_time, "> 0: scene time between frames instead (ps for molecules)")
      ->check(CLI::NonNegativeNumber)->capture_default_str();
  app.add_option("--dt", dt, "simulation time step for the DCD header (default: from the logged states)")
      ->check(CLI::NonNegativeNumber);
  CLI11_PARSE(app, argc, argv);
  try {
    (void)haptree::mol::trajectory_format(out);
    std::unique_ptr<haptree::mol::MolecularScene> mol;
    if (!scene.empty()) {
      haptree::mol::SceneOptions so;
      so.with_force_field = false;
      mol = std::make_unique<haptree::mol::MolecularScene>(haptree::mol::load_molecular_scene(scene, so));
    }
    const std::string channel = haptree::bus::channel::scene_state(suffix);
    // Pass 1: the states (and dt from the first two, for the DCD header).
    std::vector<haptree::lcmt_scene_state> states;
    int64_t bad = 0, fingerprint = 0;   // model fingerprint from a logged coupling snapshot, if any
    const std::string coeffs_prefix = "HAPTREE_COEFFS_";
    {
      lcm::LogFile file(log, "r");
      if (!file.good()) throw std::runtime_error(log + ": cannot open as an LCM log");
      haptree::lcmt_scene_state s;
      haptree::lcmt_coupling_snapshot snap;
      for (const lcm::LogEvent* ev = file.readNextEvent(); ev != nullptr; ev = file.readNextEvent()) {
        if (fingerprint == 0 && ev->channel.compare(0, coeffs_prefix.size(), coeffs_prefix) == 0 &&
            haptree::bus::decode_checked(ev->data, static_cast<size_t>(ev->datalen), snap) ==
                haptree::bus::DecodeResult::kOk)
          fingerprint = snap.model_fingerprint;
        if (ev->channel != channel) continue;
        if (haptree::bus::decode_checked(ev->data, static_cast<size_t>(ev->datalen), s) != haptree::bus::DecodeResult::kOk) {
          ++bad;
          continue;
        }
        states.push_back(s);
      }
    }
    if (states.empty())
      throw std::runtime_error(log + ": no decodable " + channel + " message (" + std::to_string(bad) +
                               " rejected); wrong --channel-suffix?");
    if (dt <= 0) {
      for (size_t i = 1; i < states.size() && dt <= 0; ++i)
        if (states[i].version > states[i - 1].version && states[i].sim_time > states[i - 1].sim_time)
          dt = (states[i].sim_time - states[i - 1].sim_time) / double(states[i].version - states[i - 1].version);
      if (dt <= 0) dt = 0.001;
    }
    const int nbodies = states.front().nbodies;
    if (mol && nbodies != mol->model->nbodies)
      throw std::runtime_error(log + ": scene states have " + std::to_string(nbodies) + " bodies, '" + scene +
                               "' has " + std::to_string(mol->model->nbodies) + ": wrong --scene?");
    // Scene states carry no model id; a logged coupling snapshot does (a body count can coincide).
    if (mol && fingerprint != 0 && static_cast<uint64_t>(fingerprint) != mol->model->fingerprint)
      throw std::runtime_error(log + ": the logged session's model (fingerprint " + fmt::format("{:016x}", static_cast<uint64_t>(fingerprint)) +
                               ") is not '" + scene + "' (" + fmt::format("{:016x}", mol->model->fingerprint) + "): wrong --scene?");
    haptree::mol::TrajectoryOptions to;
    to.path = out;
    to.every_steps = every_steps;
    to.every_time = every_time;
    to.dt = dt;
    haptree::mol::TrajectoryRecorder rec(to, mol ? &mol->structure : nullptr, mol ? mol->natoms() : nbodies - 1);
    std::vector<haptree::Vec3> r, x;
    std::vector<haptree::Quat> q;
    int64_t skipped = 0;
    for (const auto& s : states) {
      if (s.nbodies != nbodies) { ++skipped; continue; }
      if (!rec.due(s.version, s.sim_time)) continue;
      r.resize(static_cast<size_t>(nbodies));
      q.resize(static_cast<size_t>(nbodies));
      for (int k = 0; k < nbodies; ++k) {
        r[k] = haptree::Vec3(s.body_position[k][0], s.body_position[k][1], s.body_position[k][2]);
        q[k] = haptree::Quat(s.body_orientation[k][0], s.body_orientation[k][1], s.body_orientation[k][2],
                             s.body_orientation[k][3]);
      }
      if (mol) {
        haptree::mol::atom_positions_from_body_poses(mol->torsion, r, q, x);
      } else {
        x.assign(r.begin() + 1, r.end());   // body 0 is the world
      }
      rec.write(x, s.version, s.sim_time);
    }
    rec.close();
    std::printf("%s: %d frames of %d %s from %zu scene states (steps %lld..%lld, dt %g)%s\n", out.c_str(), rec.frames(),
                mol ? mol->natoms() : nbodies - 1, mol ? "atoms" : "bodies", states.size(),
                static_cast<long long>(states.front().version), static_cast<long long>(states.back().version), dt,
                skipped ? (" — " + std::to_string(skipped) + " states with another body count skipped").c_str() : "");
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "trajectory_from_log: %s\n", e.what());
    return 1;
  }
}
