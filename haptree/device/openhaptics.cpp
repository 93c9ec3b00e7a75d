#include "haptree/device/openhaptics.hpp"

#include <time.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <thread>

#include "haptree/bus/latest_value.hpp"
#include "haptree/device/axes.hpp"
#include "haptree/device/device_info.hpp"
#include "haptree/device/vendor_library.hpp"

namespace haptree::device {

namespace {

// The HD API as this driver uses it. Types and values cross-checked in two independent public
// sources (docs/devices.md, "Where the vendor constants come from").
namespace hd {
using HHD = unsigned int;
using HDenum = unsigned int;
using HDerror = unsigned int;
using HDCallbackCode = unsigned int;
using HDSchedulerHandle = unsigned long;
using HDushort = unsigned short;
struct HDErrorInfo {   // returned by value by hdGetError()
  HDerror errorCode;
  int internalErrorCode;
  HHD hHD;
};
using HDSchedulerCallback = HDCallbackCode (*)(void*);

constexpr HHD kInvalidHandle = 0xFFFFFFFFu;
constexpr HDerror kSuccess = 0x0000;
constexpr HDCallbackCode kCallbackDone = 0, kCallbackContinue = 1;
constexpr HDushort kDefaultSchedulerPriority = 0x7FFF;   // (max 0xFFFF + min 0) / 2
constexpr HDenum kCurrentButtons = 0x2000;
constexpr HDenum kCurrentVelocity = 0x2051;              // mm/s
constexpr HDenum kCurrentTransform = 0x2052;             // 16 doubles, column-major, translation (mm) at 12..14
constexpr HDenum kDeviceModelType = 0x2501;
constexpr HDenum kDeviceSerialNumber = 0x2504;
constexpr HDenum kUsableWorkspaceDimensions = 0x2551;    // minx, miny, minz, maxx, maxy, maxz (mm)
constexpr HDenum kOutputDof = 0x2554;
constexpr HDenum kCalibrationStyle = 0x2555;
constexpr HDenum kNominalMaxStiffness = 0x2602;          // N/mm
constexpr HDenum kNominalMaxForce = 0x2603;              // N
constexpr HDenum kNominalMaxContinuousForce = 0x2604;    // N
constexpr HDenum kNominalMaxDamping = 0x2609;            // N s/mm
constexpr HDenum kCurrentForce = 0x2700;                 // N
constexpr HDenum kCurrentTorque = 0x2701;                // mN m
constexpr HDenum kForceOutput = 0x4000;
constexpr HDenum kCalibrationOk = 0x5000, kCalibrationNeedsUpdate = 0x5001, kCalibrationNeedsManualInput = 0x5002;
constexpr int kCalibrationAuto = 1 << 1;   // styles: encoder reset 1 << 0, auto 1 << 1, inkwell 1 << 2
}  // namespace hd

struct HdApi {
  hd::HHD (*hdInitDevice)(const char*) = nullptr;
  void (*hdDisableDevice)(hd::HHD) = nullptr;
  void (*hdMakeCurrentDevice)(hd::HHD) = nullptr;
  void (*hdBeginFrame)(hd::HHD) = nullptr;
  void (*hdEndFrame)(hd::HHD) = nullptr;
  void (*hdEnable)(hd::HDenum) = nullptr;
  void (*hdDisable)(hd::HDenum) = nullptr;
  void (*hdGetDoublev)(hd::HDenum, double*) = nullptr;
  void (*hdGetIntegerv)(hd::HDenum, int*) = nullptr;
  void (*hdSetDoublev)(hd::HDenum, const double*) = nullptr;
  const char* (*hdGetString)(hd::HDenum) = nullptr;
  hd::HDErrorInfo (*hdGetError)() = nullptr;
  const char* (*hdGetErrorString)(hd::HDerror) = nullptr;
  void (*hdStartScheduler)() = nullptr;
  void (*hdStopScheduler)() = nullptr;
  hd::HDSchedulerHandle (*hdScheduleAsynchronous)(hd::HDSchedulerCallback, void*, hd::HDushort) = nullptr;
  void (*hdUnschedule)(hd::HDSchedulerHandle) = nullptr;
  hd::HDenum (*hdCheckCalibration)() = nullptr;
  void (*hdUpdateCalibration)(hd::HDenum) = nullptr;

