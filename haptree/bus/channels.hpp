// Channel names of the haptree bus (docs/processes.md). Uppercase, with the device/user id.
// LCM channel names are at most 63 characters; every function here throws std::invalid_argument beyond.
#pragma once

#include <string>

namespace haptree::bus::channel {

constexpr int kMaxChannelLength = 63;  // LCM_MAX_CHANNEL_NAME_LENGTH

std::string device_state(int device_id, const std::string& suffix = "");  // HAPTREE_DEVICE_STATE_<id>
std::string feedback(int device_id, const std::string& suffix = "");      // HAPTREE_FEEDBACK_<id>
std::string user_force(int user_id, const std::string& suffix = "");      // HAPTREE_USER_FORCE_<id>
std::string coeffs(int user_id, const std::string& suffix = "");          // HAPTREE_COEFFS_<id>
std::string pointer(int user_id, const std::string& suffix = "");         // HAPTREE_POINTER_<id> (viewer -> browser device)
std::string scene_state(const std::string& suffix = "");                  // HAPTREE_SCENE_STATE
std::string stats(const std::string& process, const std::string& suffix = "");  // HAPTREE_STATS_<PROCESS>
std::string coupler_settings(int user_id, const std::string& suffix = "");   // HAPTREE_COUPLER_SETTINGS_<id>

// Throws std::invalid_argument when `name` is empty, longer than 63 characters, or has characters
// outside [A-Za-z0-9_]. Returns name.
const std::string& checked(const std::string& name);

}  // namespace haptree::bus::channel
