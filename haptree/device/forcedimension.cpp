#include "haptree/device/forcedimension.hpp"

#include <cmath>
#include <cstdio>

#include "haptree/device/axes.hpp"
#include "haptree/device/device_info.hpp"
#include "haptree/device/vendor_library.hpp"

namespace haptree::device {

namespace {

// The DHD API as this driver uses it (every function takes the device ID as its last argument, a
// char). Values cross-checked in two independent public sources (docs/devices.md).
namespace dhd {
constexpr unsigned char kOn = 1, kOff = 0;
constexpr int kMotorSaturated = 2;   // dhdSetForce*: forces were saturated (not an error)
constexpr int kDelta3 = 63, kOmega3 = 33, kOmega6Right = 34, kOmega6Left = 36, kOmega7Right = 35,
              kOmega7Left = 37, kSigma7Right = 104, kSigma7Left = 105, kLambda7Right = 108, kLambda7Left = 109,
              kFalcon = 60;
}  // namespace dhd

struct DhdApi {
  int (*dhdOpen)() = nullptr;
  int (*dhdOpenID)(char) = nullptr;
  int (*dhdClose)(char) = nullptr;
  int (*dhdGetPosition)(double*, double*, double*, char) = nullptr;
  int (*dhdGetLinearVelocity)(double*, double*, double*, char) = nullptr;
  int (*dhdGetOrientationFrame)(double[3][3], char) = nullptr;
  int (*dhdSetForce)(double, double, double, char) = nullptr;
  int (*dhdSetForceAndTorque)(double, double, double, double, double, double, char) = nullptr;
  int (*dhdEnableForce)(unsigned char, char) = nullptr;
  int (*dhdGetButton)(int, char) = nullptr;
  int (*dhdGetSystemType)(char) = nullptr;
  const char* (*dhdGetSystemName)(char) = nullptr;
  const char* (*dhdErrorGetLastStr)() = nullptr;
  int (*dhdGetSerialNumber)(unsigned short*, char) = nullptr;   // optional (older SDKs)

  bool bind(VendorLibrary& l) {
    return l.bind(dhdOpen, "dhdOpen") && l.bind(dhdOpenID, "dhdOpenID") && l.bind(dhdClose, "dhdClose") &&
           l.bind(dhdGetPosition, "dhdGetPosition") && l.bind(dhdGetLinearVelocity, "dhdGetLinearVelocity") &&
           l.bind(dhdGetOrientationFrame, "dhdGetOrientationFrame") && l.bind(dhdSetForce, "dhdSetForce") &&
           l.bind(dhdSetForceAndTorque, "dhdSetForceAndTorque") && l.bind(dhdEnableForce, "dhdEnableForce") &&
           l.bind(dhdGetButton, "dhdGetButton") && l.bind(dhdGetSystemType, "dhdGetSystemType") &&
           l.bind(dhdGetSystemName, "dhdGetSystemName") && l.bind(dhdErrorGetLastStr, "dhdErrorGetLastStr") &&
           l.bind(dhdGetSerialNumber, "dhdGetSerialNumber", false);
  }
};

constexpr const char* kInstallHint =
    "install the Force Dimension SDK for Linux (libdrd.so.3 / libdhd.so.3 on the loader path, e.g. /usr/local/lib "
    "then ldconfig; it needs libusb-1.0), or pass --device-option lib=/path/to/libdhd.so.3 (docs/devices.md)";

// The device table entry of a DHD system type ("" if the table has none).
const char* table_name(int type) {
  switch (type) {
    case dhd::kDelta3: return "delta.3";
    case dhd::kOmega3: return "omega.3";
    case dhd::kOmega6Right: case dhd::kOmega6Left: return "omega.6";
    case dhd::kOmega7Right: case dhd::kOmega7Left: return "omega.7";
    case dhd::kSigma7Right: case dhd::kSigma7Left: return "sigma.7";
    case dhd::kLambda7Right: case dhd::kLambda7Left: return "lambda.7";
    case dhd::kFalcon: return "falcon";
    default: return "";
  }
}
bool has_wrist(int type) {
  return type == dhd::kOmega6Right || type == dhd::kOmega6Left || type == dhd::kOmega7Right ||
         type == dhd::kOmega7Left || type == dhd::kSigma7Right || type == dhd::kSigma7Left ||
         type == dhd::kLambda7Right || type == dhd::kLambda7Left;
}
bool has_active_wrist(int type) {
  return type == dhd::kSigma7Right || type == dhd::kSigma7Left || type == dhd::kLambda7Right ||
         type == dhd::kLambda7Left;
}

class ForceDimensionDevice final : public Device {
 public:
  explicit ForceDimensionDevice(const DeviceConfig& c) : spec_(c.spec), axes_(axis_map_option(c, "y,z,x")) {
    const std::string lib = option_string(c, "lib", "");
    libs_ = lib.empty() ? std::vector<std::string>{"libdrd.so.3", "libdhd.so.3"} : std::vector<std::string>{lib};
    const double id = option_double(c, "id", -1);
    if (!(id == -1 || (id >= 0 && id <= 127 && id == std::floor(id))))
      throw std::invalid_argument("device option id=" + option_string(c, "id", "") + ": a device index 0..127");
    want_id_ = static_cast<int>(id);
  }
  ~ForceDimensionDevice() override { close(); }

