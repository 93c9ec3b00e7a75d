#include "device_bridge/device_bridge.hpp"

#include <spdlog/spdlog.h>

#include <chrono>
#include <stdexcept>
#include <thread>

#include "haptree/bus/channels.hpp"
#include "haptree/bus/wire.hpp"
#include "haptree/device/convert.hpp"
#include "haptree/device/registry.hpp"
#include "haptree/safety.hpp"

namespace haptree {

using Clock = std::chrono::steady_clock;
static const Clock::time_point kEpoch = Clock::now();
static double now_s() { return std::chrono::duration<double>(Clock::now() - kEpoch).count(); }

DeviceBridge::DeviceBridge(bus::Bus& bus, const DeviceBridgeOptions& options) : bus_(bus), opt_(options) {
  device::DeviceConfig cfg;
  cfg.spec.name = opt_.kind + "_" + std::to_string(opt_.device);
  cfg.spec.max_force_n = opt_.max_force_n;
  cfg.spec.rate_hz = opt_.rate_hz;
  cfg.options = opt_.options;
  cfg.bus = &bus_;   // devices fed from the bus (browser) subscribe here
  cfg.device_id = opt_.device;
  cfg.channel_suffix = opt_.channel_suffix;
  device_ = device::make_device(opt_.kind, cfg);
  if (!device_) throw std::runtime_error("device_bridge: unknown device kind '" + opt_.kind + "'");
  const device::Status s = device_->open();
  if (!s.ok()) throw std::runtime_error(std::string("device_bridge: open failed: ") + s.reason);
  for (auto& t : sent_s_) t.store(-1);
  ch_state_ = bus::channel::device_state(opt_.device, opt_.channel_suffix);
  ch_feedback_ = bus::channel::feedback(opt_.device, opt_.channel_suffix);
  if (opt_.shm) {
    shm_state_ = std::make_unique<bus::ShmWriter>(ch_state_);
    shm_feedback_ = std::make_unique<bus::ShmReader>(ch_feedback_);
  } else {
    bus_.subscribe<lcmt_feedback>(ch_feedback_, [this](const lcmt_feedback& m, const std::string&) {
      fb_box_.write(m);
      on_feedback(m, now_s());
    });
  }
  spdlog::info("device_bridge {}: '{}' at {} Hz over {}", opt_.device, opt_.kind, opt_.rate_hz,
               opt_.shm ? "shared memory" : bus_.url());
}

DeviceBridge::~DeviceBridge() { device_->close(); }

void DeviceBridge::on_feedback(const lcmt_feedback& m, double t) {
  feedbacks_.fetch_add(1, std::memory_order_relaxed);
  feedback_time_s_.store(t, std::memory_order_release);
  if (m.echo_device_seq > last_echo_.load(std::memory_order_relaxed)) {
    last_echo_.store(m.echo_device_seq, std::memory_order_relaxed);
    const double sent = sent_s_[static_cast<size_t>(m.echo_device_seq % kRing)].load(std::memory_order_acquire);
    if (sent >= 0) hist_.add(1e6 * (t - sent));
  }
}

double DeviceBridge::latency_percentile_us(double q) const { return hist_.percentile(q); }
uint64_t DeviceBridge::latency_samples() const { return hist_.count(); }

int DeviceBridge::run(const std::atomic<bool>& stop) {
  const double period = 1.0 / opt_.rate_hz;
  const double t0 = now_s();
  double next = t0, next_mirror = t0;
  device::DeviceReading r;
  lcmt_device_state msg{};
  while (!stop.load(std::memory_order_relaxed)) {
    const double t = now_s();
    if (device_->read(t - t0, r).ok()) {
      device::to_lcmt(r, opt_.device, bus::now_utime(), msg);
      sent_s_[static_cast<size_t>(r.seq % kRing)].store(now_s(), std::memory_order_release);
      if (shm_state_) {
        shm_state_->write_msg(msg);
        if (opt_.mirror_rate_hz > 0 && t >= next_mirror) {
          bus_.publish(ch_state_, msg);
          if (fb_shm_.seq > 0) bus_.publish(ch_feedback_, fb_shm_);
          next_mirror = t + 1.0 / opt_.mirror_rate_hz;
        }
      } else {
        bus_.publish(ch_state_, msg);
      }
      readings_.fetch_add(1, std::memory_order_relaxed);
    }
    // apply the latest feedback (zero when it is older than the timeout)
    Vec3 f = Vec3::Zero();
    if (shm_feedback_) {
      if (shm_feedback_->read_msg(fb_shm_) == bus::ShmRead::kNew) on_feedback(fb_shm_, now_s());
      fb_ = fb_shm_;
    } else if (fb_box_.update()) {
      fb_ = fb_box_.front();
    }
    if (now_s() - feedback_time_s_.load(std::memory_order_acquire) <= opt_.feedback_timeout_s)
      f = clamp_norm(finite_or_zero(Vec3(fb_.force_n[0], fb_.force_n[1], fb_.force_n[2])), opt_.max_force_n);
    device_->write_force(f);
    last_force_n_.store(f.norm(), std::memory_order_relaxed);
    if (f.norm() > max_force_n_.load(std::memory_order_relaxed)) max_force_n_.store(f.norm());
    next += period;
    if (now_s() > next + 0.01) next = now_s();
    if (opt_.busy_poll && shm_feedback_) {
      while (now_s() < next) {
        if (shm_feedback_->read_msg(fb_shm_) == bus::ShmRead::kNew) on_feedback(fb_shm_, now_s());
      }
    } else {
      std::this_thread::sleep_until(kEpoch + std::chrono::duration_cast<Clock::duration>(
                                                 std::chrono::duration<double>(next)));
    }
  }
  device_->write_force(Vec3::Zero());
  return 0;
}

}  // namespace haptree
