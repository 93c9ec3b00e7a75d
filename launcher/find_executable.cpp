// The search of launcher/find_executable.hpp.
#include "launcher/find_executable.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <stdexcept>
#include <vector>

namespace haptree::launcher {

namespace {

bool executable(const std::string& p) {
  struct stat st {};
  return ::stat(p.c_str(), &st) == 0 && S_ISREG(st.st_mode) && ::access(p.c_str(), X_OK) == 0;
}

std::string dir_of(const std::string& p) {
  const auto s = p.find_last_of('/');
  return s == std::string::npos ? "." : p.substr(0, s);
}

}  // namespace

std::string find_executable(const std::string& name, const std::string& bin_dir, const std::string& argv0) {
  std::vector<std::string> tried;
  if (!bin_dir.empty()) {
    tried = {bin_dir + "/" + name, bin_dir + "/" + name + "/" + name};
  } else {
    std::string self = read_link("/proc/self/exe");
    if (self.empty()) self = argv0;
    const std::string d = dir_of(self);
    for (const std::string& dir : {d, d + "/..", d + "/../.."}) {
      tried.push_back(dir + "/" + name);
      tried.push_back(dir + "/" + name + "/" + name);
    }
  }
  for (const auto& p : tried)
    if (executable(p)) return p;
  std::string msg = "cannot find the executable '" + name + "' (tried";
  for (const auto& p : tried) msg += " " + p;
  throw std::runtime_error(msg + "); build it (cmake --build <dir> --target " + name + ") or pass --bin-dir");
}

std::string read_link(const std::string& p) {
  char buf[4096];
  const ssize_t n = ::readlink(p.c_str(), buf, sizeof(buf) - 1);
  if (n <= 0) return "";
  buf[n] = 0;
  return buf;
}

}  // namespace haptree::launcher