  bool bind(VendorLibrary& l) {
    return l.bind(hdInitDevice, "hdInitDevice") && l.bind(hdDisableDevice, "hdDisableDevice") &&
           l.bind(hdMakeCurrentDevice, "hdMakeCurrentDevice") && l.bind(hdBeginFrame, "hdBeginFrame") &&
           l.bind(hdEndFrame, "hdEndFrame") && l.bind(hdEnable, "hdEnable") && l.bind(hdDisable, "hdDisable") &&
           l.bind(hdGetDoublev, "hdGetDoublev") && l.bind(hdGetIntegerv, "hdGetIntegerv") &&
           l.bind(hdSetDoublev, "hdSetDoublev") && l.bind(hdGetString, "hdGetString") &&
           l.bind(hdGetError, "hdGetError") && l.bind(hdGetErrorString, "hdGetErrorString") &&
           l.bind(hdStartScheduler, "hdStartScheduler") && l.bind(hdStopScheduler, "hdStopScheduler") &&
           l.bind(hdScheduleAsynchronous, "hdScheduleAsynchronous") && l.bind(hdUnschedule, "hdUnschedule") &&
           l.bind(hdCheckCalibration, "hdCheckCalibration") && l.bind(hdUpdateCalibration, "hdUpdateCalibration");
  }
};

constexpr const char* kInstallHint =
    "install 3D Systems' OpenHaptics runtime and the Touch device driver for Linux (libHD.so on the loader path, "
    "GTDD_HOME set for the Touch), or pass --device-option lib=/path/to/libHD.so (docs/devices.md)";

// Servo ticks (~1 ms) after which a command not refreshed by the device loop is replaced by zero force.
constexpr uint64_t kStaleTicks = 50;
// No new servo sample for this long (device clock): the vendor's servo loop stopped. Long against the
// 1 ms servo period so that a loaded host's scheduling hiccup is not a fault; the servo loop itself
// zeroes a command older than kStaleTicks long before.
constexpr double kStalledS = 0.25;

struct Sample {
  uint64_t tick = 0;
  double transform[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  double velocity[3] = {0, 0, 0};
  int buttons = 0;
  hd::HDerror error = hd::kSuccess;   // latched: the first HD error seen by the servo loop
  int internal_error = 0;
  hd::HDenum calibration = hd::kCalibrationOk;
  bool force_on = false;
};

struct Command {
  double force[3] = {0, 0, 0};    // N, vendor axes
  double torque[3] = {0, 0, 0};   // N m, vendor axes
  bool enabled = false;
  uint64_t tick = 0;              // the servo tick of the sample the command answers
};

void sleep_ms(double ms) noexcept {
  timespec ts{0, static_cast<long>(ms * 1e6)};
  nanosleep(&ts, nullptr);   // async-signal-safe (the emergency stop uses it)
}

class OpenHapticsDevice final : public Device {
 public:
  explicit OpenHapticsDevice(const DeviceConfig& c)
      : spec_(c.spec), axes_(axis_map_option(c, "x,y,z")), name_(option_string(c, "name", "")) {
    const std::string lib = option_string(c, "lib", "");
    libs_ = lib.empty() ? std::vector<std::string>{"libHD.so", "libHD.so.3.4.0"} : std::vector<std::string>{lib};
  }
  ~OpenHapticsDevice() override { close(); }

  const DeviceSpec& spec() const noexcept override { return spec_; }
  DeviceDescription describe() const override { return desc_; }