  const DeviceSpec& spec() const noexcept override { return spec_; }
  DeviceDescription describe() const override { return desc_; }

  Status open() override {
    if (!lib_.open(libs_, kInstallHint) || !api_.bind(lib_)) return fail_open(lib_.error());
    const int id = want_id_ >= 0 ? api_.dhdOpenID(static_cast<char>(want_id_)) : api_.dhdOpen();
    if (id < 0)
      return fail_open(std::string("no Force Dimension device found (") + (want_id_ >= 0 ? "dhdOpenID: " : "dhdOpen: ") +
                       last_error() +
                       "): is it plugged in, powered, and readable by this user (udev rule for USB vendor 0x1451, "
                       "Falcon 0403:cb48)?");
    id_ = static_cast<char>(id);
    opened_ = true;
    register_emergency_stop(this, &ForceDimensionDevice::emergency);
    // Forces off until the first valid FEEDBACK (enable_force), and zero in the meantime.
    if (api_.dhdSetForce(0, 0, 0, id_) < 0 || api_.dhdEnableForce(dhd::kOff, id_) < 0) {
      const std::string why = std::string("dhdEnableForce(off): ") + last_error();
      close();
      return fail_open(why);
    }
    type_ = api_.dhdGetSystemType(id_);
    wrist_ = has_wrist(type_);
    torque_ = has_active_wrist(type_);
    const char* name = api_.dhdGetSystemName(id_);
    desc_.model = name ? name : "";
    if (desc_.model.empty()) desc_.model = "Force Dimension system type " + std::to_string(type_);
    unsigned short sn = 0;
    if (api_.dhdGetSerialNumber && api_.dhdGetSerialNumber(&sn, id_) >= 0 && sn != 0) desc_.serial = std::to_string(sn);
    if (const DeviceInfo* t = find_device_info(table_name(type_))) {
      desc_.max_force_n = t->max_force_n;
      desc_.max_continuous_force_n = t->max_continuous_force_n;
      desc_.max_stiffness_n_per_m = t->max_stiffness_n_per_m;
      desc_.max_damping_n_s_per_m = t->max_damping_n_s_per_m;
      desc_.workspace_radius_m = t->workspace_radius_m;
      desc_.max_torque_nm = t->max_torque_nm;
    }
    if (!torque_) desc_.max_torque_nm = 0;
    desc_.orientation = wrist_;
    desc_.torque = torque_;
    desc_.axes = axes_.str();
    return Status::Ok();
  }

  Status enable_force(bool on) noexcept override {
    if (!opened_) return Status::Error("Force Dimension device not open");
    if (!on) write_zero();
    if (api_.dhdEnableForce(on ? dhd::kOn : dhd::kOff, id_) < 0) return fail("dhdEnableForce");
    enabled_ = on;
    return Status::Ok();
  }

