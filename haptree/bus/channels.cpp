#include "haptree/bus/channels.hpp"

#include <cctype>
#include <stdexcept>

namespace haptree::bus::channel {

const std::string& checked(const std::string& name) {
  if (name.empty()) throw std::invalid_argument("channel name is empty");
  if (static_cast<int>(name.size()) > kMaxChannelLength)
    throw std::invalid_argument("channel name '" + name + "' has " + std::to_string(name.size()) +
                                " characters; LCM allows at most 63");
  for (char c : name)
    if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_'))
      throw std::invalid_argument("channel name '" + name + "': character '" + std::string(1, c) +
                                  "' is not in [A-Za-z0-9_]");
  return name;
}

namespace {
std::string with_id(const char* base, int id, const std::string& suffix) {
  if (id < 0) throw std::invalid_argument(std::string(base) + ": id " + std::to_string(id) + " is negative");
  std::string n = std::string(base) + std::to_string(id) + suffix;
  checked(n);
  return n;
}
}  // namespace

std::string device_state(int id, const std::string& s) { return with_id("HAPTREE_DEVICE_STATE_", id, s); }
std::string feedback(int id, const std::string& s) { return with_id("HAPTREE_FEEDBACK_", id, s); }
std::string user_force(int id, const std::string& s) { return with_id("HAPTREE_USER_FORCE_", id, s); }
std::string coeffs(int id, const std::string& s) { return with_id("HAPTREE_COEFFS_", id, s); }
std::string coupler_settings(int id, const std::string& s) { return with_id("HAPTREE_COUPLER_SETTINGS_", id, s); }
std::string pointer(int id, const std::string& s) { return with_id("HAPTREE_POINTER_", id, s); }
std::string scene_state(const std::string& s) {
  std::string n = "HAPTREE_SCENE_STATE" + s;
  checked(n);
  return n;
}
std::string stats(const std::string& process, const std::string& s) {
  std::string up;
  for (char c : process) up += static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  std::string n = "HAPTREE_STATS_" + up + s;
  checked(n);
  return n;
}

}  // namespace haptree::bus::channel