  Status open() override {
    if (!lib_.open(libs_, kInstallHint) || !api_.bind(lib_)) return fail_open(lib_.error());
    const hd::HHD h = api_.hdInitDevice(name_.empty() ? nullptr : name_.c_str());
    const hd::HDErrorInfo e = api_.hdGetError();
    if (e.errorCode != hd::kSuccess || h == hd::kInvalidHandle)
      return fail_open("no OpenHaptics device '" + (name_.empty() ? std::string("default") : name_) +
                       "' (hdInitDevice: " + error_text(e) +
                       "): is it plugged in, and set up with Touch_Setup (GTDD_HOME)?");
    handle_ = h;
    api_.hdMakeCurrentDevice(h);
    api_.hdDisable(hd::kForceOutput);   // off until the first valid FEEDBACK (enable_force)
    describe_device();
    api_.hdGetError();                  // a query the device does not support is not a fault
    sched_ = api_.hdScheduleAsynchronous(&OpenHapticsDevice::servo_callback, this, hd::kDefaultSchedulerPriority);
    api_.hdStartScheduler();
    const hd::HDErrorInfo es = api_.hdGetError();
    if (es.errorCode != hd::kSuccess) {
      api_.hdDisableDevice(h);
      handle_ = hd::kInvalidHandle;
      return fail_open("hdStartScheduler: " + error_text(es));
    }
    opened_ = true;
    register_emergency_stop(this, &OpenHapticsDevice::emergency);
    for (int i = 0; i < 1000 && ticks_.load(std::memory_order_acquire) == 0; ++i) sleep_ms(1);
    if (ticks_.load(std::memory_order_acquire) == 0) {
      close();
      return fail_open("the OpenHaptics servo loop never ran (no scheduler tick within 1 s)");
    }
    return Status::Ok();
  }

  Status enable_force(bool on) noexcept override {
    if (!opened_) return Status::Error("OpenHaptics device not open");
    if (on && samples_.front().calibration == hd::kCalibrationNeedsManualInput)
      return Status::Error("OpenHaptics device needs calibration by hand (put the stylus in its inkwell or "
                           "reset position); forces stay off");
    enabled_ = on;
    publish_command(Vec3::Zero(), Vec3::Zero());
    return Status::Ok();
  }

  Status read(double t, DeviceReading& out) noexcept override {
    if (!opened_) return Status::Error("OpenHaptics device not open");
    if (samples_.update() || last_new_s_ < 0) last_new_s_ = t;
    const Sample& s = samples_.front();
    if (s.error != hd::kSuccess) {
      std::snprintf(err_, sizeof err_, "OpenHaptics error 0x%04x (%s), internal code %d", s.error,
                    safe(api_.hdGetErrorString(s.error)), s.internal_error);
      return Status::Error(err_);
    }
    if (s.tick == 0) return Status::Error("OpenHaptics: no servo sample yet");
    if (t - last_new_s_ > kStalledS) return Status::Error("OpenHaptics servo loop stopped: no new sample for 250 ms");
    Mat3 R;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) R(r, c) = s.transform[c * 4 + r];   // column-major
    const Vec3 x = 1e-3 * Vec3(s.transform[12], s.transform[13], s.transform[14]);
    const Vec3 v = 1e-3 * Vec3(s.velocity[0], s.velocity[1], s.velocity[2]);
    if (!x.allFinite() || !v.allFinite() || !R.allFinite())
      return Status::Error("OpenHaptics: non-finite pose from the device");
    out.time_s = t;
    out.seq = ++seq_;
    out.position_m = axes_.to_frame(x);
    out.linear_velocity_mps = axes_.to_frame(v);
    Quat q(axes_.to_frame(R));
    out.orientation = q.normalized();
    out.buttons = s.buttons & (kButtonGrab | kButtonClutch);   // HD_DEVICE_BUTTON_1, _2
    out.grab_body = 0;
    out.grab_seq = 0;
    last_tick_ = s.tick;
    return Status::Ok();
  }

  Status write(const Vec3& f, const Vec3& tau) noexcept override {
    if (!f.allFinite() || !tau.allFinite()) return Status::Error("OpenHaptics: non-finite force");
    if (!opened_) return Status::Error("OpenHaptics device not open");
    Vec3 fv = axes_.to_vendor(f), tv = torque_ ? axes_.to_vendor(tau) : Vec3::Zero();
    if (std::isfinite(desc_.max_force_n) && fv.norm() > desc_.max_force_n) fv *= desc_.max_force_n / fv.norm();
    publish_command(fv, tv);
    return Status::Ok();
  }

  void close() noexcept override {
    if (!opened_) return;
    opened_ = false;
    enabled_ = false;
    publish_command(Vec3::Zero(), Vec3::Zero());
    // Let the servo loop render the zero command (two ticks), unless it is dead.
    const uint64_t t0 = ticks_.load(std::memory_order_acquire);
    for (int i = 0; i < 50 && ticks_.load(std::memory_order_acquire) < t0 + 2; ++i) sleep_ms(1);
    stop_.store(true, std::memory_order_release);
    api_.hdStopScheduler();
    api_.hdUnschedule(sched_);
    // The last word from this thread, whatever the servo loop did: zero force and torque, force off.
    zero_frame();
    api_.hdDisableDevice(handle_);
    api_.hdGetError();
    unregister_emergency_stop(this);
    handle_ = hd::kInvalidHandle;
  }

