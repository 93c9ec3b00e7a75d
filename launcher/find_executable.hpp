#pragma once
// Where a program finds the other programs of the session (sim_server, coupler, device_bridge, viewer,
// replay_coupling): an explicit folder, or next to itself, which covers both layouts the programs run
// from. Installed, every program is in bin/. In a build tree each program is in the folder of its
// source, <build>/<folder>/<name> (build/launcher/haptree_run, build/sim_server/sim_server,
// build/tools/replay_coupling, build/tools/faults/chaos_soak).
#include <string>

namespace haptree::launcher {

// bin_dir given: bin_dir/<name>, then bin_dir/<name>/<name>. Otherwise from the folder D of this
// executable (/proc/self/exe, else argv0): D, D/.. and D/../.., each as <dir>/<name> and then
// <dir>/<name>/<name>. The first regular, executable file wins. Throws std::runtime_error naming every
// place tried and how to build the program.
std::string find_executable(const std::string& name, const std::string& bin_dir, const std::string& argv0 = "");

// The target of the symbolic link p (readlink(2)); empty when p is none or cannot be read.
std::string read_link(const std::string& p);

}  // namespace haptree::launcher
