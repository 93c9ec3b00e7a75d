// Helpers for the real-process integration tests: spawning children with their output in a log, and
// the scripted device's grab geometry.
#pragma once

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/types.h>
#include <sys/wait.h>

#include <string>
#include <vector>

#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"

extern char** environ;

namespace haptree::testing {

// argv[0] is a path (or, with search_path, a program on PATH such as `ip`); stdout and stderr go to
// `log`; the environment is this process's, or `envp` (null-terminated) where given. Returns the pid,
// or -1.
inline pid_t spawn_logged(const std::vector<std::string>& args, const std::string& log,
                          bool search_path = false, char* const* envp = nullptr) {
  std::vector<char*> argv;
  for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  posix_spawn_file_actions_addopen(&fa, 1, log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_adddup2(&fa, 1, 2);
  pid_t pid = -1;
  char* const* env = envp ? envp : environ;
  const int rc = search_path ? posix_spawnp(&pid, argv[0], &fa, nullptr, argv.data(), env)
                             : posix_spawn(&pid, argv[0], &fa, nullptr, argv.data(), env);
  if (rc != 0) pid = -1;
  posix_spawn_file_actions_destroy(&fa);
  return pid;
}

// Waits for child p; its exit code, 128 + signal if a signal ended it.
inline int reap(pid_t p) {
  int st = 0;
  ::waitpid(p, &st, 0);
  return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
}

// SIGTERM, then reap.
inline int stop_and_reap(pid_t p) {
  ::kill(p, SIGTERM);
  return reap(p);
}

// Coupler offset that maps the scripted device's grab waypoint (0, 0, 0.01 m, position scale 10)
// onto the last body of protein_like(32); sets *body to that body.
inline Vec3 grab_offset_protein32(int* body) {
  SceneOptions so;
  so.n = 32;
  auto m = make_scene("protein_like", so);
  Data d(*m);
  State s(*m);
  forward_kinematics(*m, d, s.q);
  *body = m->nbodies - 1;
  return d.r[*body] - 10.0 * Vec3(0, 0, 0.01);
}

inline std::vector<std::string> grab_offset_args(int* body) {
  const Vec3 o = grab_offset_protein32(body);
  return {"--offset", std::to_string(o.x()), std::to_string(o.y()), std::to_string(o.z())};
}

// The three processes of a --shm session on a tcpq hub (the shm tests): sim_server on protein_like(32) at
// 1 kHz, a sleeping 5 kHz coupler (stale after 50 ms) whose offset puts the scripted device's grab on the
// last body, and a scripted device_bridge (approach 0.2 s, then a 60 s hold). Paths are the executables.
struct ShmSessionArgs {
  std::vector<std::string> sim, coupler, device;
};
inline ShmSessionArgs shm_session_args(const std::string& sim_server, const std::string& coupler,
                                       const std::string& device_bridge, const std::string& lcm_url,
                                       const std::string& suffix) {
  int body = 0;
  const std::vector<std::string> offset = grab_offset_args(&body);
  const std::vector<std::string> common = {"--lcm-url", lcm_url, "--channel-suffix", suffix};
  ShmSessionArgs a;
  a.sim = {sim_server, "--scene", "protein_like", "--n", "32", "--rate-hz", "1000"};
  a.coupler = {coupler, "--grab-body", std::to_string(body), "--rate-hz", "5000", "--sleep", "--stale-after-s", "0.05",
               "--shm"};
  a.coupler.insert(a.coupler.end(), offset.begin(), offset.end());
  a.device = {device_bridge, "--shm", "--device-option", "approach_s=0.2", "--device-option", "hold_s=60"};
  for (auto* v : {&a.sim, &a.coupler, &a.device}) v->insert(v->end(), common.begin(), common.end());
  return a;
}

}  // namespace haptree::testing
