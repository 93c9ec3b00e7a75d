// Helpers for the real-process integration tests: spawning children with their output in a log, and
// the scripted device's grab geometry.
#pragma once

#include <fcntl.h>
#include <spawn.h>
#include <sys/types.h>

#include <string>
#include <vector>

#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"

extern char** environ;

namespace haptree::testing {

// argv[0] is a path (or, with search_path, a program on PATH such as `ip`); stdout and stderr go to
// `log`. Returns the pid, or -1.
inline pid_t spawn_logged(const std::vector<std::string>& args, const std::string& log,
                          bool search_path = false) {
  std::vector<char*> argv;
  for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  posix_spawn_file_actions_addopen(&fa, 1, log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_adddup2(&fa, 1, 2);
  pid_t pid = -1;
  const int rc = search_path ? posix_spawnp(&pid, argv[0], &fa, nullptr, argv.data(), environ)
                             : posix_spawn(&pid, argv[0], &fa, nullptr, argv.data(), environ);
  if (rc != 0) pid = -1;
  posix_spawn_file_actions_destroy(&fa);
  return pid;
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

}  // namespace haptree::testing
