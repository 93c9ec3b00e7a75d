// Every channel of a Bus into an LCM log file, as lcm-logger would (the replay tests). Declare it after
// the Bus (and stop the bus's handler thread first): its subscription lives as long as the Bus.
#pragma once

#include <lcm/lcm-cpp.hpp>

#include <cstdint>
#include <memory>
#include <mutex>
#include <string>

#include "haptree/bus/bus.hpp"

namespace haptree::testing {

class LcmLogRecorder {
 public:
  LcmLogRecorder(bus::Bus& bus, const std::string& path) : log_(std::make_unique<lcm::LogFile>(path, "w")) {
    bus.subscribe_raw(".*", [this](const void* data, uint32_t size, const std::string& ch) {
      std::lock_guard<std::mutex> lock(mu_);
      lcm::LogEvent ev;
      ev.eventnum = n_++;
      ev.timestamp = bus::now_utime();
      ev.channel = ch;
      ev.datalen = static_cast<int32_t>(size);
      ev.data = const_cast<void*>(data);
      if (log_) log_->writeEvent(&ev);
    });
  }
  bool good() const { return log_ && log_->good(); }
  // Flushes and closes the file; what arrives later is not recorded.
  void close() {
    std::lock_guard<std::mutex> lock(mu_);
    log_.reset();
  }

 private:
  std::mutex mu_;
  int64_t n_ = 0;
  std::unique_ptr<lcm::LogFile> log_;
};

}  // namespace haptree::testing
