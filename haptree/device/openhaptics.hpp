// 3D Systems Touch / Touch X / Phantom Omni, Desktop, Premium through OpenHaptics' HD API (libHD.so),
// loaded at run time with our own declarations of the few functions used (the SDK headers are under a
// click-through licence and are never needed). The servo loop is the vendor's scheduler: one
// asynchronous callback at ~1 kHz reads the pose and renders the newest command, both through
// lock-free latest-value mailboxes; it never blocks, allocates or logs.
//
// Units and frames: the HD API speaks mm, mm/s, N and mN m; this device speaks m, m/s, N and N m.
// The HD frame (x right, y up, z towards the user) is haptree's: default axes=x,y,z.
// Options: lib (default libHD.so, then libHD.so.3.4.0), name (device name from Touch_Setup; default
// device), axes. Fail-safe: forces are rendered only while enabled and while the newest command is at
// most 50 servo ticks old; an HD error latches the device to zero force and read() reports it, as it
// reports a servo loop that stopped (no new sample for 250 ms).
#pragma once

#include <memory>

#include "haptree/device/registry.hpp"

namespace haptree::device {

std::unique_ptr<Device> make_openhaptics_device(const DeviceConfig& config);

}  // namespace haptree::device