  Status read(double t, DeviceReading& out) noexcept override {
    if (!opened_) return Status::Error("Force Dimension device not open");
    Vec3 x, v;
    if (api_.dhdGetPosition(&x.x(), &x.y(), &x.z(), id_) < 0) return fail("dhdGetPosition");
    if (api_.dhdGetLinearVelocity(&v.x(), &v.y(), &v.z(), id_) < 0) return fail("dhdGetLinearVelocity");
    Mat3 R = Mat3::Identity();
    if (wrist_) {
      double m[3][3];
      if (api_.dhdGetOrientationFrame(m, id_) < 0) return fail("dhdGetOrientationFrame");
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) R(r, c) = m[r][c];
    }
    const int b0 = api_.dhdGetButton(0, id_), b1 = api_.dhdGetButton(1, id_);
    if (b0 < 0 || b1 < 0) return fail("dhdGetButton");
    if (!x.allFinite() || !v.allFinite() || !R.allFinite())
      return Status::Error("Force Dimension: non-finite pose from the device");
    out.time_s = t;
    out.seq = ++seq_;
    out.position_m = axes_.to_frame(x);
    out.linear_velocity_mps = axes_.to_frame(v);
    out.orientation = Quat(axes_.to_frame(R)).normalized();
    out.buttons = (b0 == dhd::kOn ? kButtonGrab : 0) | (b1 == dhd::kOn ? kButtonClutch : 0);
    out.grab_body = 0;
    out.grab_seq = 0;
    return Status::Ok();
  }

  Status write(const Vec3& f, const Vec3& tau) noexcept override {
    if (!f.allFinite() || !tau.allFinite()) return Status::Error("Force Dimension: non-finite force");
    if (!opened_) return Status::Error("Force Dimension device not open");
    Vec3 fv = enabled_ ? axes_.to_vendor(f) : Vec3::Zero();
    if (std::isfinite(desc_.max_force_n) && fv.norm() > desc_.max_force_n) fv *= desc_.max_force_n / fv.norm();
    Vec3 tv = enabled_ && torque_ ? axes_.to_vendor(tau) : Vec3::Zero();
    if (std::isfinite(desc_.max_torque_nm) && tv.norm() > desc_.max_torque_nm)
      tv *= desc_.max_torque_nm / tv.norm();
    const int rc = torque_ ? api_.dhdSetForceAndTorque(fv.x(), fv.y(), fv.z(), tv.x(), tv.y(), tv.z(), id_)
                           : api_.dhdSetForce(fv.x(), fv.y(), fv.z(), id_);
    if (rc < 0) return fail(torque_ ? "dhdSetForceAndTorque" : "dhdSetForce");
    if (rc == dhd::kMotorSaturated) ++saturated_;
    return Status::Ok();
  }

  void close() noexcept override {
    if (!opened_) return;
    opened_ = false;
    enabled_ = false;
    stop_device();
    unregister_emergency_stop(this);
  }

 private:
  // Zero force and torque, force output off, then close: in this order, whatever failed before.
  void stop_device() noexcept {
    write_zero();
    api_.dhdEnableForce(dhd::kOff, id_);
    api_.dhdClose(id_);
  }
  void write_zero() noexcept {
    if (torque_)
      api_.dhdSetForceAndTorque(0, 0, 0, 0, 0, 0, id_);
    else
      api_.dhdSetForce(0, 0, 0, id_);
  }
  static void emergency(void* self) noexcept { static_cast<ForceDimensionDevice*>(self)->stop_device(); }

  const char* last_error() const noexcept {
    const char* s = api_.dhdErrorGetLastStr ? api_.dhdErrorGetLastStr() : nullptr;
    return s && *s ? s : "no reason given";
  }
  Status fail(const char* what) noexcept {
    std::snprintf(err_, sizeof err_, "Force Dimension: %s failed: %s", what, last_error());
    return Status::Error(err_);
  }
  Status fail_open(const std::string& why) {
    open_error_ = "forcedimension: " + why;
    return Status::Error(open_error_.c_str());
  }

  DeviceSpec spec_;
  AxisMap axes_;
  std::vector<std::string> libs_;
  int want_id_ = -1;
  VendorLibrary lib_;
  DhdApi api_;
  DeviceDescription desc_;
  std::string open_error_;
  char id_ = 0;
  int type_ = 0;
  bool opened_ = false, enabled_ = false, wrist_ = false, torque_ = false;
  int64_t seq_ = 0, saturated_ = 0;
  char err_[256] = {};
};

}  // namespace

std::unique_ptr<Device> make_forcedimension_device(const DeviceConfig& config) {
  return std::make_unique<ForceDimensionDevice>(config);
}

}  // namespace haptree::device