 private:
  static hd::HDCallbackCode servo_callback(void* self) noexcept {
    return static_cast<OpenHapticsDevice*>(self)->servo();
  }

  // The vendor's servo thread: no lock, no allocation, no logging.
  hd::HDCallbackCode servo() noexcept {
    Sample& s = samples_.back();
    api_.hdBeginFrame(handle_);
    api_.hdGetDoublev(hd::kCurrentTransform, s.transform);
    api_.hdGetDoublev(hd::kCurrentVelocity, s.velocity);
    api_.hdGetIntegerv(hd::kCurrentButtons, &s.buttons);
    const uint64_t tick = ticks_.load(std::memory_order_relaxed) + 1;
    if (calibration_ != hd::kCalibrationOk && tick % 100 == 1) {
      calibration_ = api_.hdCheckCalibration();
      if (calibration_ == hd::kCalibrationNeedsUpdate && (calibration_style_ & hd::kCalibrationAuto)) {
        api_.hdUpdateCalibration(hd::kCalibrationAuto);
        calibration_ = api_.hdCheckCalibration();
      }
    }
    commands_.update();
    const Command& c = commands_.front();
    const bool on = c.enabled && !emergency_.load(std::memory_order_acquire) && fault_ == hd::kSuccess;
    if (on != force_on_) {
      on ? api_.hdEnable(hd::kForceOutput) : api_.hdDisable(hd::kForceOutput);
      force_on_ = on;
    }
    const bool fresh = on && tick - c.tick <= kStaleTicks;
    double f[3] = {0, 0, 0}, t[3] = {0, 0, 0};
    if (fresh)
      for (int i = 0; i < 3; ++i) f[i] = c.force[i], t[i] = 1e3 * c.torque[i];   // N m -> mN m
    api_.hdSetDoublev(hd::kCurrentForce, f);
    if (torque_) api_.hdSetDoublev(hd::kCurrentTorque, t);
    api_.hdEndFrame(handle_);
    const hd::HDErrorInfo e = api_.hdGetError();
    if (e.errorCode != hd::kSuccess && fault_ == hd::kSuccess) {
      fault_ = e.errorCode;   // latched: from the next tick on, zero force and force output off
      fault_internal_ = e.internalErrorCode;
    }
    s.error = fault_;
    s.internal_error = fault_internal_;
    s.calibration = calibration_;
    s.force_on = force_on_;
    s.tick = tick;
    samples_.publish();
    ticks_.store(tick, std::memory_order_release);
    return stop_.load(std::memory_order_acquire) ? hd::kCallbackDone : hd::kCallbackContinue;
  }

  // From a fatal signal: the servo loop sees the flag and writes zero with force output off on its next
  // tick; then (the servo loop may be the thread that crashed) a zero frame from here.
  static void emergency(void* self) noexcept {
    auto* d = static_cast<OpenHapticsDevice*>(self);
    d->emergency_.store(true, std::memory_order_release);
    sleep_ms(3);
    d->zero_frame();
  }

  void zero_frame() noexcept {
    const double zero[3] = {0, 0, 0};
    api_.hdMakeCurrentDevice(handle_);
    api_.hdBeginFrame(handle_);
    api_.hdSetDoublev(hd::kCurrentForce, zero);
    if (torque_) api_.hdSetDoublev(hd::kCurrentTorque, zero);
    api_.hdEndFrame(handle_);
    api_.hdDisable(hd::kForceOutput);
  }

  void publish_command(const Vec3& f, const Vec3& t) noexcept {
    Command& c = commands_.back();
    for (int i = 0; i < 3; ++i) c.force[i] = enabled_ ? f[i] : 0.0, c.torque[i] = enabled_ ? t[i] : 0.0;
    c.enabled = enabled_;
    c.tick = last_tick_;
    commands_.publish();
  }

