// Child processes for the integration tests: argv[0] is a path (or, with search_path, a program on
// PATH such as `ip`); stdout and stderr go to `log`. Returns the pid, or -1.
#pragma once

#include <fcntl.h>
#include <spawn.h>
#include <sys/types.h>

#include <string>
#include <vector>

extern char** environ;

namespace haptree::testing {

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

}  // namespace haptree::testing
