// A vendor's C library loaded at run time (dlopen/dlsym): the build never needs the SDK, and a machine
// without it gets one line saying which library is missing and what to install.
#pragma once

#include <string>
#include <vector>

namespace haptree::device {

class VendorLibrary {
 public:
  VendorLibrary() = default;
  VendorLibrary(const VendorLibrary&) = delete;
  VendorLibrary& operator=(const VendorLibrary&) = delete;
  ~VendorLibrary();
  // Tries each name in turn (a path, or a name the dynamic loader searches). False with error() set to
  // one line naming what was tried, the loader's reason and `install_hint`.
  bool open(const std::vector<std::string>& names, const std::string& install_hint);
  // A symbol by name; nullptr (and, if required, error() naming the library and the symbol) if absent.
  void* symbol(const char* name, bool required = true);
  template <class F>
  bool bind(F& fn, const char* name, bool required = true) {
    fn = reinterpret_cast<F>(symbol(name, required));
    return fn != nullptr || !required;
  }
  bool loaded() const noexcept { return handle_ != nullptr; }
  const std::string& path() const noexcept { return path_; }
  const std::string& error() const noexcept { return error_; }
  // Unloads (after the device is closed: no vendor thread may still run the library's code). The
  // destructor does not: the process's end does.
  void close() noexcept;

 private:
  void* handle_ = nullptr;
  std::string path_, error_, hint_;
};

// Emergency stop of the open vendor devices from a fatal signal or std::terminate: each open real device
// registers a function that writes zero force and torque and turns force output off with as little as
// possible (atomics, then the vendor's own calls). A fixed table: no allocation in the handler.
using EmergencyStop = void (*)(void* device) noexcept;
void register_emergency_stop(void* device, EmergencyStop fn) noexcept;
void unregister_emergency_stop(void* device) noexcept;
// Calls every registered function once; safe to call from a signal handler as far as the vendor allows.
void emergency_stop_devices() noexcept;

}  // namespace haptree::device
