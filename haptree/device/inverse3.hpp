// Haply Inverse3 through the Haply "Inverse Service": JSON over a local WebSocket (default
// ws://127.0.0.1:10001). No vendor library is linked or loaded; the service is the driver.
//
// Protocol (Haply's public Inverse SDK documentation, docs/devices.md lists the pages): on connect the
// service sends one inventory message (every device's config, state and status); after that it sends
// exactly one state message per message it receives, so the client's send rate sets the cadence. A
// `set_cursor_force` command is valid for one tick: a force (even zero) goes out every tick or the
// device idles and the state stops flowing. Device frame: right-handed, +x right, +y forward (away
// from the user), +z up, metres and newtons.
//
// Threads: the WebSocket and the JSON live on this device's own I/O thread, paced at rate_hz with one
// command in flight. read()/write() (the haptic loop) only swap lock-free latest-value mailboxes and
// atomics: no allocation, no lock, no logging. A closed socket, a reply missing for timeout_s, or no
// valid state for timeout_s makes read() and write() fail, so the bridge's fail-safe takes over; the
// I/O thread's last command on a live socket is a zero force (on a lost link and on close()).
#pragma once

#include <atomic>
#include <memory>
#include <string>
#include <thread>

#include "haptree/bus/latest_value.hpp"
#include "haptree/device/axes.hpp"
#include "haptree/device/device.hpp"

namespace haptree::device {

struct Inverse3Params {
  std::string url = "ws://127.0.0.1:10001";
  std::string device_id;            // empty: the first Inverse3 the service reports
  std::string grip_id;              // empty: the first wireless Verse Grip, else the first wired one
  // haptree's axes from Haply's (AxisMap): for haptree's x, y, z, the Haply axis (signed) it reads.
  // Default "x,z,-y": x = Haply x (right), y = Haply z (up), z = -Haply y (towards the user).
  std::string axes = "x,z,-y";
  Vec3 origin_m = Vec3::Zero();     // device point (device axes, m) that becomes the view's origin
  double rate_hz = 1000;            // commands per second (the service answers each one)
  double timeout_s = 0.1;           // no reply / no valid state for this long: link lost
  double connect_timeout_s = 2.0;   // connection + inventory at open()
  std::string force_key = "vector"; // set_cursor_force field written: "vector" (3.1+) or "values" (older)
  double max_abs_m = 1.0;           // a cursor position farther than this (device frame) is refused
};

// What the I/O thread hands the haptic loop: the newest valid state, already in view axes.
struct Inverse3Sample {
  Vec3 position_m = Vec3::Zero();
  Vec3 velocity_mps = Vec3::Zero();
  Quat orientation = Quat::Identity();
  int32_t buttons = 0;
  double received_s = -1;           // steady clock (seconds) when it arrived
};

// What the haptic loop hands the I/O thread.
struct Inverse3Command {
  Vec3 force_n = Vec3::Zero();      // view axes
};

class Inverse3Device final : public Device {
 public:
  Inverse3Device(const DeviceSpec& spec, const Inverse3Params& p);
  ~Inverse3Device() override;
  const DeviceSpec& spec() const noexcept override { return spec_; }
  // Connects, reads the inventory, picks the device and starts the I/O thread (force output off: zero
  // force every tick). A failure says what is wrong in one line (service not running, no Inverse3,
  // unknown device_id).
  Status open() override;
  // Model and serial (the service's device_id), buttons and orientation of the grip; the service
  // reports no force, stiffness or damping limits (NaN: the --device-model table is the fallback).
  DeviceDescription describe() const override;
  // Off: the I/O thread sends a zero force each tick whatever write() says.
  Status enable_force(bool on) noexcept override;
  Status read(double time_s, DeviceReading& out) noexcept override;
  Status write(const Vec3& force_n, const Vec3& torque_nm) noexcept override;
  // Sends a zero force as the last command, closes the WebSocket and joins the I/O thread. Idempotent.
  void close() noexcept override;

  // From the inventory (valid after open()).
  const std::string& device_id() const noexcept { return device_id_; }
  const std::string& grip_id() const noexcept { return grip_id_; }
  const std::string& description() const noexcept { return description_; }   // model, version, ids
  int64_t replies() const noexcept { return replies_.load(std::memory_order_relaxed); }
  int64_t malformed() const noexcept { return malformed_.load(std::memory_order_relaxed); }

  struct Io;   // the I/O side (WebSocket client, JSON), defined in inverse3.cpp

 private:
  DeviceSpec spec_;
  Inverse3Params p_;
  Mat3 axes_;                       // view <- device
  std::string device_id_, grip_id_, model_, description_, open_error_;
  std::unique_ptr<Io> io_;
  std::thread thread_;
  bus::LatestValue<Inverse3Sample> state_box_;      // I/O thread -> read()
  bus::LatestValue<Inverse3Command> command_box_;   // write() -> I/O thread
  std::atomic<int> link_{0};        // LinkState in inverse3.cpp
  std::atomic<bool> force_on_{false};
  int grip_buttons_ = 0;            // 3 wireless (a, b, c), 1 wired, 0 no grip
  std::atomic<int64_t> replies_{0}, malformed_{0};
  int64_t seq_ = 0;
  bool closed_ = false;
  friend struct Io;
};

}  // namespace haptree::device
