#include "haptree/device/vendor_library.hpp"

#include <dlfcn.h>

#include <atomic>

namespace haptree::device {

// Never unloaded by the destructor: a vendor library may leave threads or atexit handlers behind that
// would run into unmapped code; the process's end releases it.
VendorLibrary::~VendorLibrary() = default;

bool VendorLibrary::open(const std::vector<std::string>& names, const std::string& install_hint) {
  close();
  hint_ = install_hint;
  std::string tried, why;
  for (const auto& n : names) {
    dlerror();
    handle_ = ::dlopen(n.c_str(), RTLD_NOW | RTLD_LOCAL);
    if (handle_) {
      path_ = n;
      error_.clear();
      return true;
    }
    const char* e = dlerror();
    tried += (tried.empty() ? "" : ", ") + n;
    why = e ? e : "not found";
  }
  error_ = "cannot load " + tried + " (" + why + "): " + install_hint;
  return false;
}

void* VendorLibrary::symbol(const char* name, bool required) {
  if (!handle_) return nullptr;
  dlerror();
  void* p = ::dlsym(handle_, name);
  if (!p && required)
    error_ = path_ + " has no symbol " + name + ": not the expected vendor library or version (" + hint_ + ")";
  return p;
}

void VendorLibrary::close() noexcept {
  if (handle_) ::dlclose(handle_);
  handle_ = nullptr;
}

namespace {
constexpr int kMaxDevices = 16;
struct Slot {
  std::atomic<void*> device{nullptr};
  std::atomic<EmergencyStop> fn{nullptr};
};
Slot g_slots[kMaxDevices];
}  // namespace

void register_emergency_stop(void* device, EmergencyStop fn) noexcept {
  for (auto& s : g_slots) {
    void* expected = nullptr;
    if (s.device.compare_exchange_strong(expected, device)) {
      s.fn.store(fn);
      return;
    }
  }
}

void unregister_emergency_stop(void* device) noexcept {
  for (auto& s : g_slots)
    if (s.device.load() == device) {
      s.fn.store(nullptr);
      s.device.store(nullptr);
    }
}

void emergency_stop_devices() noexcept {
  for (auto& s : g_slots) {
    void* d = s.device.load();
    const EmergencyStop fn = s.fn.exchange(nullptr);   // once
    if (d && fn) fn(d);
  }
}

}  // namespace haptree::device
