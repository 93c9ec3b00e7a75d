#include "haptree/device/replay.hpp"

#include <lcm/lcm-cpp.hpp>

#include <cmath>
#include <memory>
#include <stdexcept>

#include "haptree/bus/auth.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/device/convert.hpp"

namespace haptree::device {

ReplayDevice::ReplayDevice(const DeviceSpec& spec, const std::string& log_path, const std::string& channel,
                           bool loop)
    : spec_(spec), loop_(loop) {
  lcm::LogFile log(log_path, "r");
  if (!log.good()) throw std::runtime_error(log_path + ": cannot open as an LCM log file");
  lcmt_device_state msg;
  int64_t t0 = 0;
  // A log of a keyed session (bus/auth.hpp) is read with the process's key: verified, trailer stripped.
  const auto key = bus::process_session_key();
  const std::unique_ptr<bus::Authenticator> auth = key ? std::make_unique<bus::Authenticator>(key) : nullptr;
  for (const lcm::LogEvent* ev = log.readNextEvent(); ev != nullptr; ev = log.readNextEvent()) {
    if (ev->channel != channel) continue;
    size_t len = static_cast<size_t>(ev->datalen);
    if ((auth && auth->verify(ev->channel, ev->data, len, &len) != bus::AuthVerdict::kOk) ||
        bus::decode_checked(ev->data, len, msg) != bus::DecodeResult::kOk) {
      ++rejected_;
      continue;
    }
    DeviceReading r;
    from_lcmt(msg, r);
    if (samples_.empty()) t0 = msg.utime;
    r.time_s = static_cast<double>(msg.utime - t0) * 1e-6;
    if (!samples_.empty() && r.time_s < samples_.back().time_s) r.time_s = samples_.back().time_s;
    samples_.push_back(r);
  }
  if (samples_.empty())
    throw std::runtime_error(log_path + ": no decodable lcmt_device_state on channel '" + channel + "' (" +
                             std::to_string(rejected_) + " rejected)");
}

Status ReplayDevice::read(double t, DeviceReading& out) noexcept {
  if (!std::isfinite(t)) return Status::Error("ReplayDevice::read: time is not finite");
  const double T = duration();
  bool finished = false;
  if (loop_ && T > 0) t = std::fmod(std::max(t, 0.0), T);
  else if (t > T) finished = true;
  if (cursor_ >= samples_.size() || samples_[cursor_].time_s > t) cursor_ = 0;  // time went back
  while (cursor_ + 1 < samples_.size() && samples_[cursor_ + 1].time_s <= t) ++cursor_;
  const int64_t seq = ++seq_;
  out = samples_[cursor_];
  out.seq = seq;
  return finished ? Status::Deactivate("replay finished") : Status::Ok();
}

Status ReplayDevice::write(const Vec3& f, const Vec3& tau) noexcept {
  if (!f.allFinite() || !tau.allFinite()) return Status::Error("ReplayDevice::write: non-finite force");
  force_ = f;
  return Status::Ok();
}

}  // namespace haptree::device