  void describe_device() {
    desc_.model = safe(api_.hdGetString(hd::kDeviceModelType));
    desc_.serial = safe(api_.hdGetString(hd::kDeviceSerialNumber));
    auto get = [&](hd::HDenum what, double scale) {
      double v = std::numeric_limits<double>::quiet_NaN();
      api_.hdGetDoublev(what, &v);
      const hd::HDErrorInfo e = api_.hdGetError();
      return e.errorCode == hd::kSuccess && std::isfinite(v) && v > 0 ? v * scale : DeviceDescription::kNotReported;
    };
    desc_.max_force_n = get(hd::kNominalMaxForce, 1.0);
    desc_.max_continuous_force_n = get(hd::kNominalMaxContinuousForce, 1.0);
    desc_.max_stiffness_n_per_m = get(hd::kNominalMaxStiffness, 1e3);   // N/mm -> N/m
    desc_.max_damping_n_s_per_m = get(hd::kNominalMaxDamping, 1e3);     // N s/mm -> N s/m
    double ws[6] = {0, 0, 0, 0, 0, 0};
    api_.hdGetDoublev(hd::kUsableWorkspaceDimensions, ws);
    if (api_.hdGetError().errorCode == hd::kSuccess) {
      const double r = 0.5e-3 * std::min({ws[3] - ws[0], ws[4] - ws[1], ws[5] - ws[2]});
      if (std::isfinite(r) && r > 0) desc_.workspace_radius_m = r;
    }
    int dof = 3;
    api_.hdGetIntegerv(hd::kOutputDof, &dof);
    if (api_.hdGetError().errorCode != hd::kSuccess) dof = 3;
    torque_ = dof >= 6;
    desc_.torque = torque_;
    // The HD API reports no torque limit: a 6-DOF device takes the device table's PHANTOM Premium 6DOF value.
    const DeviceInfo* premium6 = find_device_info("phantom_premium_1.5_6dof");
    desc_.max_torque_nm = torque_ ? (premium6 ? premium6->max_torque_nm : DeviceDescription::kNotReported) : 0.0;
    desc_.orientation = true;   // HD_CURRENT_TRANSFORM: the stylus gimbal (measured on every HD device)
    desc_.axes = axes_.str();
    calibration_style_ = 0;
    api_.hdGetIntegerv(hd::kCalibrationStyle, &calibration_style_);
    // The servo loop checks the calibration on its first tick (and every 100 ticks until it is good):
    // hdCheckCalibration / hdUpdateCalibration belong in the scheduler's thread.
    calibration_ = hd::kCalibrationNeedsUpdate;
  }

  std::string error_text(const hd::HDErrorInfo& e) const {
    char buf[160];
    std::snprintf(buf, sizeof buf, "error 0x%04x %s, internal code %d", e.errorCode,
                  safe(api_.hdGetErrorString(e.errorCode)), e.internalErrorCode);
    return buf;
  }
  static const char* safe(const char* s) noexcept { return s ? s : ""; }

  Status fail_open(const std::string& why) {
    open_error_ = "openhaptics: " + why;
    return Status::Error(open_error_.c_str());
  }

  DeviceSpec spec_;
  AxisMap axes_;
  std::string name_;
  std::vector<std::string> libs_;
  VendorLibrary lib_;
  HdApi api_;
  DeviceDescription desc_;
  std::string open_error_;
  hd::HHD handle_ = hd::kInvalidHandle;
  hd::HDSchedulerHandle sched_ = 0;
  bool opened_ = false, enabled_ = false, torque_ = false;
  int64_t seq_ = 0;
  uint64_t last_tick_ = 0;
  double last_new_s_ = -1;
  char err_[256] = {};
  // Shared with the servo thread: mailboxes and atomics only.
  bus::LatestValue<Sample> samples_;
  bus::LatestValue<Command> commands_;
  std::atomic<uint64_t> ticks_{0};
  std::atomic<bool> stop_{false}, emergency_{false};
  // Servo thread only (after open).
  bool force_on_ = false;
  hd::HDerror fault_ = hd::kSuccess;
  int fault_internal_ = 0;
  hd::HDenum calibration_ = hd::kCalibrationNeedsUpdate;
  int calibration_style_ = 0;
};

}  // namespace

std::unique_ptr<Device> make_openhaptics_device(const DeviceConfig& config) {
  return std::make_unique<OpenHapticsDevice>(config);
}

}  // namespace haptree::device
