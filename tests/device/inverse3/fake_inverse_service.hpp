// A fake Haply Inverse Service for the tests: a WebSocket server on 127.0.0.1 (ephemeral port) that
// speaks the service's JSON as Haply documents it. On connect: one inventory message (config, state,
// status of one Inverse3 and optionally one Verse Grip); then exactly one state message per message
// received. The Inverse3 is a simulated mechanism: a point mass on a spring to a rest point, damped,
// driven by the commanded cursor force, integrated over the wall time between commands. Every force
// command received is logged. Grip buttons follow a schedule. Faults can be injected.
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "haptree/spatial.hpp"

namespace haptree::testing {

// Buttons held from from_s to to_s (seconds since the connection opened): bit 0 = a, 1 = b, 2 = c
// (a wired grip has one button: bit 0).
struct FakeButtons {
  double from_s = 0, to_s = 0;
  int mask = 0;
};

enum class FakeFault {
  kNone,
  kStopReplying,   // keeps reading (and logging) commands, never answers again
  kClose,          // closes the connection
  kMalformed,      // answers with text that is not JSON
};

struct FakeInverseOptions {
  std::string device_id = "049D";
  std::string grip_id = "61548";      // "": no grip
  bool wireless_grip = true;          // wireless_verse_grip (buttons a, b, c) or verse_grip (button)
  bool no_inverse3 = false;           // an inventory without any Inverse3
  Vec3 rest_m = Vec3(0.02, -0.12, 0.15);   // device frame (+x right, +y forward, +z up)
  double mass_kg = 0.1, stiffness_n_per_m = 200, damping_n_s_per_m = 8;
  Quat grip_orientation = Quat::Identity();
  std::vector<FakeButtons> buttons;
  FakeFault fault = FakeFault::kNone;
  double fault_after_s = 0;           // seconds since the connection opened
  bool old_dialect = false;           // reads set_cursor_force.values only (an older service)
};

struct ForceRecord {
  double t_s = 0;           // since the connection opened
  Vec3 force_n = Vec3::Zero();
  bool applied = false;     // false: the command's force field was not one this service reads
  int connection = 0;       // 1, 2, ... (one per WebSocket connection)
};

class FakeInverseService {
 public:
  explicit FakeInverseService(const FakeInverseOptions& o = {});   // listening when it returns
  ~FakeInverseService();
  FakeInverseService(const FakeInverseService&) = delete;
  FakeInverseService& operator=(const FakeInverseService&) = delete;

  int port() const noexcept { return port_; }
  std::string url() const { return "ws://127.0.0.1:" + std::to_string(port_); }
  std::vector<ForceRecord> forces() const;
  int64_t messages() const noexcept { return messages_.load(); }       // commands received
  int64_t connections() const noexcept { return connections_.load(); }
  int64_t open_connections() const noexcept { return open_.load(); }
  Vec3 position() const;    // device frame
  void stop();              // idempotent

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
  int port_ = 0;
  std::atomic<int64_t> messages_{0}, connections_{0}, open_{0};
  friend struct Impl;
};

}  // namespace haptree::testing
