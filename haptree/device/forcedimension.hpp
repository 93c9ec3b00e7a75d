// Force Dimension omega.x, delta.x, sigma.7, lambda.7 and the Novint Falcon through the DHD API
// (libdrd.so.3, which also exports every dhd* function, else libdhd.so.3), loaded at run time with our
// own extern "C" declarations (the SDK header uses C++ default arguments). The DHD calls are made from
// the device loop itself (read() and write()), as the SDK intends; no vendor thread.
//
// Units and frames: the DHD API speaks m, m/s, N, N m. Its frame (x towards the user, y right, z up)
// becomes haptree's (x right, y up, z towards the user) with the default axes=y,z,x.
// Options: lib (default libdrd.so.3, then libdhd.so.3), id (device index for dhdOpenID; default the
// first device, dhdOpen), axes. Torque is written on devices with an actuated wrist (sigma.7,
// lambda.7); orientation is read on devices with a wrist. Limits come from the device table entry of the
// system type the device reports (dhdGetSystemType).
#pragma once

#include <memory>

#include "haptree/device/registry.hpp"

namespace haptree::device {

std::unique_ptr<Device> make_forcedimension_device(const DeviceConfig& config);

}  // namespace haptree::device
